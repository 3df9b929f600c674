"""Scene files: a TOML description of a whole simulation, validated, built and run.

A scene composes a head, a groom, :class:`~ams_torch.Params`, colliders, a head motion, wind,
the optional stages and the run length. Only the stages a scene names are built and run.
Every key is checked; errors name the key (``scene.toml: [params].stretch_stiffness must be
non-negative ...``). Top level::

    name = "wig_in_wind"          # optional, default: file stem
    description = "..."           # optional
    frames = 120                  # frames to simulate (int >= 1)
    dt = 0.0166667                # s, optional (else params.dt)
    substeps = 1                  # optional (else params.substeps)
    scale = 1.0                   # multiplies the groom's strand count (toward the paper's sizes)

    [head]     mesh = "default" | "none" | "sphere" | path (relative to the scene file)
               subdivisions = 4   (default head), radius = 0.1 (sphere head), collide = true
               sdf_resolution = 64 (head collider SDF)
    [groom]    preset = "straight" | file = "path" | kind = "sphere" | "strand" | "wisp"
               strands, particles, seed, length, radius (sphere/strand/wisp), spread (wisp),
               [groom.growth] overrides for the preset (growth parameters)
               compare_ms = false, compare_offset = [x, y, z] (duplicate the groom as plain
               mass-spring strands, κ_I = κ_α = 0, shifted by the offset: AMS vs MS)
    [params]   any field of ams_torch.Params (integrity_model = "nonhookean", ...)
    [stages]   hair_hair = false, collisions = false, nonhookean = false
    [hair_hair] fields of ams_torch.HairHair (resolution = 64, ...)
    [motion]   type = "static" | "shake" | "nod" | "spin" | "roller_coaster" | "keyframes" |
               "recorded" and the motion's arguments (see ams_torch.apps.motion)
    [wind]     fields of ams_torch.stages.wind.Wind (speed, direction, gust, turbulence, ...)
    [[colliders]] type = "sphere" | "capsule" | "plane" | "hollow_sphere", its arguments,
               follow_head = false, and an optional [colliders.motion] (world pose over time)
    [trim]     frame = 60, point = [x, y, z], normal = [nx, ny, nz] (head frame): at that frame
               strands are cut where they cross the plane (the part on the normal's side goes)

Usage::

    scene = load_scene("datasets/scenes/default.toml")
    run = build(scene)                 # Simulator, motion, wind, ...
    result = simulate(run)             # positions (F, S, N, 3), poses, timings
"""
from __future__ import annotations

import copy
import dataclasses
import math
import os
import time
import tomllib
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional

import numpy as np
import torch

from ams_torch.apps.motion import Motion, make_motion
from ams_torch.sim.params import Params
from ams_torch.stages.wind import Wind

__all__ = ["SceneError", "load_scene", "parse_scene", "build", "simulate", "BuiltScene", "trim_strands",
           "SCENE_DIR"]

SCENE_DIR = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "datasets", "scenes")


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
            _make_collider(c)
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


def _make_collider(c: dict):
    from ams_torch.stages import collide as C

    cls = getattr(C, _COLLIDERS[c["type"]][0])
    args = {k: v for k, v in c.items() if k not in ("type", "motion")}
    for k in ("center", "a", "b", "point", "normal", "axis"):
        if k in args:
            args[k] = tuple(args[k])
    return cls(**args)


def _head_mesh(head: dict):
    if head["mesh"] == "default":
        from ams_torch.grooms.head import default_head

        return default_head(head["subdivisions"])
    if head["mesh"] in ("sphere", "none"):
        return None
    from ams_torch.geometry.mesh import load_mesh

    return load_mesh(head["mesh"])


