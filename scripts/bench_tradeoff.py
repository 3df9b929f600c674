"""The speed–accuracy trade: ms/frame against error to a converged reference, per setting.

Scenes (default sizes; ``--quick`` shrinks them):

    wisp            16 strands on a bobbing head (the AMS half of
                    datasets/scenes/wisp_comparison.toml), no head mesh, no stages; 120 frames
    head            1,000 grown ``straight`` strands on the default head, shaking (0.6 rad at
                    1.5 Hz), head collisions (64³ SDF) and hair–hair on; 30 frames
    roller_coaster  datasets/scenes/roller_coaster.toml with 300 of its 600 strands (one 4 g
                    loop, head collisions, non-Hookean integrity); 100 frames

For each scene: a reference (float64; substeps, particles per strand and, where hair–hair is on,
a 128³ grid all refined beyond the sweeps; if it diverges, it is rerun with half the substeps and
the doc says so), two reference checks (half the substeps, fewer particles) where affordable,
then the settings of :func:`sweep_settings`: one axis at a time around the base setting (the
library default: M = 1 substep, N = 32, float32, 64³ grid, every stage on): substeps
M ∈ {1, 2, 4, 8, 16}, particles N ∈ {8, 16, 32, 64}, dtype, grid ∈ {32, 64, 128}, each stage off
in turn; plus a joint M × N grid in float32. Then a *time reference* (float64, N = 32, many
substeps) against which the substeps sweep isolates the time discretisation (its log–log slope).
Every setting is simulated from the scene's t = 0 state with the same head motion.

Error against the reference at matching material points: particle k of an N-particle strand
sits at the rest arc-length fraction k / (N − 1) (grooms are resampled uniformly in arc length);
the reference's positions there are interpolated linearly between its two neighbouring
particles. Reported in mm, over all frames, strands and particles: ``rms_error_mm``,
``max_error_mm`` and ``shape_error_mm`` (the ablations' shape metric: each strand rigidly aligned
to the reference strand (Kabsch), mean particle distance, averaged over strands and frames).

Strands without hair–hair are independent, so in the roller coaster (no hair–hair) the
references simulate only 60 evenly spaced strands and errors are taken on those; timings are
always of the full scene.

The ``fast`` / ``balanced`` / ``accurate`` presets are chosen from the measured fronts
(:func:`choose_presets`) and then measured in every scene; finally a per-stage time breakdown of
a frame for each preset (``torch.profiler`` on the ``ams_torch.*`` labels of
:mod:`ams_torch.sim.integrator` and :func:`ams_torch.apps.scene.simulate`), with each stage switched off
in turn.

Writes ``docs/tradeoff.json`` (a list with one record per setting:
``scene``, ``settings``, ``ms_per_frame``, ``rms_error_mm``, ``max_error_mm``,
``shape_error_mm``, ...; the run's metadata rides at the end of tradeoff.md in an HTML comment),
``docs/tradeoff.md``, ``docs/tradeoff_pareto.png`` and
``docs/tradeoff_convergence.png``. ms/frame is wall time on one torch thread (``--threads``).

    python scripts/bench_tradeoff.py                  # default sizes, ~20 min on 2 cores
    python scripts/bench_tradeoff.py --quick          # smoke run, < 1 min
    python scripts/bench_tradeoff.py --render-only    # rewrite the doc and plots from the JSON
"""
from __future__ import annotations

import argparse
import copy
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import ams_torch as at  # noqa: E402
from ams_torch._bench import machine_info, shown_args  # noqa: E402
from ams_torch.apps import scene as scn  # noqa: E402
from ams_torch.sim.inextensibility import max_stretch  # noqa: E402
from ams_torch.sim.params import PARAM_PRESETS  # noqa: E402
from ams_torch.testing import shape_deviation  # noqa: E402

DTYPES = {"float32": torch.float32, "float64": torch.float64}
SUBSTEPS = (1, 2, 4, 8, 16)
PARTICLES = (8, 16, 32, 64)
GRIDS = (32, 64, 128)
BASE = {"substeps": 1, "particles": 32, "dtype": "float32", "grid": 64}
PRESET_NAMES = ("fast", "balanced", "accurate")


# ----------------------------------------------------------------------------------- scenes
def scene_raw(name: str, frames: int, strands: int | None = None) -> dict:
    """The raw (unvalidated) scene dict of one benchmark scene; see the module docstring."""
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


#: What switching a stage off means: ``biphasic`` drops the AMS couplings (plain MS: κ_I = κ_α = 0,
#: no sag-free offset); ``guard`` turns the divergence check off (``check_every = 0``).
STAGES = ("inextensibility", "hair_hair", "collisions", "nonhookean", "biphasic", "guard")


def has_stage(raw: dict, stage: str) -> bool:
    """Whether the scene uses ``stage`` (one of ``STAGES``)."""
    if stage in ("inextensibility", "guard", "biphasic"):
        return True
    return bool(raw.get("stages", {}).get(stage, False))


def scene_stages(raw: dict) -> list[str]:
    """The stages of ``STAGES`` the scene runs, each of which a setting may switch off."""
    return [s for s in STAGES if has_stage(raw, s)]


def build_run(raw: dict, setting: dict, subset: np.ndarray | None = None) -> scn.BuiltScene:
    """Build a scene with a setting: ``substeps``, ``particles``, ``dtype``, ``grid`` and ``off``
    (stages switched off). ``subset``: strand indices to keep (only without hair–hair)."""
    r = copy.deepcopy(raw)
    r["substeps"] = int(setting["substeps"])
    r.setdefault("groom", {})["particles"] = int(setting["particles"])
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
        params.update(integrity_stiffness=0.0, angular_stiffness=0.0, sag_free=False)
    scene = scn.parse_scene(r, where=f"bench_tradeoff:{raw['name']}", base=str(REPO / "datasets" / "scenes"))
    run = scn.build(scene, dtype=DTYPES[setting["dtype"]])
    if subset is not None:
        if run.sim.hair_hair_grid is not None:
            raise ValueError("a strand subset is only exact without hair–hair (strands are then independent)")
        old = run.sim
        run.sim = at.Simulator(old.model.rest_positions[torch.as_tensor(subset)], old.params, device=old.device,
                               dtype=old.dtype, pose=old.initial_pose, colliders=old.colliders or None)
        run.rest = run.rest[subset]
    return run


def simulate_setting(raw: dict, setting: dict, subset=None) -> dict:
    """Run one setting. Returns ``x`` (F, S, N, 3) float64 m (None if it diverged),
    ``ms`` ({stage: ms/frame} from :func:`ams_torch.apps.scene.simulate`), ``stretch`` (largest
    relative edge-length error over the run), ``wall_s`` and ``diverged`` (message or None)."""
    run = build_run(raw, setting, subset)
    edge = run.sim.model.edge_rest_length
    xs, stretch = [], [0.0]

    def keep(k, state):
        xs.append(state.x.detach().to("cpu", torch.float64))
        stretch[0] = max(stretch[0], float(max_stretch(state.x.detach(), edge).max()))

    t0 = time.perf_counter()
    try:
        out = scn.simulate(run, on_frame=keep)
    except at.SimulationDiverged as err:
        return {"x": None, "ms": None, "stretch": None, "wall_s": time.perf_counter() - t0, "diverged": str(err)}
    return {"x": torch.stack(xs), "ms": out["ms_per_frame"], "stretch": stretch[0],
            "wall_s": time.perf_counter() - t0, "diverged": None}


# ----------------------------------------------------------------------------------- errors
def material_map(n_ref: int, n: int) -> tuple:
    """Indices (n,), (n,) and weights (n,) that interpolate an n_ref-particle strand at the rest
    arc-length fractions k / (n − 1) of an n-particle one (uniform arc-length sampling)."""
    u = np.linspace(0.0, 1.0, n) * (n_ref - 1)
    i0 = np.clip(np.floor(u).astype(np.int64), 0, n_ref - 2)
    w = u - i0
    return torch.as_tensor(i0), torch.as_tensor(i0 + 1), torch.as_tensor(w, dtype=torch.float64)


def reference_at(ref: torch.Tensor, n: int) -> torch.Tensor:
    """ref: (F, S, n_ref, 3) m → (F, S, n, 3) m, at the material points of n-particle strands."""
    i0, i1, w = material_map(ref.shape[-2], n)
    return ref[..., i0, :] * (1 - w)[:, None] + ref[..., i1, :] * w[:, None]


