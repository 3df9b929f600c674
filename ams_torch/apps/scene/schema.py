"""Scene files: reading and validating the TOML (every key checked; errors name the file and key).

Validation is table driven: each section is a dict ``key -> (checker, default)``; a checker
takes the value and its key name and returns the normalised value or raises
:class:`SceneError` (``scene.toml: [groom].strands must be an integer >= 1; got 0``). Checks that
tie keys together (exactly one groom source, stages that a section needs) run after the table.
See :mod:`ams_torch.apps.scene` for the format. Keys for imported assets (SPEC §14):

    [head]  mesh = "head.obj" | "body.tfxmesh" (any trimesh format, or TressFX .tfxmesh)
    [groom] file = "hair.tfx" (a format of ams_torch.grooms.io), bind = true (bind the roots
            to the head mesh), max_bind_distance = 0.001 (m; needs bind), min_length = 0.005
            (m: strands shorter than this are dropped; default 5 mm)
    both:   units = "m" | "cm" | "mm"  or  scale = 0.01 (m per file unit; not both),
            up_axis = "y" | "z", transform = 4x4 nested list (rows, last row [0, 0, 0, 1]) or
            { rotation = [[...], [...], [...]], translation = [x, y, z] } (m)

Rotation matrices (any ``transform``, keyframe ``rotations``) must be rotations: orthonormal to
``ROTATION_TOLERANCE`` (1e-5, max |RᵀR − I|) with det +1; the error names the key.
Normalisations: paths are resolved against the scene's folder; ``units`` becomes ``scale``
(m per file unit; ``up_axis`` defaults to "y" for files); a ``transform`` becomes
``{"rotation": 3x3, "translation": [3] m}`` with the rotation replaced by the nearest exact one;
keyframe ``rotations`` become ``rotvecs``.
"""
from __future__ import annotations

import copy
import dataclasses
import os
import tomllib
from typing import Optional

from ams_torch.apps.motion import make_motion
from ams_torch.geometry.sdf import MAX_RESOLUTION
from ams_torch.apps.scene.checks import (_ABSENT, ABSENT, ANY_NUMBER, NONNEG, POSITIVE, ROTATION_TOLERANCE,  # noqa: F401
                                         UNITS, SceneError, _construct, _Ctx, _show, _table, boolean, check_rotation,
                                         check_table, file_path, integer, is_number, list_of, number, one_of,
                                         rotation, string, transform, vec3)
from ams_torch.sim.params import Params
from ams_torch.stages.wind import Wind

__all__ = ["SceneError", "read_toml", "load_scene", "parse_scene", "make_params", "make_collider", "SCENE_DIR",
           "check_rotation", "check_table", "is_number", "number", "integer", "boolean", "one_of", "string", "ABSENT",
           "ROTATION_TOLERANCE", "UNITS"]

SCENE_DIR = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))),
                         "datasets", "scenes")
# -- sections ---------------------------------------------------------------------------------
def _mesh_exts():
    import trimesh

    return {f".{e}" for e in trimesh.exchange.load.available_formats()} | {".tfxmesh"}


def _groom_exts():
    from ams_torch.grooms.io import FORMATS

    return set(FORMATS)


_IMPORT = {"units": (one_of(*UNITS), _ABSENT), "scale": (POSITIVE, _ABSENT), "up_axis": (one_of("y", "z"), _ABSENT),
           "transform": (transform, _ABSENT)}


def _imported(t: dict, section: str, from_file: bool, source: str, ctx) -> None:
    """units/scale/up_axis/transform: only for a file source; normalise units -> scale."""
    given = [k for k in _IMPORT if k in t]
    if given and not from_file:
        ctx.fail(f"[{section}].{given[0]} applies to a file ({source}); this {section} is not read from a file")
    if "units" in t and "scale" in t:
        ctx.fail(f"[{section}]: give units or scale, not both (units = {t['units']!r}, scale = {t['scale']!r})")
    if from_file:
        t["scale"] = UNITS[t.pop("units")] if "units" in t else t.get("scale", 1.0)
        t.setdefault("up_axis", "y")