def _make_groom(scene: dict, mesh) -> tuple:
    """The scene's groom (scaled strand count): (rest positions (S, N, 3) m as numpy, the
    :class:`~ams_torch.Groom` with its root binding for presets and files, or None)."""
    g = scene["groom"]
    scale = float(scene["scale"])
    strands = max(1, int(round(g.get("strands", 1000) * scale)))
    particles = g.get("particles")
    if "preset" in g:
        from ams_torch.grooms.growth import preset

        groom = preset(g["preset"], strands=strands, particles=particles, seed=g.get("seed", 0), mesh=mesh,
                       **g.get("growth", {}))
        return groom.rest_positions.numpy(), groom
    if "file" in g:
        from ams_torch.grooms.io import read_groom

        groom = read_groom(g["file"], resample=particles or 32)
        if scale != 1.0:
            groom = groom.subset(np.linspace(0, groom.num_strands - 1, strands).astype(int))
        return groom.rest_positions.numpy(), groom
    n = particles or 32
    length = g.get("length", 0.25)
    if g["kind"] == "sphere":
        from ams_torch.grooms.simple import sphere_groom

        return sphere_groom(strands, n, radius=g.get("radius", scene["head"]["radius"]), length=length).numpy(), None
    if g["kind"] == "wisp":
        from ams_torch.grooms.simple import wisp

        return np.asarray(wisp(strands, n, length=length, spread=g.get("spread", 0.01))), None
    # a single horizontal strand (or several side by side, 1 cm apart), rooted at the origin
    t = np.linspace(0.0, length, n)
    rest = np.zeros((strands, n, 3))
    rest[:, :, 0] = t
    rest[:, :, 2] = (np.arange(strands) * 0.01)[:, None]
    return rest, None


@dataclass
class BuiltScene:
    """What :func:`build` makes. ``sim`` is the :class:`~ams_torch.Simulator`; ``motion`` the head
    motion; ``wind`` (or None); ``collider_motions`` one entry per collider (Motion or None);
    ``rest`` the simulated rest shape (S, N, 3) m; ``groom`` the :class:`~ams_torch.Groom` it came
    from (root binding) for preset and file grooms, else None."""

    scene: dict
    sim: Any
    motion: Motion
    wind: Optional[Wind]
    collider_motions: List[Optional[Motion]]
    head_mesh: Any
    rest: np.ndarray
    build_seconds: Dict[str, float] = field(default_factory=dict)
    groom: Any = None


def _ms_variant(params: Params, rest: np.ndarray, offset) -> tuple:
    """Duplicate the groom as plain mass-spring strands (κ_I = κ_α = 0) shifted by ``offset``."""
    s = rest.shape[0]
    both = np.concatenate([rest, rest + np.asarray(offset)[None, None]], 0)
    per = lambda v: torch.cat([torch.full((s, 1), float(v)), torch.zeros(s, 1)])  # noqa: E731
    return params.replace(integrity_stiffness=per(params.integrity_stiffness),
                          angular_stiffness=per(params.angular_stiffness), sag_free=False), both


def build(scene: dict, device=None, dtype=torch.float32) -> BuiltScene:
    """Build the simulator and controls of a validated scene (see :func:`load_scene`).
    Only the stages the scene names are built (no grid, no SDF otherwise)."""
    from ams_torch.stages.hair_hair import HairHair
    from ams_torch.sim.simulator import Simulator

    times = {}
    t0 = time.perf_counter()
    mesh = _head_mesh(scene["head"])
    rest, groom = _make_groom(scene, mesh)
    times["groom"] = time.perf_counter() - t0
    params = make_params(scene)
    if scene["groom"]["compare_ms"]:
        params, rest = _ms_variant(params, rest, scene["groom"]["compare_offset"])
        groom = None  # the doubled groom has no single root binding
    stages = scene["stages"]
    cols, col_motions = [], []
    if stages["collisions"]:
        from ams_torch.stages.collide import MeshCollider, SphereCollider

        if scene["head"]["collide"] and mesh is not None:
            cols.append(MeshCollider(mesh, resolution=scene["head"]["sdf_resolution"], follow_head=True))
            col_motions.append(None)
        elif scene["head"]["collide"] and scene["head"]["mesh"] == "sphere":
            cols.append(SphereCollider(radius=scene["head"]["radius"], follow_head=True))
            col_motions.append(None)
        for c in scene["colliders"]:
            cols.append(_make_collider(c))
            col_motions.append(make_motion(c["motion"]) if "motion" in c else None)
    hh = HairHair(**scene.get("hair_hair", {})) if stages["hair_hair"] else None
    t1 = time.perf_counter()
    motion = make_motion(scene.get("motion"))
    sim = Simulator(rest, params, device=device, dtype=dtype, pose=motion(0.0, dtype=dtype), hair_hair=hh,
                    colliders=cols or None)
    if sim.collision_stage is not None:
        for c in cols:
            if hasattr(c, "sdf"):
                c.sdf  # build (or load) the SDF now, not inside the first frame
    times["simulator"] = time.perf_counter() - t1
    wind = Wind(**scene["wind"]) if "wind" in scene else None
    return BuiltScene(scene, sim, motion, wind, col_motions, mesh, rest, times, groom)