def errors_mm(x: torch.Tensor, ref: torch.Tensor) -> dict:
    """x: (F, S, N, 3) m; ref: (F, S, N_ref, 3) m. RMS, max and shape error (mm) over the sequence."""
    r = reference_at(ref, x.shape[-2])
    d = (x - r).norm(dim=-1)
    shape = shape_deviation(x, r, align=True)  # (F, S) m
    return {"rms_error_mm": float(d.pow(2).mean().sqrt()) * 1e3, "max_error_mm": float(d.max()) * 1e3,
            "shape_error_mm": float(shape.mean()) * 1e3}


# --------------------------------------------------------------------------------- settings
def setting_key(s: dict) -> tuple:
    return (s["substeps"], s["particles"], s["dtype"], s.get("grid"), tuple(sorted(s.get("off", ()))))


def setting_label(s: dict) -> str:
    """Short text of a setting: ``M=4 N=32 float32 grid=64 -collisions``."""
    out = f"M={s['substeps']} N={s['particles']} {s['dtype']}"
    if s.get("grid"):
        out += f" grid={s['grid']}"
    for st in s.get("off", ()):
        out += f" -{st}"
    return out


def sweep_settings(raw: dict, args) -> list[dict]:
    """The settings of one scene: each axis swept around the base, then the joint M × N grid.
    Each setting carries ``axes``: the sweeps it belongs to (the base belongs to all)."""
    hh = has_stage(raw, "hair_hair")
    base = dict(BASE, grid=BASE["grid"] if hh else None, off=[])
    cands = []
    for m in args.substeps:
        cands.append((dict(base, substeps=m), "substeps"))
    for n in args.particles:
        cands.append((dict(base, particles=n), "particles"))
    for d in args.dtypes:
        cands.append((dict(base, dtype=d), "dtype"))
    if hh:
        for g in args.grids:
            cands.append((dict(base, grid=g), "grid"))
    for st in scene_stages(raw):
        cands.append((dict(base, off=[st]), "stages"))
    cands.append((dict(base), "stages"))
    jm, jn = args.joint[raw["name"]]
    for m in jm:
        for n in jn:
            cands.append((dict(base, substeps=m, particles=n), "joint"))
    out: dict = {}
    for s, axis in cands:
        rec = out.setdefault(setting_key(s), dict(s, axes=[]))
        if axis not in rec["axes"]:
            rec["axes"].append(axis)
    return list(out.values())


def reference_setting(raw: dict, args, substeps=None, particles=None) -> dict:
    return {"substeps": substeps or args.ref_substeps[raw["name"]],
            "particles": particles or args.ref_particles[raw["name"]], "dtype": "float64",
            "grid": args.ref_grid if has_stage(raw, "hair_hair") else None, "off": []}


def pareto(points: list[tuple[float, float]]) -> list[int]:
    """Indices of the (cost, error) points no other point beats in both (ties kept), by cost."""
    order = sorted(range(len(points)), key=lambda i: (points[i][0], points[i][1]))
    front, best = [], math.inf
    for i in order:
        if points[i][1] < best:
            front.append(i)
            best = points[i][1]
    return front


# -------------------------------------------------------------------------------- breakdown
def profile_setting(raw: dict, setting: dict, frames: int) -> dict:
    """Per-stage ms/frame of one setting from ``torch.profiler`` over ``frames`` frames from the
    scene's start (after an unrecorded one-frame warm-up run). Keys: ``springs``, ``biphasic``,
    ``assembly`` (the rest of the assembly), ``solve``, ``inextensibility``, ``hair_hair``,
    ``collisions`` (with its own length-restore rounds), ``other`` (poses, position updates,
    divergence guard) and ``total`` (the whole step); a stage that did not run is 0."""
    from torch.profiler import ProfilerActivity, profile

    run = build_run(raw, setting)
    scn.simulate(run, frames=1)  # warm-up, not recorded
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        scn.simulate(run, frames=frames)
    total = {}
    for evt in prof.events():
        if not evt.name.startswith("ams_torch."):
            continue
        name, parent = evt.name[len("ams_torch."):], evt.cpu_parent
        while parent is not None and parent.name != "ams_torch.collisions":
            parent = parent.cpu_parent
        if parent is not None and name == "inextensibility":
            continue  # the collision stage's own length restore: counted in collisions
        total[name] = total.get(name, 0.0) + evt.cpu_time_total / 1e3 / frames
    ms = {k: total.get(k, 0.0) for k in ("springs", "biphasic", "solve", "inextensibility", "hair_hair",
                                         "collisions")}
    ms["assembly"] = max(0.0, total.get("assembly", 0.0) - ms["springs"] - ms["biphasic"])
    ms["total"] = total.get("step", 0.0)
    ms["other"] = max(0.0, ms["total"] - total.get("assembly", 0.0) - ms["solve"] - ms["inextensibility"]
                      - ms["hair_hair"] - ms["collisions"])
    return ms


# ---------------------------------------------------------------------------------- presets
def _geomean(values) -> float:
    values = [max(v, 1e-12) for v in values]
    return float(math.exp(sum(math.log(v) for v in values) / len(values)))


def _pick(cands: list, cost, error, budget: float, tol: float):
    """The cheapest candidate whose error is within ``tol`` (relative) of the lowest error among
    the candidates costing at most ``budget``; the cheapest candidate when none fits."""
    within = [c for c in cands if cost(c) <= budget]
    if not within:
        return min(cands, key=cost)
    best = min(error(c) for c in within)
    return min((c for c in within if error(c) <= (1 + tol) * best), key=cost)


def choose_presets(records: list[dict], scenes: list[str], budgets: dict, tol: float = 0.05) -> dict:
    """Pick ``fast`` / ``balanced`` / ``accurate`` from the measured data.

    Each preset has a cost budget (``budgets``, × the cost of the library default M = 1, N = 32,
    float32, 64³ grid) and takes, on each axis, the cheapest option whose error is within ``tol``
    (5 %) of the lowest error that fits in the budget (improvements smaller than that are not
    worth paying for, and are below the run-to-run noise of the timings):

    1. substeps M and particles N, jointly: for every (M, N) of the joint grid measured in every
       scene (float32, every stage on), cost = geometric mean over scenes of ms/frame relative to
       the scene's base setting and error = geometric mean of RMS error relative to the base's;
       only points of this aggregated Pareto front are candidates;
    2. the hair–hair grid (scenes with hair–hair; the grid sweep at the base setting; cost = the
       base frame with the hair–hair stage's time at that grid, which is less noisy than the total);
    3. the dtype (the dtype sweep at the base setting; geometric means over scenes).

    Returns ``{name: {"substeps", "particles", "dtype", "grid", "cost", "error", "budget"}}``
    plus ``_front`` and ``_points`` (the aggregated (M, N) points).
    """
    by = {(r["scene"], setting_key(r["settings"])): r for r in records if r["rms_error_mm"] is not None}

    def rec(sc, **kw):
        return by.get((sc, setting_key(dict(BASE, grid=_base_grid(records, sc), off=[]) | kw)))

    base = {sc: rec(sc) for sc in scenes}
    joint = None
    for sc in scenes:
        mn = {(r["settings"]["substeps"], r["settings"]["particles"]) for r in records
              if r["scene"] == sc and "joint" in r["axes"] and r["rms_error_mm"] is not None}
        joint = mn if joint is None else joint & mn
    keys = sorted(joint or [])
    pts = []
    for m, n in keys:
        pts.append((_geomean([rec(sc, substeps=m, particles=n)["ms_per_frame"] / base[sc]["ms_per_frame"]
                              for sc in scenes]),
                    _geomean([rec(sc, substeps=m, particles=n)["rms_error_mm"] / base[sc]["rms_error_mm"]
                              for sc in scenes])))
    front = pareto(pts)
    hh = [sc for sc in scenes if _base_grid(records, sc)]
    dt_pairs = [(rec(sc), rec(sc, dtype="float64")) for sc in scenes if rec(sc, dtype="float64")]
    out = {}
    for name in PRESET_NAMES:
        b = budgets[name]
        i = _pick(front, lambda j: pts[j][0], lambda j: pts[j][1], b, tol)
        m, n = keys[i]
        grid = None
        if hh:
            sc = hh[0]
            grids = [r for r in records if r["scene"] == sc and "grid" in r["axes"] and r["rms_error_mm"] is not None]
            b_ms, b_hh = base[sc]["ms_per_frame"], base[sc]["ms_per_stage"].get("hair_hair", 0.0)

            def grid_cost(r):  # the base frame with this grid's hair–hair stage (less noisy than the total)
                return (b_ms - b_hh + r["ms_per_stage"].get("hair_hair", 0.0)) / b_ms

            grid = _pick(grids, grid_cost, lambda r: r["rms_error_mm"], b, tol)["settings"]["grid"]
        dtype = "float32"
        if dt_pairs:
            opts = [("float32", 1.0, 1.0),
                    ("float64", _geomean([r64["ms_per_frame"] / r32["ms_per_frame"] for r32, r64 in dt_pairs]),
                     _geomean([r64["rms_error_mm"] / r32["rms_error_mm"] for r32, r64 in dt_pairs]))]
            dtype = _pick(opts, lambda o: o[1] * pts[i][0], lambda o: o[2], b, tol)[0]
        out[name] = {"substeps": m, "particles": n, "dtype": dtype, "grid": grid, "cost": pts[i][0],
                     "error": pts[i][1], "budget": b}
    out["_front"] = [{"substeps": keys[i][0], "particles": keys[i][1], "cost": pts[i][0], "error": pts[i][1]}
                     for i in front]
    out["_points"] = [{"substeps": k[0], "particles": k[1], "cost": p[0], "error": p[1]} for k, p in zip(keys, pts)]
    return out


