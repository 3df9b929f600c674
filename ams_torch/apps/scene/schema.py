"""Scene files: reading and validating the TOML (every key checked; errors name the file and key).

See :mod:`ams_torch.apps.scene` for the format.
"""
from __future__ import annotations

import copy
import dataclasses
import math
import os
import tomllib
from typing import Optional

from ams_torch.apps.motion import make_motion
from ams_torch.sim.params import Params
from ams_torch.stages.wind import Wind

__all__ = ["SceneError", "read_toml", "load_scene", "parse_scene", "make_params", "make_collider", "SCENE_DIR"]

SCENE_DIR = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))),
                         "datasets", "scenes")


class SceneError(ValueError):
    """A scene file is invalid; the message names the file and the key."""


_TOP = {"name", "description", "frames", "dt", "substeps", "scale", "head", "groom", "params", "stages",
        "hair_hair", "motion", "wind", "colliders", "trim", "render"}
_HEAD = {"mesh", "subdivisions", "radius", "collide", "sdf_resolution"}
_GROOM = {"preset", "file", "kind", "strands", "particles", "seed", "length", "radius", "spread", "growth",
          "compare_ms", "compare_offset"}
_STAGES = {"hair_hair", "collisions", "nonhookean"}
_TRIM = {"frame", "point", "normal"}
_RENDER = {"view", "fps", "size", "every"}
_COLLIDERS = {"sphere": ("SphereCollider", {"center", "radius"}),
              "capsule": ("CapsuleCollider", {"a", "b", "radius"}),
              "plane": ("PlaneCollider", {"point", "normal"}),
              "hollow_sphere": ("HollowSphereCollider", {"center", "radius", "thickness", "cut_height", "axis"})}
_GROOM_KINDS = ("sphere", "strand", "wisp")


def _fail(where: str, msg: str):
    raise SceneError(f"{where}: {msg}")


def _check_keys(d: dict, allowed: set, where: str, section: str):
    if not isinstance(d, dict):
        _fail(where, f"[{section}] must be a table; got {type(d).__name__}")
    unknown = sorted(set(d) - allowed)
    if unknown:
        _fail(where, f"unknown key(s) {unknown} in [{section}]; allowed: {sorted(allowed)}")


def _num(v, key: str, where: str, *, integer=False, positive=False, nonneg=False):
    ok = isinstance(v, int) if integer else isinstance(v, (int, float))
    if isinstance(v, bool) or not ok or not math.isfinite(float(v)):
        _fail(where, f"{key} must be {'an integer' if integer else 'a number'}; got {v!r}")
    if positive and not v > 0:
        _fail(where, f"{key} must be positive; got {v!r}")
    if nonneg and not v >= 0:
        _fail(where, f"{key} must be non-negative; got {v!r}")
    return v


def _vec3(v, key: str, where: str):
    if not (isinstance(v, (list, tuple)) and len(v) == 3 and all(
            isinstance(c, (int, float)) and not isinstance(c, bool) and math.isfinite(c) for c in v)):
        _fail(where, f"{key} must be a list of three numbers; got {v!r}")
    return [float(c) for c in v]


def _bool(v, key: str, where: str):
    if not isinstance(v, bool):
        _fail(where, f"{key} must be true or false; got {v!r}")
    return v


def _path(v, key: str, where: str, base: str):
    if not isinstance(v, str):
        _fail(where, f"{key} must be a file path string; got {v!r}")
    p = v if os.path.isabs(v) else os.path.join(base, v)
    if not os.path.isfile(p):
        _fail(where, f"{key}: no such file {v!r} (looked for {p})")
    return p


def read_toml(path: str, kind: str, error=None, overrides: Optional[dict] = None) -> dict:
    """Read a TOML file as a dict with ``name`` defaulting to the file stem and ``overrides``
    replacing top-level keys; a missing file or bad TOML raises ``error`` (default
    :class:`SceneError`) naming the file."""
    error = error or SceneError
    if not os.path.isfile(path):
        raise error(f"{path}: no such {kind} file")
    with open(path, "rb") as f:
        try:
            raw = tomllib.load(f)
        except tomllib.TOMLDecodeError as err:
            raise error(f"{path}: not valid TOML: {err}") from None
    raw.setdefault("name", os.path.splitext(os.path.basename(path))[0])
    raw.update(overrides or {})
    return raw