def _head_mesh(v, key, ctx):
    if isinstance(v, str) and v in ("default", "sphere", "none"):
        return v
    if not isinstance(v, str):
        ctx.fail(f"{key} must be 'default', 'sphere', 'none' or a mesh file path; got {_show(v)}")
    return file_path(_mesh_exts, "mesh file")(v, key, ctx)


HEAD = {"mesh": (_head_mesh, "default"), "subdivisions": (integer(1, 8), 4), "radius": (POSITIVE, 0.1),
        "collide": (boolean, _ABSENT), "sdf_resolution": (integer(8, MAX_RESOLUTION), 64), **_IMPORT}


def _head(raw, ctx) -> dict:
    h = _table(raw, HEAD, "head", ctx)
    h.setdefault("collide", h["mesh"] != "none")
    _imported(h, "head", h["mesh"] not in ("default", "sphere", "none"), "[head].mesh = path", ctx)
    return h


def _any(v, key, ctx):
    return v


def _growth(v, key, ctx):
    from ams_torch.grooms.growth import GrowthParams

    if not isinstance(v, dict):
        ctx.fail(f"{key} must be a table; got {_show(v)}")
    fields = {f.name: f.default for f in dataclasses.fields(GrowthParams)}
    spec = {k: (boolean if isinstance(d, bool) else integer(1) if k == "steps" or isinstance(d, int) else ANY_NUMBER
                if isinstance(d, float) else _any, _ABSENT) for k, d in fields.items()}
    spec.update({k: (POSITIVE, _ABSENT) for k in ("tail_length", "tie_radius", "spread")})
    spec["region"] = (_any, _ABSENT)
    return _table(v, spec, "groom.growth", ctx)


def _groom_preset(v, key, ctx):
    from ams_torch.grooms.presets import PRESETS

    return one_of(*PRESETS)(v, key, ctx)


GROOM = {"preset": (_groom_preset, _ABSENT), "file": (file_path(_groom_exts, "groom file"), _ABSENT),
         "kind": (one_of("sphere", "strand", "wisp"), _ABSENT), "strands": (integer(1), _ABSENT),
         "particles": (integer(4), _ABSENT), "seed": (integer(0), _ABSENT), "length": (POSITIVE, _ABSENT),
         "radius": (POSITIVE, _ABSENT), "spread": (POSITIVE, _ABSENT), "growth": (_growth, _ABSENT),
         "compare_ms": (boolean, False), "compare_offset": (vec3(), [0.1, 0.0, 0.0]), "bind": (boolean, _ABSENT),
         "max_bind_distance": (POSITIVE, _ABSENT), "min_length": (NONNEG, _ABSENT), **_IMPORT}


def _groom(raw, head: dict, ctx) -> dict:
    g = _table(raw, GROOM, "groom", ctx)
    sources = [k for k in ("preset", "file", "kind") if k in g]
    if len(sources) != 1:
        ctx.fail(f"[groom] needs exactly one of preset, file, kind; got {sources}")
    if "preset" in g and head["mesh"] in ("sphere", "none"):
        ctx.fail("[groom].preset grows on a head mesh: set [head].mesh to 'default' or a file")
    if "growth" in g and "preset" not in g:
        ctx.fail("[groom].growth sets growth parameters of a preset; this groom has no preset")
    if "growth" in g and g["preset"] != "ponytail":
        from ams_torch.grooms.growth import GrowthParams

        args = {k: v for k, v in g["growth"].items() if k not in ("region", "tail_length", "tie_radius", "spread")}
        _construct(GrowthParams, args, "groom.growth", ctx)
    _imported(g, "groom", "file" in g, "[groom].file", ctx)
    if g.get("bind"):
        if "file" not in g:
            ctx.fail("[groom].bind binds a groom read from a file ([groom].file) to the head mesh")
        if head["mesh"] in ("sphere", "none"):
            ctx.fail(f"[groom].bind needs a head mesh to bind to ([head].mesh = 'default' or a file); "
                     f"got {head['mesh']!r}")
    if "max_bind_distance" in g and not g.get("bind"):
        ctx.fail("[groom].max_bind_distance needs bind = true")
    if "min_length" in g and "file" not in g:
        ctx.fail("[groom].min_length drops short strands of a groom read from a file ([groom].file)")
    return g


