"""The benchmark scenes, their settings, and one run of a setting compared at material points.

A *setting* is a dict: ``substeps`` M, ``particles`` N, ``dtype`` ("float32" | "float64"),
``grid`` (hair–hair resolution, None without hair–hair), ``gs`` (``Params.geometric_stiffness``),
``off`` (stages switched off, see ``STAGES``) and optionally ``contact`` (``Params.contact``:
"frame", the default, or "substep") and ``params`` (other Params fields, e.g. the references'
``stiffness_cap``).

Every N describes the same hair: each scene's groom is built once as a fine polyline
(``FINE`` points per strand) and resampled uniformly in arc length to N particles
(``ams_torch.grooms.groom.resample_strands``, as ``scripts/convergence_n.py`` does). Runs are
compared at ``POINTS`` fixed material points per strand (rest arc-length fractions,
``ams_torch.testing.at_material_points``), so runs of different N compare point for point.
"""
from __future__ import annotations

import copy
import time
from pathlib import Path

import numpy as np
import torch

import ams_torch as at
from ams_torch.apps import scene as scn
from ams_torch.grooms.groom import resample_strands
from ams_torch.sim.inextensibility import max_stretch
from ams_torch.testing import at_material_points, shape_deviation

REPO = Path(__file__).resolve().parents[2]
DTYPES = {"float32": torch.float32, "float64": torch.float64}
#: the library default: Params() (M = 1, per-length material, geometric stiffness on), 32 particles,
#: float32, 64³ grid
BASE = {"substeps": 1, "particles": 32, "dtype": "float32", "grid": 64, "gs": bool(at.Params().geometric_stiffness),
        "off": [], "contact": at.Params().contact}
#: the contact mode that is not the library's default (its own substeps sweep)
OTHER_CONTACT = "frame" if BASE["contact"] == "substep" else "substep"
FINE = {"wisp": 1025, "head": 257, "roller_coaster": 257}  # points of the fine polylines
POINTS = 33  # material points per strand at which runs are compared
#: What switching a stage off means: ``biphasic`` drops the AMS couplings (plain MS: ω_I² = A = 0,
#: no sag-free offset); ``guard`` turns the divergence check off (``check_every = 0``).
STAGES = ("inextensibility", "hair_hair", "collisions", "nonhookean", "biphasic", "guard")
SCENE_TEXT = {
    "wisp": "strands leaving a patch along +x and curving down (0.3 m), head bobbing ±10 cm "
            "(keyframes of `wisp_comparison.toml`, AMS half); no head mesh, no stages",
    "head": "grown `straight` groom on the default head, head shaking 0.6 rad at 1.5 Hz, head collisions "
            "(64³ SDF) and hair–hair interaction",
    "roller_coaster": "`datasets/scenes/roller_coaster.toml`: grown `straight` groom, one 0.5 m loop at up to "
                      "4 g, head collisions, non-Hookean (plastic) integrity",
}


def scene_raw(name: str, frames: int, strands: int | None = None) -> dict:
    """The raw (unvalidated) scene dict of one benchmark scene."""
    if name == "wisp":
        raw = {"name": "wisp", "frames": frames, "head": {"mesh": "none"},
               "groom": {"kind": "wisp", "strands": strands or 16, "particles": 32, "length": 0.3,
                         "spread": 0.01},
               "motion": {"type": "keyframes", "times": [0.0, 0.5, 1.0, 1.5, 2.0],
                          "translations": [[0.0, 0.0, 0.0], [0.0, 0.1, 0.0], [0.0, -0.1, 0.0],
                                           [0.0, 0.1, 0.0], [0.0, 0.0, 0.0]]}}
    elif name == "head":
        raw = {"name": "head", "frames": frames,
               "head": {"mesh": "default", "subdivisions": 4, "sdf_resolution": 64},
               "groom": {"preset": "straight", "strands": strands or 1000, "particles": 32},
               "stages": {"collisions": True, "hair_hair": True},
               "hair_hair": {"resolution": 64},
               "motion": {"type": "shake", "amplitude": 0.6, "frequency": 1.5}}
    elif name == "roller_coaster":
        import tomllib

        with open(REPO / "datasets" / "scenes" / "roller_coaster.toml", "rb") as f:
            raw = tomllib.load(f)
        raw["name"] = "roller_coaster"
        raw["frames"] = frames
        if strands:
            raw["groom"]["strands"] = strands
    else:
        raise ValueError(f"unknown scene {name!r}; choose one of wisp, head, roller_coaster")
    return raw