def load_scene(path: str, overrides: Optional[dict] = None) -> dict:
    """Read and validate a scene TOML file. ``overrides``: top-level keys replacing the file's
    (e.g. ``{"frames": 3, "scale": 0.1}``). Returns the validated scene dict (paths resolved)."""
    raw = read_toml(path, "scene", SceneError, overrides)
    return parse_scene(raw, where=path, base=os.path.dirname(os.path.abspath(path)))


def parse_scene(raw: dict, where: str = "scene", base: str = ".") -> dict:
    """Validate a scene dict (as read from TOML); returns a normalised deep copy.
    Raises :class:`SceneError` naming the key on any problem."""
    s = copy.deepcopy(raw)
    _check_keys(s, _TOP, where, "top level")
    s.setdefault("name", "scene")
    if not isinstance(s["name"], str):
        _fail(where, f"name must be a string; got {s['name']!r}")
    s["frames"] = _num(s.get("frames", 60), "frames", where, integer=True, positive=True)
    s["scale"] = _num(s.get("scale", 1.0), "scale", where, positive=True)
    if "dt" in s:
        _num(s["dt"], "dt", where, positive=True)
    if "substeps" in s:
        _num(s["substeps"], "substeps", where, integer=True, positive=True)

    head = s.setdefault("head", {})
    _check_keys(head, _HEAD, where, "head")
    mesh = head.setdefault("mesh", "default")
    if not isinstance(mesh, str):
        _fail(where, f"[head].mesh must be 'default', 'sphere', 'none' or a file path; got {mesh!r}")
    if mesh not in ("default", "sphere", "none"):
        head["mesh"] = _path(mesh, "[head].mesh", where, base)
    head["subdivisions"] = _num(head.get("subdivisions", 4), "[head].subdivisions", where, integer=True, positive=True)
    head["radius"] = _num(head.get("radius", 0.1), "[head].radius", where, positive=True)
    head["sdf_resolution"] = _num(head.get("sdf_resolution", 64), "[head].sdf_resolution", where, integer=True,
                                  positive=True)
    head["collide"] = _bool(head.get("collide", mesh != "none"), "[head].collide", where)

    groom = s.setdefault("groom", {"kind": "sphere"})
    _check_keys(groom, _GROOM, where, "groom")
    sources = [k for k in ("preset", "file", "kind") if k in groom]
    if len(sources) != 1:
        _fail(where, f"[groom] needs exactly one of preset, file, kind; got {sources}")
    if "preset" in groom:
        from ams_torch.grooms.growth import PRESETS

        if groom["preset"] not in PRESETS:
            _fail(where, f"[groom].preset must be one of {list(PRESETS)}; got {groom['preset']!r}")
        if mesh in ("sphere", "none"):
            _fail(where, "[groom].preset grows on a head mesh: set [head].mesh to 'default' or a file")
    if "file" in groom:
        groom["file"] = _path(groom["file"], "[groom].file", where, base)
    if "kind" in groom and groom["kind"] not in _GROOM_KINDS:
        _fail(where, f"[groom].kind must be one of {list(_GROOM_KINDS)}; got {groom['kind']!r}")
    for key in ("strands", "particles", "seed"):
        if key in groom:
            _num(groom[key], f"[groom].{key}", where, integer=True, nonneg=(key == "seed"), positive=(key != "seed"))
    for key in ("length", "radius", "spread"):
        if key in groom:
            _num(groom[key], f"[groom].{key}", where, positive=True)
    if "growth" in groom:
        _check_keys(groom["growth"], set(groom["growth"]), where, "groom.growth")
    groom["compare_ms"] = _bool(groom.get("compare_ms", False), "[groom].compare_ms", where)
    groom["compare_offset"] = _vec3(groom.get("compare_offset", [0.1, 0.0, 0.0]), "[groom].compare_offset", where)

    stages = s.setdefault("stages", {})
    _check_keys(stages, _STAGES, where, "stages")
    for k in _STAGES:
        stages[k] = _bool(stages.get(k, False), f"[stages].{k}", where)

    params = s.setdefault("params", {})
    names = {f.name: f for f in dataclasses.fields(Params)}
    _check_keys(params, set(names), where, "params")
    for k, v in params.items():
        default = getattr(Params(), k)
        if isinstance(default, bool):
            _bool(v, f"[params].{k}", where)
        elif isinstance(default, str):
            if not isinstance(v, str):
                _fail(where, f"[params].{k} must be a string; got {v!r}")
        elif isinstance(default, tuple):
            params[k] = _vec3(v, f"[params].{k}", where)
        else:
            _num(v, f"[params].{k}", where, integer=isinstance(default, int))
    try:
        make_params(s)
    except ValueError as err:
        msg = str(err).replace("Params.", "[params].")
        _fail(where, msg)

    hh = s.get("hair_hair", {})
    from ams_torch.stages.hair_hair import HairHair

    _check_keys(hh, {f.name for f in dataclasses.fields(HairHair)}, where, "hair_hair")
    if hh and not stages["hair_hair"]:
        _fail(where, "[hair_hair] settings given but [stages].hair_hair is false")
    try:
        HairHair(**hh)
    except (TypeError, ValueError) as err:
        _fail(where, f"[hair_hair]: {err}")

    if "motion" in s:
        if not isinstance(s["motion"], dict):
            _fail(where, f"[motion] must be a table; got {s['motion']!r}")
        m = dict(s["motion"])
        if m.get("type") == "recorded" and "path" in m:
            s["motion"]["path"] = _path(m["path"], "[motion].path", where, base)
        try:
            make_motion(s["motion"])
        except (TypeError, ValueError, FileNotFoundError) as err:
            _fail(where, f"[motion]: {err}")

    if "wind" in s:
        _check_keys(s["wind"], {f.name for f in dataclasses.fields(Wind)}, where, "wind")
        try:
            Wind(**s["wind"])
        except (TypeError, ValueError) as err:
            _fail(where, f"[wind]: {err}")

    cols = s.setdefault("colliders", [])
    if not isinstance(cols, list):
        _fail(where, "[[colliders]] must be an array of tables")
    for i, c in enumerate(cols):
        sec = f"colliders[{i}]"
        if not isinstance(c, dict) or c.get("type") not in _COLLIDERS:
            _fail(where, f"[{sec}].type must be one of {sorted(_COLLIDERS)}; got {c.get('type') if isinstance(c, dict) else c!r}")
        _check_keys(c, _COLLIDERS[c["type"]][1] | {"type", "friction", "follow_head", "motion"}, where, sec)
        if "motion" in c:
            try:
                make_motion(c["motion"])
            except (TypeError, ValueError, FileNotFoundError) as err:
                _fail(where, f"[{sec}.motion]: {err}")
        try:
            make_collider(c)
        except (TypeError, ValueError) as err:
            _fail(where, f"[{sec}]: {err}")
    if cols and not stages["collisions"]:
        _fail(where, "[[colliders]] given but [stages].collisions is false")

    if "trim" in s:
        t = s["trim"]
        _check_keys(t, _TRIM, where, "trim")
        t["frame"] = _num(t.get("frame", 1), "[trim].frame", where, integer=True, positive=True)
        t["point"] = _vec3(t.get("point", [0.0, 0.0, 0.0]), "[trim].point", where)
        t["normal"] = _vec3(t.get("normal", [0.0, -1.0, 0.0]), "[trim].normal", where)
        if not any(t["normal"]):
            _fail(where, "[trim].normal must be non-zero")
    r = s.setdefault("render", {})
    _check_keys(r, _RENDER, where, "render")
    if "view" in r and r["view"] not in ("front", "side", "back"):
        _fail(where, f"[render].view must be front, side or back; got {r['view']!r}")
    for k in ("fps", "size"):
        if k in r:
            _num(r[k], f"[render].{k}", where, positive=True)
    if "every" in r:
        _num(r["every"], "[render].every", where, integer=True, positive=True)
    return s


def make_params(scene: dict) -> Params:
    """The scene's :class:`Params` (``[params]``, ``dt``, ``substeps``, ``[stages].nonhookean``)."""
    p = dict(scene.get("params", {}))
    if "gravity" in p:
        p["gravity"] = tuple(p["gravity"])
    if "dt" in scene:
        p["dt"] = float(scene["dt"])
    if "substeps" in scene:
        p["substeps"] = int(scene["substeps"])
    if scene.get("stages", {}).get("nonhookean"):
        p["integrity_model"] = "nonhookean"
    return Params(**p)


def make_collider(c: dict):
    from ams_torch.stages import collide as C

    cls = getattr(C, _COLLIDERS[c["type"]][0])
    args = {k: v for k, v in c.items() if k not in ("type", "motion")}
    for k in ("center", "a", "b", "point", "normal", "axis"):
        if k in args:
            args[k] = tuple(args[k])
    return cls(**args)