def _params_spec() -> dict:
    spec = {}
    for f in dataclasses.fields(Params):
        d = f.default
        spec[f.name] = (boolean if isinstance(d, bool) else one_of("hookean", "nonhookean")
                        if f.name == "integrity_model" else string if isinstance(d, str) else vec3()
                        if isinstance(d, tuple) else integer(0) if isinstance(d, int) else ANY_NUMBER, _ABSENT)
    return spec


def _hair_hair_spec() -> dict:
    from ams_torch.stages.hair_hair import HairHair

    return {f.name: (boolean if isinstance(f.default, bool) else integer(0) if isinstance(f.default, int)
                     else ANY_NUMBER, _ABSENT) for f in dataclasses.fields(HairHair)}


def _keyframes(m: dict, section: str, ctx) -> None:
    """Keyframe motions: lengths agree; ``rotations`` (validated rotations) become ``rotvecs``."""
    k = len(m["times"])
    if any(b <= a for a, b in zip(m["times"], m["times"][1:])):
        ctx.fail(f"[{section}].times must be strictly increasing (s); got {_show(m['times'])}")
    for name in ("rotvecs", "translations", "rotations"):
        if name in m and len(m[name]) != k:
            ctx.fail(f"[{section}].{name} has {len(m[name])} entries; [{section}].times has {k}")
    if "rotations" in m:
        if "rotvecs" in m:
            ctx.fail(f"[{section}]: give rotvecs or rotations, not both")
        from ams_torch.geometry.pose import matrix_to_axis_angle
        import torch

        m["rotvecs"] = matrix_to_axis_angle(torch.tensor(m.pop("rotations"), dtype=torch.float64)).tolist()


_AXIS = (vec3(nonzero=True), _ABSENT)
MOTIONS = {
    "static": {},
    "shake": {"amplitude": (ANY_NUMBER, _ABSENT), "frequency": (ANY_NUMBER, _ABSENT), "axis": _AXIS},
    "nod": {"amplitude": (ANY_NUMBER, _ABSENT), "frequency": (ANY_NUMBER, _ABSENT), "axis": _AXIS},
    "spin": {"rate": (ANY_NUMBER, _ABSENT), "ramp": (NONNEG, _ABSENT), "axis": _AXIS},
    "roller_coaster": {"radius": (POSITIVE, _ABSENT), "peak_g": (POSITIVE, _ABSENT), "loops": (integer(1), _ABSENT)},
    "keyframes": {"times": (list_of(ANY_NUMBER), _ABSENT), "rotvecs": (list_of(vec3()), _ABSENT),
                  "translations": (list_of(vec3()), _ABSENT), "rotations": (list_of(rotation), _ABSENT)},
    "recorded": {"path": (file_path({".npz"}, "recorded motion (.npz)"), _ABSENT)},
}


def motion_section(raw, section: str, ctx) -> dict:
    """Validate a motion table (``type`` and that motion's arguments)."""
    if not isinstance(raw, dict):
        ctx.fail(f"[{section}] must be a table; got {_show(raw)}")
    kind = one_of(*MOTIONS)(raw.get("type", "static"), f"[{section}].type", ctx)
    m = {"type": kind, **_table({k: v for k, v in raw.items() if k != "type"}, MOTIONS[kind], section, ctx)}
    if kind == "keyframes":
        if "times" not in m:
            ctx.fail(f"[{section}].times is required for keyframes")
        _keyframes(m, section, ctx)
    if kind == "recorded" and "path" not in m:
        ctx.fail(f"[{section}].path is required for a recorded motion")
    _construct(make_motion, {"spec": m}, section, ctx)
    return m