def _base_grid(records: list[dict], scene: str):
    """The base setting's grid in ``scene``: BASE["grid"] where hair–hair runs, else None."""
    hh = any(r["settings"].get("grid") is not None for r in records if r["scene"] == scene)
    return BASE["grid"] if hh else None


# ------------------------------------------------------------------------------------- runs
def _subset(raw: dict, count: int | None):
    strands = int(raw["groom"].get("strands", 1))
    if has_stage(raw, "hair_hair") or not count or count >= strands:
        return None
    return np.unique(np.linspace(0, strands - 1, count).round().astype(np.int64))


def run_scene(name: str, args, log) -> tuple:
    """Reference, reference checks, every setting of the sweeps and the time reference of one
    scene. Returns (records, info, reference positions (F, S, N_ref, 3) m, strand subset or None)."""
    raw = scene_raw(name, args.frames[name], args.strands.get(name))
    subset = _subset(raw, args.ref_strands.get(name))
    t0 = time.perf_counter()
    ref_set = reference_setting(raw, args)
    failed = []
    while True:
        ref = simulate_setting(raw, ref_set, subset)
        if ref["x"] is not None:
            break
        failed.append({"settings": dict(ref_set), "diverged": ref["diverged"]})
        log(f"[{name}] reference {setting_label(ref_set)} diverged: {ref['diverged'][:120]}")
        if ref_set["substeps"] <= 4:
            raise RuntimeError(f"{name}: every reference diverged: {failed}")
        ref_set = dict(ref_set, substeps=ref_set["substeps"] // 2)  # fall back to fewer substeps
    log(f"[{name}] reference {setting_label(ref_set)}: {ref['ms']['total']:.1f} ms/frame, {ref['wall_s']:.0f} s")
    info = {"reference_failed": failed, "scene": name, "frames": args.frames[name], "strands": int(raw["groom"].get("strands", 1)),
            "reference": ref_set, "reference_ms_per_frame": ref["ms"]["total"], "reference_wall_s": ref["wall_s"],
            "error_strands": None if subset is None else int(len(subset)), "checks": []}
    for axis in args.ref_checks.get(name, ()):  # the reference with half the substeps or half the particles
        m, n = ref_set["substeps"], ref_set["particles"]
        chk_set = dict(ref_set, substeps=m // 2 if axis == "substeps" else m, particles=n // 2 if axis == "particles" else n)
        chk = simulate_setting(raw, chk_set, subset)
        e = errors_mm(chk["x"], ref["x"]) if chk["x"] is not None else {}
        info["checks"].append({"settings": chk_set, **e, "wall_s": chk["wall_s"]})
        log(f"[{name}] reference check {setting_label(chk_set)} vs reference: "
            f"RMS {e.get('rms_error_mm', float('nan')):.3g} mm")
    records, kept = [], {}
    for s in sweep_settings(raw, args):
        axes = s.pop("axes")
        keep = [] if "substeps" in axes else None
        rec = measure(name, raw, s, axes, ref["x"], subset, keep)
        if keep:
            kept[len(records)] = keep[0]
        records.append(rec)
        log(f"[{name}] {_summary(rec)}")
    # time discretisation alone: the substeps sweep against a float64 run at the same N with many substeps
    m_time = args.time_ref_substeps.get(name)
    if m_time:
        t_set = dict(reference_setting(raw, args, substeps=m_time, particles=BASE["particles"]),
                     grid=BASE["grid"] if has_stage(raw, "hair_hair") else None)
        t_ref = simulate_setting(raw, t_set, subset)
        while t_ref["x"] is None and t_set["substeps"] > 8:
            info.setdefault("time_reference_failed", []).append({"settings": dict(t_set), "diverged": t_ref["diverged"]})
            log(f"[{name}] time reference {setting_label(t_set)} diverged: {t_ref['diverged'][:120]}")
            t_set = dict(t_set, substeps=t_set["substeps"] // 2)
            t_ref = simulate_setting(raw, t_set, subset)
        info["time_reference"] = t_set
        info["time_reference_wall_s"] = t_ref["wall_s"]
        for i, x in (kept.items() if t_ref["x"] is not None else ()):
            e = errors_mm(x, t_ref["x"])
            records[i]["time_rms_error_mm"] = float(f"{e['rms_error_mm']:.5g}")
            records[i]["time_max_error_mm"] = float(f"{e['max_error_mm']:.5g}")
        log(f"[{name}] time reference {setting_label(t_set)}: " + (", ".join(
            f"M={records[i]['settings']['substeps']}: {records[i]['time_rms_error_mm']:.3g} mm" for i in kept)
            if t_ref["x"] is not None else f"diverged: {t_ref['diverged'][:120]}"))
    info["wall_s"] = time.perf_counter() - t0
    info["load_avg_1min_at_end"] = round(os.getloadavg()[0], 2)
    return records, info, ref["x"], subset


def votes(info: dict, records: list) -> bool:
    """Whether a scene takes part in choosing the presets: not if its first-choice reference
    diverged, nor if its reference checks differ from the reference by more than the default
    setting's own error (then the reference cannot rank the settings)."""
    if info["reference_failed"]:
        return False
    base = next((r for r in records if r["scene"] == info["scene"] and setting_key(r["settings"])
                 == setting_key(dict(BASE, grid=BASE["grid"] if r["settings"].get("grid") else None, off=[]))), None)
    floor = max((c.get("rms_error_mm") or 0.0 for c in info["checks"]), default=0.0)
    return base is not None and base["rms_error_mm"] is not None and floor < base["rms_error_mm"]


def library_presets() -> dict:
    """The library's presets as benchmark settings: ``{name: {"substeps", "particles", "dtype", "grid"}}``
    (``Params.preset`` and ``Params.preset_settings``)."""
    out = {}
    for name in PRESET_NAMES:
        p, extra = at.Params.preset(name), at.Params.preset_settings(name)
        out[name] = {"substeps": p.substeps, "particles": extra["particles"], "dtype": extra["dtype"],
                     "grid": extra["hair_hair_resolution"]}
    return out


def preset_setting(preset: dict, raw: dict) -> dict:
    """The setting of a preset (``{"substeps", "particles", "dtype", "grid"}``) in a scene: the grid
    only where the scene has hair–hair."""
    return {"substeps": preset["substeps"], "particles": preset["particles"], "dtype": preset["dtype"],
            "grid": preset["grid"] if has_stage(raw, "hair_hair") else None, "off": []}


def measure_presets(name: str, raw: dict, presets: dict, ref_x: torch.Tensor, subset, records: list, log) -> None:
    """Tag the records of the presets' settings in scene ``name`` with the sweep ``preset``,
    simulating (and adding) those the sweeps did not measure."""
    for pname in PRESET_NAMES:
        s = preset_setting(presets[pname], raw)
        rec = next((r for r in records if r["scene"] == name and setting_key(r["settings"]) == setting_key(s)), None)
        if rec is None:
            rec = measure(name, raw, s, ["preset"], ref_x, subset)
            records.append(rec)
            log(f"[{name}] {pname}: {_summary(rec)}")
        elif "preset" not in rec["axes"]:
            rec["axes"].append("preset")
        rec.setdefault("presets", []).append(pname)


def _summary(rec: dict) -> str:
    if rec["rms_error_mm"] is None:
        return f"{setting_label(rec['settings']):40s} diverged: {rec['diverged'][:80]}"
    return (f"{setting_label(rec['settings']):40s} {rec['ms_per_frame']:9.1f} ms/frame  RMS {rec['rms_error_mm']:8.3f} mm"
            f"  max {rec['max_error_mm']:8.2f} mm  shape {rec['shape_error_mm']:7.3f} mm")


def measure(name: str, raw: dict, s: dict, axes: list, ref_x: torch.Tensor, subset, keep=None) -> dict:
    """Simulate one setting and compare it with the reference: one JSON record. ``keep``: a
    list to which the compared positions (F, S, N, 3) are appended (None: not kept)."""
    res = simulate_setting(raw, s)
    rec = {"scene": name, "settings": s, "axes": axes, "frames": raw["frames"],
           "strands": int(raw["groom"].get("strands", 1)), "error_strands": None if subset is None else int(len(subset)),
           "diverged": res["diverged"], "wall_s": round(res["wall_s"], 2)}
    if res["x"] is None:
        rec.update(ms_per_frame=None, rms_error_mm=None, max_error_mm=None, shape_error_mm=None, max_stretch=None)
        return rec
    x = res["x"] if subset is None else res["x"][:, torch.as_tensor(subset)]
    if keep is not None:
        keep.append(x)
    rec.update(ms_per_frame=round(res["ms"]["total"], 3),
               ms_per_stage={k: round(v, 3) for k, v in res["ms"].items() if k != "total"},
               **{k: float(f"{v:.5g}") for k, v in errors_mm(x, ref_x).items()},
               max_stretch=float(f"{res['stretch']:.4g}"))
    return rec


def run_breakdown(args, presets: dict, log) -> list[dict]:
    """Profiled per-stage ms/frame for each preset in each scene, and for ``balanced`` with each
    stage of the scene switched off in turn. Every row is profiled ``args.profile_repeats`` times in
    interleaved passes (so a burst of load from another process hits one pass of a row, not all)
    and per label the minimum is kept."""
    rows = []
    for name in args.scenes:
        raw = scene_raw(name, args.frames[name], args.strands.get(name))
        for preset in PRESET_NAMES:
            variants = [[]] + ([[st] for st in scene_stages(raw)] if preset == "balanced" else [])
            for off in variants:
                rows.append((name, raw, preset, dict(preset_setting(presets[preset], raw), off=off)))
    runs: list = [[] for _ in rows]
    for _ in range(args.profile_repeats):
        for i, (name, raw, preset, s) in enumerate(rows):
            runs[i].append(profile_setting(raw, s, args.profile_frames))
    out = []
    for (name, raw, preset, s), rs in zip(rows, runs):
        ms = {k: min(r[k] for r in rs) for k in rs[0]}
        out.append({"scene": name, "preset": preset, "settings": s, "ms_per_frame": {k: round(v, 3) for k, v in ms.items()}})
        off = s["off"]
        log(f"[breakdown {name}] {preset:8s} {'-' + off[0] if off else '':17s} "
            + " ".join(f"{k}={v:.1f}" for k, v in ms.items()))
    return out


def convergence_slopes(records: list[dict], infos: list[dict]) -> dict:
    """Per scene, the substeps sweep (N = 32, float32): RMS error against the scene's reference and
    against the same-N float64 time reference, and the least-squares slope of log(error) against
    log(M) for the latter over M ≤ M_time / 4 (further from the time reference its own error would
    steepen the slope). First order (backward Euler) gives −1."""
    out = {}
    for info in infos:
        sc = info["scene"]
        rs = sorted((r for r in records if r["scene"] == sc and "substeps" in r["axes"] and r["rms_error_mm"]),
                    key=lambda r: r["settings"]["substeps"])
        if len(rs) < 2:
            continue
        d = {"substeps": [r["settings"]["substeps"] for r in rs], "rms_error_mm": [r["rms_error_mm"] for r in rs],
             "time_rms_error_mm": [r.get("time_rms_error_mm") for r in rs], "slope": None, "fit_substeps": []}
        m_time = info.get("time_reference", {}).get("substeps")
        if m_time:  # at M = M_time the run is the time reference up to float32 round-off: not a measurement
            d["time_rms_error_mm"] = [e if m < m_time else None for m, e in zip(d["substeps"], d["time_rms_error_mm"])]
        fit = [(m, e) for m, e in zip(d["substeps"], d["time_rms_error_mm"]) if e and m_time and m <= m_time / 4]
        if len(fit) >= 2:
            d["slope"] = float(np.polyfit(np.log([f[0] for f in fit]), np.log([f[1] for f in fit]), 1)[0])
            d["fit_substeps"] = [f[0] for f in fit]
            d["time_reference_substeps"] = m_time
        out[sc] = d
    return out


# ---------------------------------------------------------------------------------- outputs
AXIS_STYLE = {"base": ("k", "*", "base (M=1, N=32, float32)"), "substeps": ("tab:blue", "o", "substeps M"),
              "particles": ("tab:orange", "s", "particles N"), "dtype": ("tab:green", "D", "float64"),
              "grid": ("tab:purple", "^", "hair–hair grid"), "stages": ("tab:red", "v", "a stage off"),
              "joint": ("0.6", ".", "joint M × N"), "preset": ("tab:cyan", "P", "preset")}


def _axis_of(r: dict) -> str:
    s = r["settings"]
    if setting_key(s) == setting_key(dict(BASE, grid=s.get("grid") and BASE["grid"], off=[])):
        return "base"
    for a in ("stages", "dtype", "grid", "substeps", "particles", "preset", "joint"):
        if a in r["axes"]:
            return a
    return r["axes"][0]


def _log_axes(ax) -> None:
    """Log–log axes with plain-number major labels and no minor labels."""
    from matplotlib.ticker import FuncFormatter, NullFormatter

    ax.set_xscale("log")
    ax.set_yscale("log")
    for axis in (ax.xaxis, ax.yaxis):
        axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        axis.set_minor_formatter(NullFormatter())


def plot_pareto(records: list[dict], scenes: list[str], path: Path) -> None:
    """Error (RMS, mm) against ms/frame per scene, log–log, with the Pareto front and the presets."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(scenes), figsize=(5.0 * len(scenes), 4.3), squeeze=False)
    for ax, sc in zip(axes[0], scenes):
        rs = [r for r in records if r["scene"] == sc and r["rms_error_mm"] is not None]
        seen = set()
        for r in rs:
            a = _axis_of(r)
            color, marker, label = AXIS_STYLE[a]
            ax.scatter(r["ms_per_frame"], r["rms_error_mm"], c=color, marker=marker, s=60 if a == "base" else 28,
                       label=label if a not in seen else None, zorder=3, edgecolors="none")
            seen.add(a)
            if a == "stages":
                ax.annotate("−" + r["settings"]["off"][0], (r["ms_per_frame"], r["rms_error_mm"]), fontsize=6,
                            xytext=(3, -8), textcoords="offset points", color="tab:red")
        pts = [(r["ms_per_frame"], r["rms_error_mm"]) for r in rs]
        front = pareto(pts)
        fx = [pts[i][0] for i in front]
        fy = [pts[i][1] for i in front]
        ax.step(fx, fy, where="post", color="k", lw=0.8, alpha=0.6, label="Pareto front", zorder=2)
        for r in rs:
            for p in r.get("presets", []):
                ax.scatter(r["ms_per_frame"], r["rms_error_mm"], s=160, facecolors="none", edgecolors="k", lw=1.2,
                           zorder=4)
                ax.annotate(p, (r["ms_per_frame"], r["rms_error_mm"]), fontsize=8, fontweight="bold",
                            xytext=(6, 4), textcoords="offset points")
        _log_axes(ax)
        ax.set_xlabel("ms / frame (CPU)")
        ax.set_ylabel("RMS vertex error vs reference (mm)")
        ax.set_title(sc)
        ax.grid(True, which="both", alpha=0.25)
    handles, labels = axes[0][0].get_legend_handles_labels()
    for ax in axes[0][1:]:
        for h, l in zip(*ax.get_legend_handles_labels()):
            if l not in labels:
                handles.append(h)
                labels.append(l)
    fig.legend(handles, labels, loc="lower center", ncol=5, fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.1, 1, 1))
    fig.savefig(path, dpi=90)
    plt.close(fig)


def plot_convergence(slopes: dict, path: Path) -> None:
    """RMS error against substeps M, log–log, per scene: against the same-N time reference (solid,
    the time discretisation alone) and against the full reference (dotted), with a slope −1 guide."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.0, 4.4))
    for k, (sc, d) in enumerate(slopes.items()):
        color = f"C{k}"
        t = [(m, e) for m, e in zip(d["substeps"], d["time_rms_error_mm"]) if e]
        if t:
            slope = f"slope {d['slope']:.2f}" if d["slope"] is not None else ""
            ax.plot([a for a, _ in t], [b for _, b in t], "o-", color=color,
                    label=f"{sc}: vs same-N time ref. ({slope})")
        ax.plot(d["substeps"], d["rms_error_mm"], "s:", color=color, alpha=0.7, label=f"{sc}: vs reference")
    firsts = [(d["substeps"][0], d["time_rms_error_mm"][0]) for d in slopes.values() if d["time_rms_error_mm"][0]]
    if firsts:
        m = np.array(next(iter(slopes.values()))["substeps"], dtype=float)
        top = min(e for _, e in firsts)
        ax.plot(m, top / m, "k--", lw=0.8, label="slope −1")
    _log_axes(ax)
    if slopes:
        ax.set_xticks(next(iter(slopes.values()))["substeps"])
    ax.set_xlabel("substeps M")
    ax.set_ylabel("RMS vertex error (mm)")
    ax.set_title("Error against substeps (N = 32, float32)", fontsize=10)
    ax.grid(True, which="both", alpha=0.25)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _fmt(v, digits=3) -> str:
    if v is None:
        return "—"
    if v == 0:
        return "0"
    return f"{v:.{digits}g}" if abs(v) < 1e4 else f"{v:.0f}"


def _find(records, scene, **kw):
    for r in records:
        if r["scene"] != scene:
            continue
        s = r["settings"]
        want = dict(BASE, grid=BASE["grid"] if s.get("grid") is not None else None, off=[])
        want.update(kw)
        if setting_key(s) == setting_key(want):
            return r
    return None


SCENE_TEXT = {
    "wisp": "16 strands leaving a patch along +x and curving down (0.3 m), head bobbing ±10 cm "
            "(keyframes of `wisp_comparison.toml`, AMS half); no head mesh, no stages",
    "head": "grown `straight` groom on the default head, head shaking 0.6 rad at 1.5 Hz, head collisions "
            "(64³ SDF) and hair–hair interaction",
    "roller_coaster": "`datasets/scenes/roller_coaster.toml`: grown `straight` groom, one 0.5 m loop at up to "
                      "4 g, head collisions, non-Hookean (plastic) integrity",
}


def _preset_rec(records, scene, pname):
    return next((r for r in records if r["scene"] == scene and pname in r.get("presets", [])), None)


def _row_cells(r) -> str:
    if r is None or r["rms_error_mm"] is None:
        return "—" if r is None else "diverged"
    return f"{r['ms_per_frame']:.1f}; {r['rms_error_mm']:.3g} / {r['max_error_mm']:.3g} / {r['shape_error_mm']:.3g}"


def write_markdown(path: Path, records, infos, breakdown, chosen, slopes, machine, args, wall_s, loads,
                   command: str) -> None:
    """docs/tradeoff.md from the measurements (see the module docstring for what each number is)."""
    scenes = [i["scene"] for i in infos]
    library = library_presets()
    L = ["# The speed–accuracy trade, the recommended presets and the cost of each stage", ""]
    L += ["Generated by `" + command + "` in "
          f"{wall_s / 60:.1f} min on {machine['cpu']} ({machine['cpu_cores']} cores), torch {machine['torch']}, "
          f"{machine['threads']} intra-op thread(s), CPU. Raw numbers: [`tradeoff.json`](tradeoff.json) (one record "
          "per setting: `scene`, `settings`, `ms_per_frame`, `rms_error_mm`, `max_error_mm`, `shape_error_mm`, ...). "
          "1-minute load average: " + ", ".join(f"{k} {v}" for k, v in loads) + ". Another process shared the "
          "2 cores, so absolute ms/frame are noisy; one torch thread was used because two threads on two shared "
          "cores made small problems up to 10× slower.", ""]
    if args.note:
        L += [args.note, ""]

    # ---- summary: presets
    L += ["## Recommended presets", "",
          "```python", "import ams_torch as at",
          "params = at.Params.preset(\"balanced\")          # the Params fields of the preset (substeps)",
          "extra = at.Params.preset_settings(\"balanced\")  # particles per strand, dtype, hair–hair grid",
          "```", "",
          "| preset | `Params.preset` sets | particles N | dtype | hair–hair grid | "
          + " | ".join(f"{sc}: ms/frame; RMS / max / shape error (mm)" for sc in scenes) + " |",
          "|---|---|---:|---|---:|" + "---|" * len(scenes)]
    for pname in PRESET_NAMES:
        c = chosen[pname]
        grid = c["grid"] or library[pname]["grid"]
        L.append(f"| `{pname}` | substeps = {c['substeps']} | {c['particles']} | {c['dtype']} | {grid}³ | "
                 + " | ".join(_row_cells(_preset_rec(records, sc, pname)) for sc in scenes) + " |")
    base_cells = " | ".join(_row_cells(_find(records, sc)) for sc in scenes)
    L.append(f"| library default `Params()` | substeps = 1 | 32 | float32 | 64³ | {base_cells} |")
    mismatch = [p for p in PRESET_NAMES if (library[p]["substeps"], library[p]["particles"], library[p]["dtype"])
                != (chosen[p]["substeps"], chosen[p]["particles"], chosen[p]["dtype"])
                or (chosen[p]["grid"] is not None and chosen[p]["grid"] != library[p]["grid"])]
    L += ["", "These are the presets the rule below picks from this run's data. "
          + ("`ams_torch.sim.params.PARAM_PRESETS` holds the same values." if not mismatch else
             "**`ams_torch.sim.params.PARAM_PRESETS` differs for " + ", ".join(f"`{p}`" for p in mismatch)
             + f"** (library: {', '.join(f'{p}: {library[p]}' for p in mismatch)}): update it or rerun."), ""]

    # ---- summary: findings
    L += ["## What the measurements say", ""]
    f = []

    def rms_of(sc, **kw):
        r = _find(records, sc, **kw)
        return None if r is None else r["rms_error_mm"]

    def ms_of(sc, **kw):
        r = _find(records, sc, **kw)
        return None if r is None else r["ms_per_frame"]

    def _doubling(sc):
        es = [rms_of(sc, particles=n) for n in sorted(args.particles)]
        es = [e for e in es if e]
        return (es[-1] / es[0]) ** (1 / (len(es) - 1)) if len(es) >= 2 else None

    def _monotone(sc):
        es = [rms_of(sc, particles=n) for n in sorted(args.particles)]
        return all(a is not None and b is not None and b <= a for a, b in zip(es, es[1:]))

    f.append("**Particles per strand.** RMS error at M = 1 for N = "
             + "/".join(map(str, args.particles)) + ": "
             + "; ".join(f"{sc} " + " / ".join(_fmt(rms_of(sc, particles=n)) for n in args.particles) + " mm"
                         for sc in scenes) + ". Each doubling of N multiplies the error by about "
             + ", ".join(f"{_doubling(sc):.2f} ({sc}{'' if _monotone(sc) else ', not monotone'})" for sc in scenes
                         if _doubling(sc)) + ". N is not only a "
             "resolution here: the constants are per particle (spring stiffness per pair, two pinned root particles), "
             "so a finer strand is also a slightly different material.")
    parts = []
    for sc in scenes:
        m_hi = max(args.substeps)
        n_hi = max(args.joint[sc][1])
        best = min((r for r in records if r["scene"] == sc and "joint" in r["axes"] and r["rms_error_mm"] is not None
                    and r["settings"]["particles"] == n_hi), key=lambda r: r["rms_error_mm"], default=None)
        parts.append(f"{sc}: N = 32, M = 1 → {m_hi}: {_fmt(rms_of(sc))} → {_fmt(rms_of(sc, substeps=m_hi))} mm"
                     + (f"; N = {n_hi}, M = 1 → {best['settings']['substeps']}: {_fmt(rms_of(sc, particles=n_hi))} → "
                        f"{_fmt(best['rms_error_mm'])} mm" if best else ""))
    f.append("**Substeps.** " + "; ".join(parts) + ".")
    first = [f"{sc} {d['slope']:.2f}" for sc, d in slopes.items() if d.get("slope") is not None
             and -1.4 <= d["slope"] <= -0.7]
    other = [f"{sc} {d['slope']:.2f}" for sc, d in slopes.items() if d.get("slope") is not None
             and not -1.4 <= d["slope"] <= -0.7]
    if first or other:
        f.append(("**Against a same-N reference the substeps converge at first order** (backward Euler) in "
                  + ", ".join(first) + " (log–log slopes)" if first else "")
                 + ("; " if first and other else "")
                 + (f"**not in {', '.join(other)}**, where the differences between runs do not shrink with M"
                    if other else "") + " (see *Convergence in substeps*).")
    for i in infos:
        checks = [c for c in i["checks"] if c.get("rms_error_mm") is not None]
        if checks:
            f.append(f"**The {i['scene']} reference is converged to about {max(c['rms_error_mm'] for c in checks):.3g} mm "
                     "RMS** (" + ", ".join(f"{setting_label(c['settings'])}: {c['rms_error_mm']:.3g} mm" for c in checks)
                     + "); errors below that are not resolved"
                     + ("" if votes(i, records) else ", and it is more than the default setting's error, so this scene "
                        "does not vote on the presets") + ".")
    dts = []
    for sc in scenes:
        a, b = rms_of(sc), rms_of(sc, dtype="float64")
        if a and b:
            dts.append(f"{sc} {abs(b - a) / a:.1%} at {ms_of(sc, dtype='float64') / ms_of(sc):.2f}× the time")
    if dts:
        small = all(abs(rms_of(sc, dtype="float64") - rms_of(sc)) <= 0.01 * rms_of(sc) for sc in scenes
                    if rms_of(sc) and rms_of(sc, dtype="float64"))
        f.append("**float64**: the RMS error changes by " + ", ".join(dts)
                 + ("; float32 round-off is far below the discretisation error." if small else "."))
    for sc in scenes:
        if _find(records, sc) and _find(records, sc)["settings"].get("grid"):
            g = [(gr, rms_of(sc, grid=gr), ms_of(sc, grid=gr)) for gr in args.grids]
            es = [e for _, e, _ in g if e is not None]
            f.append(f"**Hair–hair grid ({sc})**: " + ", ".join(f"{gr}³: {_fmt(e)} mm at {_fmt(t)} ms/frame"
                                                              for gr, e, t in g if e is not None)
                     + (". The grid's resolution moves the error by less than 5 %." if es and max(es) <= 1.05 * min(es)
                        else "."))
            hh_off, b0 = _find(records, sc, off=["hair_hair"]), _find(records, sc)
            if hh_off and b0 and hh_off["rms_error_mm"] is not None and \
                    abs(hh_off["rms_error_mm"] - b0["rms_error_mm"]) < 0.05 * b0["rms_error_mm"]:
                f.append(f"**Hair–hair barely matters in this {sc} scene**: switching it off changes the RMS error from "
                         f"{b0['rms_error_mm']:.4g} to {hh_off['rms_error_mm']:.4g} mm, so the scene supports the grid "
                         "recommendation only weakly: a denser groom with more strand–strand contact may want a finer "
                         "grid.")
    for sc in scenes:
        base = _find(records, sc)
        offs = [r for r in (_find(records, sc, off=[st]) for st in STAGES) if r is not None]
        if base and offs and base["rms_error_mm"] is not None:
            f.append(f"**Stages ({sc})**, each switched off at the default setting (RMS {base['rms_error_mm']:.3g} mm, "
                     f"{base['ms_per_frame']:.1f} ms/frame; one run each, so the ms are noisy: the profiled "
                     "breakdown below compares costs better): " + ", ".join(
                         f"−{r['settings']['off'][0]}: RMS {_fmt(r['rms_error_mm'])} mm, "
                         f"{_fmt(r['ms_per_frame'])} ms" if r["rms_error_mm"] is not None else
                         f"−{r['settings']['off'][0]}: diverged" for r in offs) + ".")
    for sc in scenes:
        base = _find(records, sc)
        nocol = _find(records, sc, off=["collisions"])
        if base and nocol and base.get("max_stretch") is not None and nocol.get("max_stretch") is not None \
                and base["max_stretch"] > 0.1:
            rounds = at.Params().collision_inextensibility if hasattr(at.Params(), "collision_inextensibility") else 0
            f.append(f"**Contact stretches the hair ({sc})**: the largest relative edge-length error at the end of a "
                     f"frame is {base['max_stretch']:.3g} with head collisions and {nocol['max_stretch']:.2g} without "
                     f"(the collision stage runs after inextensibility, SPEC §4, followed by {rounds} round(s) of "
                     "length restore + push-out, `Params.collision_inextensibility`), so fast hair–head contact still "
                     "leaves stretched edges for the next frame's stiff springs.")
    for i in infos:
        for fail in i.get("reference_failed", []):
            f.append(f"**The {i['scene']} reference at {setting_label(fail['settings'])} diverged** "
                     f"({fail['diverged'][:160]}); the reference is {setting_label(i['reference'])}.")
        for fail in i.get("time_reference_failed", []):
            f.append(f"**The {i['scene']} time reference at {setting_label(fail['settings'])} diverged** "
                     f"({fail['diverged'][:160]}).")
    div = [f"{r['scene']} {setting_label(r['settings'])}" for r in records if r["diverged"]]
    if div:
        f.append("**Diverged settings**: " + "; ".join(div) + ".")
    L += [f"- {x}" for x in f] + [""]

    L += ["## Error against cost", "", "![Pareto plot: RMS error against ms/frame](tradeoff_pareto.png)", "",
          "Each point is one setting; the black step line is the Pareto front of the scene (no other setting is "
          "both faster and more accurate); circled points are the presets.", ""]

    # ---- how chosen
    L += ["## How the presets were chosen", "",
          "`choose_presets` in the script, on this run's data"
          + (f" of the scenes {', '.join(chosen.get('_scenes', scenes))}" if chosen.get("_scenes", scenes) != scenes
             else "")
          + (" (" + ", ".join(sorted(set(scenes) - set(chosen.get("_scenes", scenes))))
             + " does not vote: a scene votes only if its reference did not diverge and its reference checks "
             "differ from it by less than the default setting's error)" if chosen.get("_scenes", scenes) != scenes
             else "")
          + ". Each preset has a cost budget ("
          + ", ".join(f"`{p}` ≤ {args.budgets[p]:g}×" for p in PRESET_NAMES)
          + " the cost of the library default M = 1, N = 32, float32, 64³ grid) and takes, on each axis, the "
          "cheapest option whose error is within 5 % of the lowest error that fits in its budget (smaller gains "
          "are not worth paying for and are below the noise of the timings):", "",
          "1. M and N jointly: for every (M, N) of the joint grid measured in all scenes (float32, every stage on), "
          "cost = geometric mean over the scenes of ms/frame relative to the scene's default and error = geometric "
          "mean of RMS error relative to the default's; the candidates are the points of this aggregated Pareto "
          "front (table below).",
          "2. The hair–hair grid: the grid sweep of the head scene (at M = 1, N = 32); its cost is the default "
          "frame with the hair–hair stage's measured time at that grid (the rest of the frame is the same work, "
          "and its timing noise would otherwise decide).",
          "3. The dtype: the dtype sweep (geometric mean over the scenes).", ""]
    near = [f"({x['substeps']}, {x['particles']}) at {x['cost']:.2f}× against `{p}`'s {args.budgets[p]:g}×"
            for x in chosen["_front"] for p in PRESET_NAMES if abs(x["cost"] / args.budgets[p] - 1) <= 0.25]
    if near:
        L += ["Timings on this shared machine vary by 20–30 % between runs, so a front point whose cost lies within "
              "25 % of a budget can fall on either side of it in a rerun: " + "; ".join(near) + ".", ""]
    L += ["| M | N | cost (× default) | error (× default) | on the front | preset |", "|---:|---:|---:|---:|---|---|"]
    front_keys = {(x["substeps"], x["particles"]) for x in chosen["_front"]}
    for pt in chosen["_points"]:
        k = (pt["substeps"], pt["particles"])
        tag = ", ".join(p for p in PRESET_NAMES if (chosen[p]["substeps"], chosen[p]["particles"]) == k)
        L.append(f"| {k[0]} | {k[1]} | {pt['cost']:.2f} | {pt['error']:.2f} | {'yes' if k in front_keys else ''} | "
                 f"{tag} |")
    L.append("")

    # ---- convergence
    L += ["## Convergence in substeps", "", "![RMS error against substeps](tradeoff_convergence.png)", "",
          "The substeps sweep (N = 32, float32, every stage on) against two references: the scene's reference "
          "(M, N and grid all refined) and a *time reference*, float64 at the same N = 32 (and 64³ grid) with many "
          "substeps, which isolates the time discretisation. The slope is fitted over M ≤ M_time / 4.", "",
          "| scene | against | " + " | ".join(f"M = {m}" for m in args.substeps) + " | log–log slope |",
          "|---|---|" + "---:|" * (len(args.substeps) + 1)]
    for sc, d in slopes.items():
        errs = dict(zip(d["substeps"], d["rms_error_mm"]))
        terrs = dict(zip(d["substeps"], d["time_rms_error_mm"]))
        if any(terrs.values()):
            L.append(f"| {sc} | time reference (M = {d.get('time_reference_substeps')}, N = 32) | "
                     + " | ".join(_fmt(terrs.get(m)) for m in args.substeps)
                     + f" | {_fmt(d['slope'], 2) if d['slope'] is not None else '—'} |")
        L.append(f"| {sc} | reference | " + " | ".join(_fmt(errs.get(m)) for m in args.substeps) + " | |")
    first = [sc for sc, d in slopes.items() if d.get("slope") is not None and -1.4 <= d["slope"] <= -0.7]
    other = [f"{sc} ({d['slope']:.2f})" for sc, d in slopes.items() if d.get("slope") is not None and sc not in first]
    L += ["", "RMS error in mm. "
          + (f"Against the same-N time reference the error falls at first order in {', '.join(first)}, as backward "
             "Euler should (slope ≈ −1; `tests/test_tradeoff.py` checks this on a small wisp). " if first else "")
          + (f"It does not in {', '.join(other)}: there the differences between runs hardly shrink with M, most "
             "likely because the once-per-frame stages (contact, plastic yield of the non-Hookean integrity, "
             "inextensibility) dominate them. " if other else "")
          + "Against the full reference the error stops falling after a few substeps: there the error of N = 32 "
          "particles dominates, and no number of substeps removes it.", ""]

    # ---- breakdown
    L += ["## Where a frame's time goes", "",
          f"`torch.profiler` over {args.profile_frames} frames (after a one-frame warm-up run; per label the "
          f"minimum of {getattr(args, 'profile_repeats', 1)} such runs) on the `ams_torch.*` "
          "labels of `ams_torch/integrator.py` and `ams_torch.apps.scene.simulate`, ms/frame, profiler overhead included "
          "(totals are above the un-profiled ms/frame). `springs`: edge/bend/torsion forces and Jacobian blocks; "
          "`biphasic`: integrity and angular couplings; `assembly`: the rest of the system assembly; `solve`: the "
          "banded solve; `other`: pose interpolation, position updates, divergence guard. The `balanced` rows with "
          "a stage switched off show that the stage's cost goes to 0 (`biphasic` off is plain MS; `guard` off is "
          "`check_every = 0`). `collisions` includes the collision stage's own length-restore rounds "
          "(`Params.collision_inextensibility`), which run only with inextensibility on: hence its smaller cost in "
          "the `−inextensibility` rows. Rows were profiled minutes apart on a shared machine, so compare a stage "
          "across rows rather than the totals.", ""]
    cols = ("springs", "biphasic", "assembly", "solve", "inextensibility", "hair_hair", "collisions", "other", "total")
    for sc in scenes:
        L += [f"**{sc}**", "", "| preset | switched off | " + " | ".join(cols) + " |",
              "|---|---|" + "---:|" * len(cols)]
        for b in breakdown:
            if b["scene"] == sc:
                off = b["settings"]["off"]
                L.append(f"| {b['preset']} | {off[0] if off else ''} | "
                         + " | ".join(_fmt(b["ms_per_frame"].get(c), 3) for c in cols) + " |")
        L.append("")

    # ---- method
    L += ["## What was measured", "",
          "| scene | groom | frames | reference (float64) | reference ms/frame | errors on |",
          "|---|---|---:|---|---:|---|"]
    for i in infos:
        ref = i["reference"]
        L.append(f"| {i['scene']} | {i['strands']} strands; {SCENE_TEXT[i['scene']]} | {i['frames']} | "
                 f"M = {ref['substeps']}, N = {ref['particles']}" + (f", grid {ref['grid']}³" if ref["grid"] else "")
                 + f" | {i['reference_ms_per_frame']:.0f} | "
                 + (f"{i['error_strands']} evenly spaced strands (exact: without hair–hair the strands are "
                    "independent)" if i["error_strands"] else "all strands") + " |")
    L += ["",
          "- **Settings.** The base setting is the library default: M = 1 substep, N = 32 particles per strand, "
          "float32, a 64³ hair–hair grid where hair–hair is on, every stage on. Around it each axis is swept alone: "
          f"M ∈ {{{', '.join(map(str, args.substeps))}}}, N ∈ {{{', '.join(map(str, args.particles))}}}, "
          f"dtype ∈ {{{', '.join(args.dtypes)}}}, grid ∈ {{{', '.join(map(str, args.grids))}}} (head only), and each "
          "stage switched off in turn (`−biphasic` is plain mass-spring, κ_I = κ_α = 0; `−guard` is "
          "`check_every = 0`). Then a joint M × N grid in float32 ("
          + "; ".join(f"{sc}: M ∈ {{{', '.join(map(str, args.joint[sc][0]))}}} × N ∈ "
                      f"{{{', '.join(map(str, args.joint[sc][1]))}}}" for sc in scenes)
          + ") and the presets. The full cross product (5 × 4 × 2 × 3 × stages) was not run: it does not fit "
          "in 30 minutes on 2 cores.",
          "- **Grooms at each N.** Each groom is grown (or built) at N particles, i.e. resampled uniformly in arc "
          "length from the same curves, so every N describes the same hair.",
          "- **Error at matching material points.** Particle k of an N-particle strand sits at the rest arc-length "
          "fraction k/(N − 1); the reference's position there is interpolated linearly between its two neighbouring "
          "particles. RMS and max are over all frames, strands and particles (mm). The shape error is the ablations' "
          "metric (`ams_torch.testing.shape_deviation(align=True)`): each strand rigidly aligned to the reference "
          "strand, mean particle distance, averaged over strands and frames; it ignores a strand swinging rigidly "
          "out of phase.",
          "- **ms/frame** is the wall time of `Simulator.step` per frame (mean over the run, from "
          "`ams_torch.apps.scene.simulate`), with the divergence guard on.", ""]
    checks = [(i["scene"], c) for i in infos for c in i["checks"]]
    if checks:
        L += ["How converged the references are (the reference with half the substeps, or half the particles; "
              "the reference's own error is of this order):", "",
              "| scene | check run | RMS vs reference (mm) | max (mm) | shape (mm) |", "|---|---|---:|---:|---:|"]
        for sc, c in checks:
            L.append(f"| {sc} | {setting_label(c['settings'])} | {_fmt(c.get('rms_error_mm'))} | "
                     f"{_fmt(c.get('max_error_mm'))} | {_fmt(c.get('shape_error_mm'))} |")
        L.append("")
    for sc in scenes:
        L += [f"## All settings: {sc}", "",
              "| setting | sweeps | ms/frame | RMS (mm) | max (mm) | shape (mm) | max stretch |",
              "|---|---|---:|---:|---:|---:|---:|"]
        for r in sorted((r for r in records if r["scene"] == sc), key=lambda r: (r["ms_per_frame"] or 1e18)):
            L.append(f"| {setting_label(r['settings'])} | {', '.join(r['axes'])} | {_fmt(r['ms_per_frame'])} | "
                     f"{_fmt(r['rms_error_mm'])} | {_fmt(r['max_error_mm'])} | {_fmt(r['shape_error_mm'])} | "
                     f"{_fmt(r['max_stretch'], 2) if r['max_stretch'] is not None else 'diverged'} |")
        L.append("")
    path.write_text("\n".join(L))


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes", nargs="+", default=["wisp", "head", "roller_coaster"],
                   choices=("wisp", "head", "roller_coaster"))
    p.add_argument("--quick", action="store_true",
                   help="smoke run: tiny scenes, few frames, small references, output under out/tradeoff_quick")
    p.add_argument("--threads", type=int, default=1, help="torch intra-op threads (default 1; 0: torch's default)")
    p.add_argument("--profile-frames", type=int, help="frames profiled per breakdown row (default 5; --quick: 1)")
    p.add_argument("--out", type=Path, help="output folder (default docs/; --quick: out/tradeoff_quick)")
    p.add_argument("--render-only", action="store_true",
                   help="rewrite tradeoff.md and the plots from an existing tradeoff.json in --out (no simulation)")
    p.add_argument("--note", default="", help="a sentence added to tradeoff.md (e.g. machine load)")
    args = p.parse_args(argv)
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    q = args.quick
    args.frames = {"wisp": 10, "head": 4, "roller_coaster": 8} if q else {"wisp": 120, "head": 30, "roller_coaster": 100}
    args.strands = {"wisp": 4, "head": 60, "roller_coaster": 30} if q else {"wisp": 16, "head": 1000, "roller_coaster": 300}
    args.substeps = (1, 2, 4) if q else SUBSTEPS
    args.particles = (16, 32) if q else PARTICLES
    args.dtypes = tuple(DTYPES)
    args.grids = (32, 64) if q else GRIDS
    args.ref_grid = 64 if q else 128
    args.ref_substeps = {"wisp": 8, "head": 4, "roller_coaster": 4} if q else {"wisp": 32, "head": 16, "roller_coaster": 32}
    args.ref_particles = {"wisp": 48, "head": 48, "roller_coaster": 48} if q else {"wisp": 128, "head": 96,
                                                                                  "roller_coaster": 96}
    args.ref_strands = {"roller_coaster": 10 if q else 60}
    args.ref_checks = ({"wisp": ("substeps", "particles")} if q else
                       {"wisp": ("substeps", "particles"), "roller_coaster": ("substeps", "particles")})
    args.joint = ({sc: ((1, 2), (16, 32)) for sc in ("wisp", "head", "roller_coaster")} if q else
                  {"wisp": (SUBSTEPS, PARTICLES), "head": ((1, 2, 4, 8), (16, 32, 64)),
                   "roller_coaster": ((1, 2, 4, 8), PARTICLES)})
    args.budgets = {"fast": 0.9, "balanced": 2.5, "accurate": 6.0}
    args.time_ref_substeps = {"wisp": 8, "head": 8, "roller_coaster": 8} if q else {"wisp": 64, "head": 16,
                                                                                     "roller_coaster": 64}
    args.profile_frames = args.profile_frames or (1 if q else 5)
    args.profile_repeats = 1 if q else 2
    out = args.out or (REPO / "out" / "tradeoff_quick" if q else REPO / "docs")
    out.mkdir(parents=True, exist_ok=True)

    if args.render_only:
        data = json.loads((out / "tradeoff.json").read_text())
        if isinstance(data, dict):  # older layout: {"records": [...], "meta": {...}}
            records, meta = data["records"], data["meta"]
        else:
            records, meta = data, read_meta(out / "tradeoff.md")
        for k, v in meta["args"].items():
            setattr(args, k, {kk: tuple(tuple(x) for x in vv) for kk, vv in v.items()} if k == "joint" else v)
        _write_outputs(out, records, meta["scenes"], meta["breakdown"], meta["presets_chosen"], meta["machine"], args,
                       meta["wall_s"], [tuple(x) for x in meta["load_avg_1min"]], meta)
        print(f"rewrote {out / 'tradeoff.md'} and the plots from {out / 'tradeoff.json'}")
        return

    machine = machine_info()
    loads = [("at the start", machine["load_avg_1min_at_start"])]
    t_start = time.perf_counter()

    def log(msg):
        print(f"[{time.perf_counter() - t_start:7.1f} s] {msg}", flush=True)

    # warm up: native solver library, SDF cache, allocator
    simulate_setting(scene_raw("wisp", 2, 2), dict(BASE, particles=8, off=[]))
    records, infos, refs = [], [], {}
    for sc in args.scenes:
        recs, info, ref_x, subset = run_scene(sc, args, log)
        records += recs
        infos.append(info)
        refs[sc] = (ref_x, subset)
        loads.append((f"after {sc}", info["load_avg_1min_at_end"]))
        log(f"[{sc}] done in {info['wall_s']:.0f} s")
    select = [i["scene"] for i in infos if votes(i, records)] or list(args.scenes)
    chosen = choose_presets(records, select, args.budgets)
    chosen["_scenes"] = select
    presets = {p: {k: chosen[p][k] for k in ("substeps", "particles", "dtype", "grid")} for p in PRESET_NAMES}
    for p in PRESET_NAMES:
        presets[p]["grid"] = presets[p]["grid"] or library_presets()[p]["grid"]
        log(f"preset {p}: M={presets[p]['substeps']} N={presets[p]['particles']} {presets[p]['dtype']} "
            f"grid={presets[p]['grid']} (cost {chosen[p]['cost']:.2f}×, error {chosen[p]['error']:.2f}× the default)")
    for sc in args.scenes:
        measure_presets(sc, scene_raw(sc, args.frames[sc], args.strands.get(sc)), presets, *refs[sc], records, log)
    refs.clear()
    breakdown = run_breakdown(args, presets, log)
    slopes = convergence_slopes(records, infos)
    wall = time.perf_counter() - t_start
    loads.append(("at the end", round(os.getloadavg()[0], 2)))
    meta = {"command": f"python scripts/bench_tradeoff.py {shown_args(hide=('--note',))}".strip(), "wall_s": round(wall, 1),
            "machine": machine, "load_avg_1min": loads, "scenes": infos, "presets_chosen": chosen,
            "presets_library": library_presets(), "convergence": slopes, "breakdown": breakdown,
            "args": {k: getattr(args, k) for k in ("substeps", "particles", "dtypes", "grids", "joint", "budgets",
                                                   "profile_frames", "profile_repeats", "note")}}
    (out / "tradeoff.json").write_text("[\n" + ",\n".join(json.dumps(r) for r in records) + "\n]\n")
    _write_outputs(out, records, infos, breakdown, chosen, machine, args, wall, loads, meta)
    lib = library_presets()
    for p in PRESET_NAMES:
        if presets[p] != lib[p]:
            log(f"NOTE: the library's preset {p} is {lib[p]}; this run picks {presets[p]}")
    log(f"wrote {out / 'tradeoff.md'}, tradeoff.json, tradeoff_pareto.png, tradeoff_convergence.png in {wall / 60:.1f} min")


META_TAG = "bench_tradeoff meta (read by --render-only):"


def read_meta(md: Path) -> dict:
    """The run's metadata from the HTML comment at the end of tradeoff.md."""
    text = md.read_text()
    start = text.rindex("<!-- " + META_TAG) + len("<!-- " + META_TAG)
    return json.loads(text[start:text.index("-->", start)])


def _write_outputs(out: Path, records, infos, breakdown, chosen, machine, args, wall, loads, meta) -> None:
    scenes = [i["scene"] for i in infos]
    plot_pareto(records, scenes, out / "tradeoff_pareto.png")
    slopes = convergence_slopes(records, infos)
    plot_convergence(slopes, out / "tradeoff_convergence.png")
    path = out / "tradeoff.md"
    write_markdown(path, records, infos, breakdown, chosen, slopes, machine, args, wall, loads, meta["command"])
    # "--" cannot occur in an HTML comment; outside JSON strings it cannot occur at all
    blob = json.dumps(meta).replace("--", "-\\u002d")
    path.write_text(path.read_text() + f"\n<!-- {META_TAG} {blob} -->\n")


if __name__ == "__main__":
    main()