def trim_strands(rest: torch.Tensor, x: torch.Tensor, v: torch.Tensor, pose, point, normal,
                 min_fraction: float = 0.2) -> tuple:
    """Cut strands where they cross a plane (digital trimming).

    rest: (S, N, 3) m head-frame rest shape; x, v: (S, N, 3) world positions (m) and velocities
    (m/s); pose: the head pose; point, normal: the plane in the head frame (the side the normal
    points to is cut off). Each strand whose current shape crosses the plane keeps the arc-length
    fraction f up to the crossing (at least ``min_fraction``); its rest shape, positions and
    velocities are resampled to the same N particles over that fraction. Returns (new rest
    (S, N, 3), new x, new v, kept fraction (S,)).
    """
    xl = pose.to_local(x)
    p = torch.as_tensor(point, dtype=x.dtype, device=x.device)
    n = torch.nn.functional.normalize(torch.as_tensor(normal, dtype=x.dtype, device=x.device), dim=0)
    side = (xl - p) @ n  # (S, N), > 0: to be cut
    seg = (xl[:, 1:] - xl[:, :-1]).norm(dim=-1)
    arc = torch.nn.functional.pad(torch.cumsum(seg, -1), (1, 0))  # (S, N)
    total = arc[:, -1].clamp(min=1e-12)
    out = side > 0
    num = x.shape[1]
    first = torch.where(out.any(-1), out.float().argmax(-1), torch.full_like(out[:, 0], num, dtype=torch.long))
    frac = torch.ones(x.shape[0], dtype=x.dtype, device=x.device)
    cut = (first > 0) & (first < num)
    i1 = first.clamp(1, num - 1)
    i0 = i1 - 1
    s0 = side.gather(1, i0[:, None])[:, 0]
    s1 = side.gather(1, i1[:, None])[:, 0]
    w = (-s0 / (s1 - s0).clamp(min=1e-12)).clamp(0, 1)  # s0 <= 0 < s1
    a0, a1 = arc.gather(1, i0[:, None])[:, 0], arc.gather(1, i1[:, None])[:, 0]
    frac = torch.where(cut, ((a0 + w * (a1 - a0)) / total).clamp(min=min_fraction, max=1.0), frac)

    def resample(y: torch.Tensor) -> torch.Tensor:
        u = arc / total[:, None]  # (S, N) parameter of each particle along the current strand
        target = torch.linspace(0, 1, num, dtype=x.dtype, device=x.device)[None] * frac[:, None]
        idx = torch.searchsorted(u.contiguous(), target.contiguous()).clamp(1, num - 1)
        ua, ub = u.gather(1, idx - 1), u.gather(1, idx)
        t = ((target - ua) / (ub - ua).clamp(min=1e-12)).clamp(0, 1)[..., None]
        ya = y.gather(1, (idx - 1)[..., None].expand(-1, -1, 3))
        yb = y.gather(1, idx[..., None].expand(-1, -1, 3))
        return ya + t * (yb - ya)

    return resample(rest), resample(x), resample(v), frac