WIND = {"direction": (vec3(nonzero=True), _ABSENT), "speed": (NONNEG, _ABSENT), "gust": (NONNEG, _ABSENT),
        "gust_frequency": (ANY_NUMBER, _ABSENT), "turbulence": (NONNEG, _ABSENT), "noise_scale": (POSITIVE, _ABSENT),
        "noise_frequency": (ANY_NUMBER, _ABSENT), "modes": (integer(1, 1024), _ABSENT),
        "seed": (integer(0, 2**63 - 1), _ABSENT), "coefficient": (NONNEG, _ABSENT)}
_COLLIDER_ARGS = {"friction": (NONNEG, _ABSENT), "follow_head": (boolean, _ABSENT)}
COLLIDERS = {
    "sphere": ("SphereCollider", {"center": (vec3(), _ABSENT), "radius": (POSITIVE, _ABSENT)}),
    "capsule": ("CapsuleCollider", {"a": (vec3(), _ABSENT), "b": (vec3(), _ABSENT), "radius": (POSITIVE, _ABSENT)}),
    "plane": ("PlaneCollider", {"point": (vec3(), _ABSENT), "normal": (vec3(nonzero=True), _ABSENT)}),
    "hollow_sphere": ("HollowSphereCollider", {"center": (vec3(), _ABSENT), "radius": (POSITIVE, _ABSENT),
                                               "thickness": (POSITIVE, _ABSENT), "cut_height": (ANY_NUMBER, _ABSENT),
                                               "axis": _AXIS}),
}


def _colliders(raw, stages: dict, ctx) -> list:
    if not isinstance(raw, list):
        ctx.fail(f"[[colliders]] must be an array of tables; got {_show(raw)}")
    out = []
    for i, c in enumerate(raw):
        sec = f"colliders[{i}]"
        kind = c.get("type") if isinstance(c, dict) else c
        if not isinstance(kind, str) or kind not in COLLIDERS:
            ctx.fail(f"[{sec}].type must be one of {sorted(COLLIDERS)}; got {_show(kind)}")
        spec = {"type": (string, _ABSENT), **COLLIDERS[kind][1], **_COLLIDER_ARGS,
                "motion": ((lambda v, k, cx, s=sec: motion_section(v, f"{s}.motion", cx)), _ABSENT)}
        c = _table(c, spec, sec, ctx)
        _construct(make_collider, {"c": c}, sec, ctx)
        out.append(c)
    if out and not stages["collisions"]:
        ctx.fail("[[colliders]] given but [stages].collisions is false")
    return out


STAGES = {k: (boolean, False) for k in ("hair_hair", "collisions", "nonhookean")}
TRIM = {"frame": (integer(1), 1), "point": (vec3(), [0.0, 0.0, 0.0]), "normal": (vec3(nonzero=True), [0.0, -1.0, 0.0])}
RENDER = {"view": (one_of("front", "side", "back"), _ABSENT), "fps": (POSITIVE, _ABSENT), "size": (POSITIVE, _ABSENT),
          "every": (integer(1), _ABSENT)}
_SECTION = (_any, _ABSENT)  # checked by its own section validator below
TOP = {"name": (string, "scene"), "description": (string, _ABSENT), "frames": (integer(1), 60),
       "dt": (POSITIVE, _ABSENT), "substeps": (integer(1), _ABSENT), "scale": (POSITIVE, 1.0),
       **{k: _SECTION for k in ("head", "groom", "params", "stages", "hair_hair", "motion", "wind", "colliders",
                                "trim", "render")}}


#: the deepest nesting of tables and arrays a scene or recipe file may have
MAX_DEPTH = 32


def _depth(value) -> int:
    """How deeply tables and arrays nest in ``value`` (iteratively: no recursion limit)."""
    deepest, stack = 0, [(value, 0)]
    while stack:
        v, d = stack.pop()
        deepest = max(deepest, d)
        if d <= MAX_DEPTH:
            stack.extend((c, d + 1) for c in (v.values() if isinstance(v, dict) else v if isinstance(v, list) else ()))
    return deepest