def has_stage(raw: dict, stage: str) -> bool:
    """Whether the scene uses ``stage`` (one of ``STAGES``)."""
    if stage in ("inextensibility", "guard", "biphasic"):
        return True
    return bool(raw.get("stages", {}).get(stage, False))


def scene_stages(raw: dict) -> list[str]:
    return [s for s in STAGES if has_stage(raw, s)]


def base_setting(raw: dict, **changes) -> dict:
    """The base setting in this scene (grid only with hair–hair), with ``changes``."""
    s = dict(BASE, grid=BASE["grid"] if has_stage(raw, "hair_hair") else None, off=[])
    s.update(changes)
    return s


def setting_key(s: dict) -> tuple:
    return (s["substeps"], s["particles"], s["dtype"], s.get("grid"), bool(s.get("gs")),
            tuple(sorted(s.get("off", ()))), tuple(sorted(s.get("params", {}).items())), s.get("contact", BASE["contact"]))


def setting_label(s: dict) -> str:
    """Short text of a setting: ``M=4 N=32 float32 grid=64 SPEC -collisions FC`` (``SPEC``: geometric
    stiffness off, the SPEC form; ``FC`` / ``SC``: contact once per frame / at the substep rate,
    when it is not the library's default)."""
    out = f"M={s['substeps']} N={s['particles']} {s['dtype']}"
    if s.get("grid"):
        out += f" grid={s['grid']}"
    if not s.get("gs"):
        out += " SPEC"
    if s.get("contact", BASE["contact"]) != BASE["contact"]:
        out += " SC" if s["contact"] == "substep" else " FC"
    for st in s.get("off", ()):
        out += f" -{st}"
    for k, v in sorted(s.get("params", {}).items()):
        out += f" {k}={v:g}"
    return out


def _edited(raw: dict, setting: dict, strands: int | None = None) -> dict:
    r = copy.deepcopy(raw)
    r["substeps"] = int(setting["substeps"])
    off = set(setting.get("off", ()))
    stages = r.setdefault("stages", {})
    params = r.setdefault("params", {})
    for st in ("hair_hair", "collisions", "nonhookean"):
        if st in off:
            stages[st] = False
    if "hair_hair" in off:
        r.pop("hair_hair", None)
    if "collisions" in off:
        r.pop("colliders", None)
    if stages.get("hair_hair"):
        r.setdefault("hair_hair", {})["resolution"] = int(setting["grid"])
    if "inextensibility" in off:
        params["inextensibility"] = False
    if "guard" in off:
        params["check_every"] = 0
    if "biphasic" in off:
        params.update(integrity_rate=0.0, angular_rigidity=0.0, sag_free=False)
    params["geometric_stiffness"] = bool(setting.get("gs"))
    params["contact"] = setting.get("contact", BASE["contact"])
    params.update(setting.get("params", {}))
    if strands is not None:
        r["groom"]["strands"] = strands
        r["groom"]["particles"] = 8
    return r


_FINE: dict = {}


def fine_rest(raw: dict) -> torch.Tensor:
    """(S, FINE, 3) float64 m: the scene's groom as fine polylines (built once per scene)."""
    key = (raw["name"], int(raw["groom"].get("strands", 1)))
    if key not in _FINE:
        r = copy.deepcopy(raw)
        r["groom"]["particles"] = FINE[raw["name"]]
        r.setdefault("stages", {}).update(collisions=False, hair_hair=False)
        r.pop("hair_hair", None)
        scene = scn.parse_scene(r, where=f"bench_tradeoff:{raw['name']}", base=str(REPO / "datasets" / "scenes"))
        _FINE[key] = torch.as_tensor(scn.build(scene, dtype=torch.float64).rest, dtype=torch.float64)
    return _FINE[key]