def simulate(run: BuiltScene, frames: Optional[int] = None, progress: bool = False, on_frame=None) -> dict:
    """Run a built scene. Returns a dict: ``positions`` (F, S, N, 3) float32 numpy (world, m),
    ``rotations`` (F, 3, 3), ``translations`` (F, 3) m, ``ms_per_frame`` {stage: ms} (``solve``:
    the AMS integration incl. inextensibility; ``hair_hair``, ``collisions``, ``wind``, ``trim``)
    and the final ``state``. ``on_frame(k, state)`` is called after each frame."""
    from ams_torch.geometry.pose import Pose

    sim = run.sim
    scene = run.scene
    frames = int(frames or scene["frames"])
    dt = sim.params.dt
    state = sim.initial_state()
    timings = {"solve": 0.0}
    sync = (lambda: torch.cuda.synchronize()) if sim.device.type == "cuda" else (lambda: None)  # noqa: E731

    def timed(name, stage):
        timings[name] = 0.0

        def run_stage(*args):
            sync()
            t = time.perf_counter()
            with torch.profiler.record_function(f"ams_torch.{name}"):
                out = stage(*args)
            sync()
            timings[name] += time.perf_counter() - t
            return out

        return run_stage

    def wrap_stages():
        names = []
        if sim.hair_hair_grid is not None:
            names.append("hair_hair")
        if sim.collision_stage is not None:
            names.append("collisions")
        sim.stages = [timed(n, st) for n, st in zip(names, sim.stages)]

    wrap_stages()
    wind = None
    if run.wind is not None and not run.wind.is_zero:
        timings["wind"] = 0.0
        raw = run.wind.bind(sim)

        def wind(x, v, t):
            t0 = time.perf_counter()
            out = raw(x, v, t)
            timings["wind"] += time.perf_counter() - t0
            return out

    trim = scene.get("trim")
    xs, rots, trans, crots, ctrans = [], [], [], [], []
    specs = scene["colliders"] if sim.collision_stage is not None else []
    scene_motions = run.collider_motions[len(run.collider_motions) - len(specs):]
    it = range(frames)
    if progress:
        from tqdm.auto import tqdm

        it = tqdm(it, desc=f"simulating {scene['name']}", unit="frame")
    wall = 0.0
    for k in it:
        if trim is not None and k + 1 == trim["frame"]:
            t0 = time.perf_counter()
            state, sim = _apply_trim(run, state, trim)
            wrap_stages()
            if wind is not None:
                raw = run.wind.bind(sim)
            timings["trim"] = time.perf_counter() - t0
        t_end = (k + 1) * dt
        pose = run.motion(t_end, device=sim.device, dtype=sim.dtype)
        cposes = None
        if any(m is not None for m in run.collider_motions):
            cposes = [None if m is None else m(t_end, device=sim.device, dtype=sim.dtype) for m in run.collider_motions]
        sync()
        t0 = time.perf_counter()
        with torch.profiler.record_function("ams_torch.step"):
            state = sim.step(state, pose, external_force=wind, collider_poses=cposes)
        sync()
        wall += time.perf_counter() - t0
        xs.append(state.x.detach().to("cpu", torch.float32).numpy())
        rots.append(state.pose.rotation.detach().cpu().numpy())
        trans.append(state.pose.translation.detach().cpu().numpy())
        if specs:
            cr, ct = _collider_world_poses(specs, scene_motions, t_end, state.pose)
            crots.append(cr)
            ctrans.append(ct)
        if on_frame is not None:
            on_frame(k, state)
    staged = sum(v for k, v in timings.items() if k not in ("solve", "trim"))
    timings["solve"] = wall - staged
    ms = {k: 1e3 * v / frames for k, v in timings.items()}
    ms["total"] = 1e3 * wall / frames
    run.sim = sim
    out = {"positions": np.stack(xs), "rotations": np.stack(rots), "translations": np.stack(trans),
           "ms_per_frame": ms, "state": state}
    if specs:
        out["collider_rotations"], out["collider_translations"] = np.stack(crots), np.stack(ctrans)
    return out


def _collider_world_poses(specs, motions, t: float, head_pose) -> tuple:
    """World rotations (C, 3, 3) and translations (C, 3) m of the scene's colliders at time t
    (their motion's pose, relative to the head when ``follow_head``), for drawing."""
    rots, trans = [], []
    hr = head_pose.rotation.detach().cpu().double().numpy()
    ht = head_pose.translation.detach().cpu().double().numpy()
    for spec, m in zip(specs, motions):
        if m is not None:
            p = m(t, dtype=torch.float64)
            r, tr = p.rotation.numpy(), p.translation.numpy()
        else:
            r, tr = np.eye(3), np.zeros(3)
        if spec.get("follow_head", False):
            r, tr = hr @ r, hr @ tr + ht
        rots.append(r)
        trans.append(tr)
    return np.stack(rots), np.stack(trans)


def _apply_trim(run: BuiltScene, state, trim: dict):
    """Cut the groom by the scene's plane and rebuild the simulator around the shorter strands."""
    from ams_torch.sim.simulator import Simulator

    old = run.sim
    rest, x, v, frac = trim_strands(old.model.rest_positions, state.x, state.v, state.pose,
                                    trim["point"], trim["normal"])
    sim = Simulator(rest, old.params, device=old.device, dtype=old.dtype, pose=state.pose,
                    hair_hair=old.hair_hair, colliders=old.colliders or None)
    new = sim.initial_state(state.pose)
    run.sim = sim
    return new.replace(x=x, v=v, time=state.time, frame=state.frame), sim