def read_toml(path: str, kind: str, error=None, overrides: Optional[dict] = None) -> dict:
    """Read a TOML file as a dict with ``name`` defaulting to the file stem and ``overrides``
    replacing top-level keys; a missing file or bad TOML raises ``error`` (default
    :class:`SceneError`) naming the file."""
    error = error or SceneError
    if not os.path.isfile(path):
        raise error(f"{path}: no such {kind} file")
    with open(path, "rb") as f:
        data = f.read()
    try:
        raw = tomllib.loads(data.decode("utf-8-sig"))  # a UTF-8 byte-order mark, as some editors write, is fine
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as err:
        raise error(f"{path}: not valid TOML: {err}") from None
    except RecursionError:
        raise error(f"{path}: not valid TOML here: tables or arrays nested too deeply") from None
    if _depth(raw) > MAX_DEPTH:
        raise error(f"{path}: tables or arrays nested more than {MAX_DEPTH} levels deep; a {kind} needs a few")
    raw.setdefault("name", os.path.splitext(os.path.basename(path))[0])
    raw.update(overrides or {})
    return raw


def load_scene(path: str, overrides: Optional[dict] = None) -> dict:
    """Read and validate a scene TOML file. ``overrides``: top-level keys replacing the file's
    (e.g. ``{"frames": 3, "scale": 0.1}``). Returns the validated scene dict (paths resolved)."""
    raw = read_toml(path, "scene", SceneError, overrides)
    return parse_scene(raw, where=path, base=os.path.dirname(os.path.abspath(path)))


def parse_scene(raw: dict, where: str = "scene", base: str = ".") -> dict:
    """Validate a scene dict (as read from TOML); returns a normalised deep copy (defaults
    filled in, paths resolved). Raises :class:`SceneError` naming the file and the key."""
    ctx = _Ctx(where, base)
    s = _table(copy.deepcopy(raw), TOP, "top level", ctx)
    s["head"] = _head(s.get("head", {}), ctx)
    s["groom"] = _groom(s.get("groom", {"kind": "sphere"}), s["head"], ctx)
    s["stages"] = _table(s.get("stages", {}), STAGES, "stages", ctx)
    s["params"] = _table(s.get("params", {}), _params_spec(), "params", ctx)
    _construct(lambda: make_params(s), {}, "params", ctx, prefix="Params.")
    if "hair_hair" in s:
        from ams_torch.stages.hair_hair import HairHair

        s["hair_hair"] = _table(s["hair_hair"], _hair_hair_spec(), "hair_hair", ctx)
        if s["hair_hair"] and not s["stages"]["hair_hair"]:
            ctx.fail("[hair_hair] settings given but [stages].hair_hair is false")
        _construct(HairHair, s["hair_hair"], "hair_hair", ctx, prefix="HairHair.")
    if "motion" in s:
        s["motion"] = motion_section(s["motion"], "motion", ctx)
    if "wind" in s:
        s["wind"] = _table(s["wind"], WIND, "wind", ctx)
        _construct(Wind, s["wind"], "wind", ctx, prefix="wind.")
    s["colliders"] = _colliders(s.get("colliders", []), s["stages"], ctx)
    if "trim" in s:
        s["trim"] = _table(s["trim"], TRIM, "trim", ctx)
    s["render"] = _table(s.get("render", {}), RENDER, "render", ctx)
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
    """The collider of a validated ``[[colliders]]`` table (its ``motion`` is not part of it)."""
    from ams_torch.stages import collide as C

    cls = getattr(C, COLLIDERS[c["type"]][0])
    args = {k: v for k, v in c.items() if k not in ("type", "motion")}
    for k in ("center", "a", "b", "point", "normal", "axis"):
        if k in args:
            args[k] = tuple(args[k])
    return cls(**args)