def make_run(raw: dict, setting: dict, backend: str = "native", subset=None) -> scn.BuiltScene:
    """The scene with a setting: the stages, params, colliders and motion of the scene file
    (built on a one-strand groom), the simulator on the fine groom resampled to N particles
    (``subset``: strand indices to keep; only exact without hair–hair)."""
    r = _edited(raw, setting, strands=1)
    scene = scn.parse_scene(r, where=f"bench_tradeoff:{raw['name']}", base=str(REPO / "datasets" / "scenes"))
    shell = scn.build(scene, dtype=DTYPES[setting["dtype"]])
    rest = resample_strands(fine_rest(raw), int(setting["particles"]))
    if subset is not None:
        if shell.sim.hair_hair is not None:
            raise ValueError("a strand subset is only exact without hair–hair (strands are then independent)")
        rest = rest[torch.as_tensor(subset)]
    old = shell.sim
    shell.sim = at.Simulator(rest, old.params, dtype=old.dtype, pose=old.initial_pose, hair_hair=old.hair_hair,
                             colliders=old.colliders or None, backend=backend)
    shell.rest = rest.numpy()
    shell.scene = dict(shell.scene, groom=dict(shell.scene["groom"], strands=int(rest.shape[0]),
                                               particles=int(rest.shape[1])))
    return shell


def run_setting(raw: dict, setting: dict, subset=None, backend: str = "native", probes=(), keep_at=None,
                points: int = POINTS) -> dict:
    """Run one setting over the whole scene. Returns ``pts`` (F, S, points, 3) float64 m at the
    material points (None if it diverged), ``stretch`` (largest relative edge-length error at
    the end of a frame), ``state`` (the state after ``keep_at`` frames, for timing windows),
    ``wall_s``, ``diverged`` (message or None) and ``probes`` (each probe's result)."""
    run = make_run(raw, setting, backend, subset)
    rest = torch.as_tensor(run.rest, dtype=torch.float64)
    edge = run.sim.model.edge_rest_length
    pts, stretch, kept = [], [0.0], {}

    def on_frame(k, state):
        pts.append(at_material_points(rest, state.x.detach().double(), points))
        stretch[0] = max(stretch[0], float(max_stretch(state.x.detach(), edge).max()))
        if keep_at is not None and k + 1 == keep_at:
            kept["state"] = state
        for p in probes:
            p(k, state)

    t0 = time.perf_counter()
    try:
        scn.simulate(run, on_frame=on_frame)
    except at.SimulationDiverged as err:
        return {"pts": None, "stretch": None, "state": None, "wall_s": time.perf_counter() - t0,
                "diverged": str(err), "run": run}
    return {"pts": torch.stack(pts), "stretch": stretch[0], "state": kept.get("state"),
            "wall_s": time.perf_counter() - t0, "diverged": None, "run": run}


def errors_mm(x: torch.Tensor, ref: torch.Tensor) -> dict:
    """x, ref: (F, S, P, 3) m at the same material points. RMS, max and shape error (mm): the
    shape error aligns each strand rigidly to the reference strand (Kabsch) and averages the
    point distances over strands and frames."""
    d = (x - ref).norm(dim=-1)
    shape = shape_deviation(x, ref, align=True)
    return {"rms_error_mm": float(d.pow(2).mean().sqrt()) * 1e3, "max_error_mm": float(d.max()) * 1e3,
            "shape_error_mm": float(shape.mean()) * 1e3}


def strand_subset(raw: dict, count: int | None):
    """Evenly spaced strand indices for the error runs, or None (all strands): only without
    hair–hair, where strands are independent and a subset is exact."""
    strands = int(raw["groom"].get("strands", 1))
    if has_stage(raw, "hair_hair") or not count or count >= strands:
        return None
    return np.unique(np.linspace(0, strands - 1, count).round().astype(np.int64))
