"""Parameter identification through whole rollouts (docs/identification.md): the cases, the studies
around them and the page. The fits themselves are library code, :mod:`ams_torch.apps.identify`
(parametrisations, rollout loss, finite-difference check, Adam / L-BFGS fit), on checkpointed
rollouts (:func:`ams_torch.sim.rollout`, ``checkpoint_every`` frames per recomputed segment).

Cases (float64, dt = 1/60 s):

    shake           κ_I (integrity rate ω_I²), drag and stretch rigidity EA of a sphere groom
                    without bending/torsion proxies, from a 60-frame shake simulated at N = 64,
                    M = 8 and fitted at N = 32, M = 2 (compared at material points)
    shake_control   the same fit against a target made at the fit's own resolution
    shake_default   the same three fields with the library's default material (bending and
                    torsion proxies on), to measure what the stretch rigidity does there
    coaster         the non-Hookean transition from a roller-coaster ride (4 g loop, 92 frames),
                    target at N = 64, M = 8, fitted at N = 32, M = 8
    coaster_control the same fit against a target at the fit's resolution (N = 32, M = 2)

Before any fit, the gradient of its loss is compared with central finite differences along
random directions of the unconstrained parameters, on the full rollout. Peak memory of one
loss + backward with and without checkpointing is measured in subprocesses (the high-water mark
of resident memory, VmHWM, reset before the rollout) and the bytes autograd saves are counted
with ``torch.autograd.graph.saved_tensors_hooks``.

    .venv/bin/python scripts/identify.py                  # → docs/identification.{md,json}, docs/identification*.png
    .venv/bin/python scripts/identify.py --quick          # smoke run, a few minutes
    .venv/bin/python scripts/identify.py --render-only    # the page and plots again from the JSON
    .venv/bin/python scripts/identify.py --memory-only    # rerun the memory rows only, keep the rest of the JSON
    .venv/bin/python scripts/identify.py --scale-only     # the fit at scale (1,000 strands, every stage, per-strand drag)
    .venv/bin/python scripts/identify.py --cases shake coaster --max-evals 20
"""
from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable, Sequence

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import ams_torch as at  # noqa: E402
from ams_torch._bench import machine_info, shown_args  # noqa: E402
from ams_torch.apps.identify import (  # noqa: E402,F401  (the script's namespace is the tests' too)
    POINTS, Fraction, Log, fd_check, fit, fit_simulator, loss_and_grad, loss_at, loss_mm2, rollout_loss,
    set_values, trajectory, unconstrained, values)
from ams_torch.apps.identify import make_target as _make_target  # noqa: E402
from ams_torch.apps.motion import RollerCoaster  # noqa: E402
from ams_torch.grooms.groom import resample_strands  # noqa: E402
from ams_torch.apps.motion import Shake  # noqa: E402
from ams_torch.testing import sphere_groom  # noqa: E402

F64 = torch.float64
DT = 1.0 / 60.0
#: the memory probe's checkpointing: none, every frame, and segments of ⌈√frames⌉ frames
CHECKPOINT_MODES = ("none", "every frame", "sqrt")


def checkpoint_every(mode: str, frames: int) -> int:
    """``checkpoint_every`` of a memory-probe mode (see :data:`CHECKPOINT_MODES`)."""
    return {"none": 0, "every frame": 1, "sqrt": math.ceil(math.sqrt(frames))}[mode]


def make_target(fine: torch.Tensor, n: int, substeps: int, params: at.Params, poses) -> torch.Tensor:
    """The captured motion: ``fine`` polylines resampled to n particles, simulated with ``params``
    at ``substeps`` (float64, torch backend), positions at the material points: (F, S, points, 3)."""
    return _make_target(resample_strands(fine, n), params.replace(substeps=substeps), poses)


# ------------------------------------------------------------------------ cases
SHAKE_TRUE = {"integrity_rate": 100.0, "drag": 1.5, "stretch_rigidity": 8e-3}
SHAKE_START = {"integrity_rate": 300.0, "drag": 0.6, "stretch_rigidity": 2.4e-2}  # ×3, ÷2.5, ×3
NO_PROXIES = {"bend_rigidity": 0.0, "torsion_rigidity": 0.0}
COASTER_RATE = 1000.0  # ω_I², s⁻² (see the docs: at 100 every particle yields far past the breaking point)
COASTER_BREAK = 1.0


def shake_motion(frames: int = 60):
    return Shake(amplitude=0.6, frequency=1.5, translation=(0.03, 0.03, 0.0)).poses(frames, DT, dtype=F64)


def coaster_motion(frames: int = 92):
    """A 0.5 m loop at up to 4 g (1.42 s) and a few frames at rest: 92 frames."""
    return RollerCoaster(radius=0.5, peak_g=4.0).poses(frames, DT, dtype=F64)


def case_spec(name: str, quick: bool = False) -> dict:
    """The definition of a case: fine groom, motion, materials, resolutions, true and start values."""
    strands = 6 if quick else 12
    fine = sphere_groom(strands, 257, seed=0, dtype=F64)
    if name.startswith("shake"):
        frames = 20 if quick else 60
        base = dict(NO_PROXIES) if name != "shake_default" else {}
        control = name == "shake_control"
        return {"name": name, "fine": fine, "poses": shake_motion(frames), "base": base,
                "true": dict(SHAKE_TRUE), "start": dict(SHAKE_START),
                "fields": {k: Log() for k in SHAKE_TRUE},
                "target_res": (32, 2) if control else (64, 8), "fit_res": (32, 2),
                "fits": [("lbfgs", 30), ("adam", 60)] if name == "shake" else [("lbfgs", 30)],
                "what": f"{strands} strands of a 0.25 m sphere groom ({'default material' if name == 'shake_default' else 'no bending/torsion proxies'}), "
                        f"{frames} frames of a 0.6 rad, 1.5 Hz shake about +y with a 3 cm sway in x and y"}
    if name.startswith("coaster"):
        frames = 40 if quick else 92
        control = name == "coaster_control"
        base = {"integrity_model": "nonhookean", "integrity_rate": COASTER_RATE, "integrity_break": COASTER_BREAK}
        return {"name": name, "fine": fine, "poses": coaster_motion(frames), "base": base,
                "true": {"integrity_transition": 0.5}, "start": {"integrity_transition": 0.25},
                "fields": {"integrity_transition": Fraction(COASTER_BREAK)},
                "target_res": (32, 2) if control else (64, 8), "fit_res": (32, 2) if control else (32, 8),
                "fits": [("adam", 30), ("lbfgs", 20)] if control else [("adam", 30)],
                "what": f"{strands} strands of a 0.25 m sphere groom, non-Hookean integrity (ω_I² = {COASTER_RATE:g} s⁻², "
                        f"break {COASTER_BREAK}), {frames} frames of RollerCoaster(radius=0.5, peak_g=4)"}
    raise ValueError(f"unknown case {name!r}")


def case_simulator(spec: dict, values_: Dict[str, float]) -> at.Simulator:
    n, m = spec["fit_res"]
    params = at.Params(substeps=m, **spec["base"], **values_)
    return fit_simulator(resample_strands(spec["fine"], n), params, spec["fields"])


def case_target(spec: dict) -> torch.Tensor:
    n, m = spec["target_res"]
    return make_target(spec["fine"], n, m, at.Params(**spec["base"], **spec["true"]), spec["poses"])


def sensitivity(spec: dict, target: torch.Tensor, factor: float = 2.0) -> dict:
    """Loss (mm²) at the true values at the fit resolution, and the RMS change of the fitted
    trajectory (mm) when one field is multiplied by ``factor`` (the others true)."""
    sim = case_simulator(spec, spec["true"])
    with torch.no_grad():
        base = trajectory(sim, spec["poses"], checkpoint_every=0)
        out = {"loss_at_truth_mm2": float(loss_mm2(base, target)), "factor": factor, "rms_change_mm": {}}
        for k, v in spec["true"].items():
            set_values(sim, {**spec["true"], k: v * factor if k != "integrity_transition" else min(v * factor, 0.95)})
            out["rms_change_mm"][k] = math.sqrt(float(loss_mm2(trajectory(sim, spec["poses"], checkpoint_every=0),
                                                                base)))
    return out


PROFILE_RESOLUTIONS = ((32, 2), (32, 8), (64, 2), (64, 8))


def resolution_profiles(spec: dict, target: torch.Tensor, field: str, grid: Sequence[float],
                        resolutions=PROFILE_RESOLUTIONS) -> dict:
    """Where the cross-resolution bias of a fit comes from: the loss against the case's target along
    one field (the others at their true values) for simulations at several (N, M), forward only
    (the library's default backend: the native kernels where built). Returns {"field", "grid",
    "rows": [{"n", "m", "loss": [...], "best": the grid value of least loss}]}."""
    rows = []
    for n, m in resolutions:
        rest = resample_strands(spec["fine"], n)
        losses = []
        for v in grid:
            params = at.Params(substeps=m, **spec["base"], **{**spec["true"], field: v})
            sim = at.Simulator(rest, params, dtype=F64)
            with torch.no_grad():
                losses.append(float(loss_mm2(trajectory(sim, spec["poses"], checkpoint_every=0), target)))
        best = grid[min(range(len(grid)), key=losses.__getitem__)]
        rows.append({"n": n, "m": m, "loss": losses, "best": best})
    return {"case": spec["name"], "field": field, "grid": list(grid), "rows": rows}


def transition_scan(spec: dict, target: torch.Tensor, ts: Sequence[float], grad: bool = True) -> dict:
    """Loss and dloss/dt along the transition t (the other fields as in the case)."""
    sim = case_simulator(spec, spec["start"])
    rows = []
    for t in ts:
        set_values(sim, {"integrity_transition": t})
        if grad:
            loss, g = loss_and_grad(sim, spec["poses"], target)
            z = float(unconstrained(sim)["integrity_transition"].detach())
            dtdz = COASTER_BREAK * torch.sigmoid(torch.tensor(z)).item() * (1 - torch.sigmoid(torch.tensor(z)).item())
            rows.append({"t": t, "loss": loss, "dloss_dt": g["integrity_transition"] / dtdz})
        else:
            rows.append({"t": t, "loss": loss_at(sim, spec["poses"], target)})
    return {"rows": rows}


# ------------------------------------------------------------------------ at scale
SCALE_FRAMES = 30


def scale_spec(quick: bool = False) -> dict:
    """A groom at scale: 1,000 strands × 32 particles hanging from the default head, head contact
    (64³ SDF) and hair–hair (32³ grid) on, a shake of 30 frames; learnable: the integrity rate (one
    value) and the drag per strand (S, 1), true drags 1.5 s⁻¹ × exp(0.3 ξ), ξ ~ N(0, 1) seeded."""
    from ams_torch.geometry.sdf import SDFGrid
    from ams_torch.grooms.head import hanging_groom

    strands = 64 if quick else 1000
    head = at.default_head(4)
    grid = SDFGrid.from_mesh(head, resolution=64)
    rest = hanging_groom(head, strands, 32, 0.25, sdf=grid, seed=1, dtype=F64)
    xi = torch.randn(strands, 1, generator=torch.Generator().manual_seed(5), dtype=F64)
    return {"rest": rest, "grid": grid, "poses": shake_motion(8 if quick else SCALE_FRAMES),
            "true": {"integrity_rate": 100.0, "drag": 1.5 * torch.exp(0.3 * xi)},
            "start": {"integrity_rate": 200.0, "drag": torch.full((strands, 1), 3.0, dtype=F64)},
            "stages": {"colliders": [at.MeshCollider(grid)], "hair_hair": at.HairHair(resolution=32)},
            "what": f"{strands} strands × 32 particles hanging from the default head (`hanging_groom`), head "
                    f"contact (64³ SDF) and hair–hair (32³ grid) on, {8 if quick else SCALE_FRAMES} frames of the "
                    "shake; target and fit at the same resolution (M = 1), float64, native backend"}


def run_scale(args, log=print) -> dict:
    """Fit the integrity rate and the per-strand drag of :func:`scale_spec` (Adam or L-BFGS) on the native
    backend (forward: fused kernels; backward: the native adjoints of every stage: the dynamics, the
    collisions, the hair–hair grid, the frame's end), after a finite-difference check of the gradient
    on the full rollout."""
    spec = scale_spec(args.quick)
    stages = spec["stages"]
    t0 = time.perf_counter()
    target = _make_target(spec["rest"], at.Params(**spec["true"]), spec["poses"], backend="native", **stages)
    t_target = time.perf_counter() - t0
    sim = fit_simulator(spec["rest"], at.Params(**spec["start"]), {"integrity_rate": Log(), "drag": Log()},
                        backend="native", **stages)
    t0 = time.perf_counter()
    fd = fd_check(sim, spec["poses"], target, directions=2, steps=(1e-4,))
    t_fd = time.perf_counter() - t0
    log(f"[scale] target {t_target:.0f} s; FD check {t_fd:.0f} s: " +
        ", ".join(f"{r['autograd']:.6g} vs {r['fd']['0.0001']:.6g} (rel {r['best_rel']:.1e})" for r in fd["directions"]))
    hist = fit(sim, spec["poses"], target, iterations=args.scale_evals, optimizer=args.scale_optimizer,
               lr=args.scale_lr, lr_final=args.scale_lr / 5, log=log)
    true_drag = spec["true"]["drag"].reshape(-1)
    fitted = torch.tensor(hist["final_values"]["drag"], dtype=F64).reshape(-1)
    start = spec["start"]["drag"].reshape(-1)
    rel = (fitted / true_drag - 1).abs()
    rel_start = (start / true_drag - 1).abs()
    corr = float(torch.corrcoef(torch.stack((fitted, true_drag)))[0, 1])
    out = {"what": spec["what"], "strands": int(spec["rest"].shape[0]), "frames": len(spec["poses"]),
           "optimizer": args.scale_optimizer + (f" (lr {args.scale_lr:g} → {args.scale_lr / 5:g})"
                                                if args.scale_optimizer == "adam" else " (strong Wolfe)"),
           "evaluations": hist["iterations"], "wall_s": hist["wall_s"], "s_per_evaluation": hist["s_per_iteration"],
           "target_s": t_target, "fd": {"rows": [{k: v for k, v in r.items() if k != "d"} for r in fd["directions"]],
                                        "worst_rel": fd["worst_rel"], "s": t_fd},  # (not the 1,001-value directions)
           "loss": hist["loss"], "final_loss": hist["final_loss"],
           "integrity_rate": {"true": spec["true"]["integrity_rate"], "start": spec["start"]["integrity_rate"],
                              "fitted": hist["final_values"]["integrity_rate"]},
           "drag": {"median_rel_error": float(rel.median()), "p90_rel_error": float(rel.quantile(0.9)),
                    "max_rel_error": float(rel.max()), "median_rel_error_at_start": float(rel_start.median()),
                    "correlation": corr, "true_range": [float(true_drag.min()), float(true_drag.max())]}}
    log(f"[scale] {out['evaluations']} evaluations, {out['wall_s'] / 60:.1f} min: integrity rate "
        f"{out['integrity_rate']['fitted']:.4g} (true 100); drag per strand median error "
        f"{out['drag']['median_rel_error']:.2%} (start {out['drag']['median_rel_error_at_start']:.2%}), "
        f"p90 {out['drag']['p90_rel_error']:.2%}, correlation {corr:.3f}")
    return out


def render_scale(sc: dict, meta: dict) -> list:
    """The page's section of the fit at scale."""
    d, k = sc["drag"], sc["integrity_rate"]
    fd = "; ".join(f"{r['autograd']:.8g} vs {r['fd']['0.0001']:.8g} (rel {r['best_rel']:.1e})" for r in sc["fd"]["rows"])
    return ["## At scale: 1,000 strands, head contact and hair–hair, a per-strand field", "",
            f"Generated by `{meta.get('scale_command', 'python scripts/identify.py --scale-only')}`. {sc['what']}. "
            "Learnable: the integrity rate ω_I² (one value, log-parametrised) and the drag per strand (an (S, 1) "
            "field, one log-value per strand): "
            f"{sc['strands'] + 1} unknowns. {sc.get('optimizer', 'lbfgs (strong Wolfe)').replace('lbfgs', 'L-BFGS')}, each evaluation a full "
            "rollout checkpointed "
            "every frame (`ams_torch.sim.rollout`) and its backward: the native adjoints of every stage, the "
            "strand dynamics (substep by substep, with the contact's), the collisions, the hair–hair grid (P2G, "
            "pressure, G2P) and the frame's end (`ams_torch.native_status()[\"gradients\"]`).", "",
            f"- Gradient check on the full rollout, two random directions, h = 1e-4: {fd}.",
            f"- Integrity rate: {k['start']:g} → {k['fitted']:.5g} s⁻² (true {k['true']:g}).",
            f"- Drag per strand (true {d['true_range'][0]:.2f}–{d['true_range'][1]:.2f} s⁻¹, start 3.0 everywhere): "
            f"median relative error {d['median_rel_error']:.2%} (at the start {d['median_rel_error_at_start']:.2%}), "
            f"90th percentile {d['p90_rel_error']:.2%}, largest {d['max_rel_error']:.2%}; correlation of fitted "
            f"and true {d['correlation']:.3f}.",
            f"- Loss {sc['loss'][0]:.4g} → {sc['final_loss']:.4g} mm² in {sc['evaluations']} evaluations; wall "
            f"{sc['wall_s'] / 60:.1f} min ({sc['s_per_evaluation']:.0f} s per evaluation on the loaded shared machine, "
            f"1 thread: an order of magnitude, not a benchmark).", ""]


# ------------------------------------------------------------------------ memory
def _vm(field: str) -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1]) * 1024
    raise RuntimeError(field)


def saved_bytes(fn: Callable[[], torch.Tensor]) -> tuple:
    """(bytes of distinct storages autograd saves for backward while running fn(), fn()'s output),
    counted with ``saved_tensors_hooks`` (inside checkpointed regions the checkpoint's own hooks
    take over, so those are not seen: what is seen is what stays saved outside them)."""
    seen = {}

    def pack(t):
        s = t.untyped_storage()
        seen[(s.data_ptr(), s.nbytes())] = s.nbytes()
        return t

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        out = fn()
    return sum(seen.values()), out


def memory_probe(name: str, checkpoint: str, quick: bool = False) -> dict:
    """One loss + backward of a case at its start values, in this process: the rise of the resident
    high-water mark (VmHWM, reset through /proc/self/clear_refs before the rollout) over the resident
    size before it, wall time, and the saved-tensor bytes of a second, identical rollout.
    ``checkpoint``: one of :data:`CHECKPOINT_MODES`."""
    torch.set_num_threads(1)
    spec = case_spec(name, quick)
    sim = case_simulator(spec, spec["start"])
    frames = len(spec["poses"])
    every = checkpoint_every(checkpoint, frames)
    target = torch.zeros(frames, sim.model.num_strands, POINTS, 3, dtype=F64)  # values do not matter
    loss_and_grad(sim, spec["poses"][:2], target[:2], min(every, 2))  # warm-up (lazy inits)
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")
    before = _vm("VmRSS")
    t0 = time.perf_counter()
    loss_and_grad(sim, spec["poses"], target, every)
    wall = time.perf_counter() - t0
    peak = _vm("VmHWM")
    saved, loss = saved_bytes(lambda: rollout_loss(sim, spec["poses"], target, checkpoint_every=every))
    loss.backward()
    state = sim.initial_state()
    per_frame_input = sum(t.numel() * t.element_size() for t in (state.x, state.v, state.ghost_rest))
    return {"case": name, "checkpoint": checkpoint, "checkpoint_every": every, "frames": frames,
            "rss_before_MiB": before / 2 ** 20, "peak_rise_MiB": (peak - before) / 2 ** 20, "wall_s": wall,
            "saved_outside_checkpoints_MiB": saved / 2 ** 20, "frame_state_KiB": per_frame_input / 1024}


def memory_in_subprocess(name: str, checkpoint: str, quick: bool) -> dict:
    cmd = [sys.executable, str(Path(__file__).resolve()), "--memory-probe", name, "--probe-checkpoint",
           checkpoint] + (["--quick"] if quick else [])
    res = subprocess.run(cmd, capture_output=True, text=True, check=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
    return json.loads(res.stdout.strip().splitlines()[-1])


# ------------------------------------------------------------------------ report
DISCUSSION = ("<!-- discussion: hand-written, kept when the script rewrites this page -->",
              "<!-- /discussion -->")


def kept_discussion(page: Path) -> str:
    """The hand-written discussion block of an existing page (between the DISCUSSION markers)."""
    text = page.read_text() if page.exists() else ""
    a, b = text.find(DISCUSSION[0]), text.find(DISCUSSION[1])
    if a < 0 or b < a:
        return "\n".join(DISCUSSION)
    return text[a:b + len(DISCUSSION[1])]


def render(results: dict, out: Path) -> None:
    meta = results["meta"]
    L = ["# Parameter identification through rollouts", "",
         f"Generated by `{meta['command']}` in {meta['wall_s'] / 60:.1f} min on {meta['machine']['cpu']} "
         f"({meta['machine']['cpu_cores']} cores shared with other jobs; load average {meta['load_start']} at the start, "
         f"{meta['load_end']} at the end: wall times are noisy, read them as orders of magnitude), torch "
         f"{meta['machine']['torch']}, 1 thread, float64. Raw numbers: [`identification.json`](identification.json).",
         ""]
    L += [results.get("narrative", ""), ""]
    L += ["## Cases", ""]
    for c in results["cases"]:
        sp = c["spec"]
        L.append(f"- **{c['name']}**: {sp['what']}; target at N = {sp['target_res'][0]}, M = {sp['target_res'][1]}, "
                 f"fitted at N = {sp['fit_res'][0]}, M = {sp['fit_res'][1]}; learnable: "
                 + ", ".join(f"`{k}`" for k in sp["true"]) + ".")
    L += ["", "## Gradient check (before the fits)", "",
          "Directional derivative of each case's loss at its start values along unit random directions d of the "
          "unconstrained parameters (log-values; logit for the transition): autograd through the checkpointed "
          "rollout against the central difference (L(z + hd) − L(z − hd)) / 2h. Relative difference |ad − fd| / "
          "max(|ad|, |fd|).", "",
          "| case | frames | direction | autograd | FD h = " + " | FD h = ".join(f"{h:g}" for h in results["fd_steps"]) +
          " | rel. diff " + " | rel. diff ".join(f"h = {h:g}" for h in results["fd_steps"]) + " |",
          "|---|---|---|---|" + "---|" * (2 * len(results["fd_steps"]))]
    for c in results["cases"]:
        fd = c["fd"]
        for i, r in enumerate(fd["directions"]):
            L.append(f"| {c['name']} | {c['frames']} | "
                     f"({', '.join(f'{x:+.2f}' for x in r['d'])}) | {r['autograd']:.8g} | " +
                     " | ".join(f"{r['fd'][str(h)]:.8g}" for h in results["fd_steps"]) + " | " +
                     " | ".join(f"{r['rel'][str(h)]:.1e}" for h in results["fd_steps"]) + " |")
    L += ["", "## Recovered against true", "",
          "| case | optimizer | field | true | start | fitted | fitted / true | loss at start (mm²) | final loss (mm²) | "
          "loss at the true values (mm²) | evaluations | wall (min) | s / evaluation |",
          "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for c in results["cases"]:
        for f in c["fits"]:
            for j, k in enumerate(c["spec"]["true"]):
                first = j == 0
                L.append(f"| {c['name'] if first else ''} | {f['optimizer'] if first else ''} | `{k}` | "
                         f"{c['spec']['true'][k]:.4g} | {c['spec']['start'][k]:.4g} | {f['final_values'][k]:.4g} | "
                         f"{f['final_values'][k] / c['spec']['true'][k]:.3f} | " +
                         (f"{f['loss'][0]:.4g} | {f['final_loss']:.4g} | {c['sensitivity']['loss_at_truth_mm2']:.4g} | "
                          f"{f['iterations']} | {f['wall_s'] / 60:.1f} | {f['s_per_iteration']:.1f} |" if first else
                          "| | | | | |"))
    L += ["", "Loss: mean squared distance at the material points over all frames and strands (mm²); its square root "
          "is the RMS error in mm. *Loss at the true values* is the fit resolution's own model error against the "
          "target: zero for the controls, the floor a cross-resolution fit starts from otherwise.", "",
          "### What each field does to the trajectory", "",
          "RMS change (mm) of the fit-resolution trajectory when one field is doubled (transition: 0.5 → 0.95), "
          "the others at their true values, against the loss floor (RMS mm) of the resolution change:", "",
          "| case | " + " | ".join(sorted({k for c in results["cases"] for k in c["spec"]["true"]})) +
          " | model error at the true values (RMS mm) |", "|---|" + "---|" * (1 + len({k for c in results["cases"]
                                                                                     for k in c["spec"]["true"]}))]
    keys = sorted({k for c in results["cases"] for k in c["spec"]["true"]})
    for c in results["cases"]:
        s = c["sensitivity"]
        L.append(f"| {c['name']} | " + " | ".join(f"{s['rms_change_mm'][k]:.3g}" if k in s["rms_change_mm"] else "–"
                                                  for k in keys) + f" | {math.sqrt(s['loss_at_truth_mm2']):.3g} |")
    L += ["", "![loss curves and parameter paths](identification.png)", ""]
    if results.get("profiles"):
        L += ["### Where a cross-resolution bias comes from", "",
              "Loss against the case's target (N = 64, M = 8) along one field, the others at their true values, "
              "for simulations at several (N, M) (forward only): the grid value of least loss is where a fit at "
              "that resolution would put the field if the others were right.", "",
              "| case | field | N | M | best on the grid | loss there (mm²) | loss at the true value (mm²) |",
              "|---|---|---|---|---|---|---|"]
        for p in results["profiles"]:
            true = next(c["spec"]["true"][p["field"]] for c in results["cases"] if c["name"] == p["case"])
            for r in p["rows"]:
                at_true = (r["loss"][p["grid"].index(true)] if true in p["grid"] else float("nan"))
                L.append(f"| {p['case']} | `{p['field']}` | {r['n']} | {r['m']} | {r['best']:.4g} | "
                         f"{min(r['loss']):.4g} | {at_true:.4g} |")
        L += ["", "![loss profiles at several resolutions](identification_profiles.png)", ""]
    if results.get("scans"):
        L += ["### The non-Hookean transition: loss along t", "",
              "![loss and gradient along the transition](identification_transition.png)", "",
              "| scan | points | t range | least loss at t | sign changes of dloss/dt (autograd) | "
              "sign changes of the scan's secants |", "|---|---|---|---|---|---|"]
        for label, sc in results["scans"].items():
            rows = sc["rows"]
            best = min(rows, key=lambda r: r["loss"])
            sec = [b["loss"] - a["loss"] for a, b in zip(rows, rows[1:])]
            flips = lambda xs: sum(1 for a, b in zip(xs, xs[1:]) if a * b < 0)  # noqa: E731
            ad = flips([r["dloss_dt"] for r in rows]) if "dloss_dt" in rows[0] else "–"
            L.append(f"| {label} | {len(rows)} | {rows[0]['t']}–{rows[-1]['t']} | {best['t']} ({best['loss']:.3g} mm²) | "
                     f"{ad} | {flips(sec)} |")
        L.append("")
    rerun = f"These rows were rerun by `{meta['memory_command']}`. " if meta.get("memory_command") else ""
    L += ["## Memory: one loss + backward, with and without checkpointing", "",
          rerun + "Each row is a fresh subprocess (`scripts/identify.py --memory-probe CASE --probe-checkpoint MODE`) that "
          "runs one rollout + backward at the case's start values after a 2-frame warm-up. *Peak rise*: the "
          "high-water mark of resident memory (VmHWM, reset through `/proc/self/clear_refs` just before the "
          "rollout) minus the resident size before it (glibc keeps freed heap, so this is the peak of what the "
          "rollout and its backward held at once, plus fragmentation). *Saved for backward*: the distinct "
          "storages that autograd saves during a second, identical rollout, counted with "
          "`torch.autograd.graph.saved_tensors_hooks` (inside checkpointed frames the checkpoint's own hooks "
          "take over, so what is counted is what stays saved outside them). Modes: `none` (a plain rollout: "
          "every frame's graph is kept), `every frame` and `sqrt` (`ams_torch.sim.rollout(..., checkpoint_every=k)` "
          "with k = 1 and k = ⌈√frames⌉: each segment of k frames runs without autograd in the forward pass, "
          "keeping only its input state, and is rebuilt and back-propagated, one segment at a time, in the "
          "backward pass; the fits use k = 1).", "",
          "| case | frames | checkpoint | RSS before (MiB) | peak rise (MiB) | saved for backward, outside "
          "checkpoints (MiB) | state per frame (KiB) | wall (s) |", "|---|---|---|---|---|---|---|---|"]
    for r in results["memory"]:
        L.append(f"| {r['case']} | {r['frames']} | {r['checkpoint']} | {r['rss_before_MiB']:.0f} | "
                 f"{r['peak_rise_MiB']:.1f} | {r['saved_outside_checkpoints_MiB']:.2f} | {r['frame_state_KiB']:.1f} | "
                 f"{r['wall_s']:.1f} |")
    if results.get("scale"):
        L += [""] + render_scale(results["scale"], meta)
    L += ["", "## Reproduce", "", "```", "OMP_NUM_THREADS=1 .venv/bin/python scripts/identify.py", "```",
          "", "`tests/test_identify.py` runs the script's functions on a tiny case (two fields recovered within 5 %, "
          "and a finite-difference check of a short rollout's gradient).", ""]
    (out / "identification.md").write_text("\n".join(L))


def plot(results: dict, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cases = results["cases"]
    cols = 3
    rows_ = math.ceil((len(cases) + 1) / cols)
    fig, axes = plt.subplots(rows_, cols, figsize=(4.6 * cols, 3.6 * rows_), squeeze=False)
    axes = axes.flatten()
    for c in cases:
        for f in c["fits"]:
            axes[0].semilogy(f["loss"] + [f["final_loss"]], label=f"{c['name']} {f['optimizer']}")
    axes[0].set_xlabel("loss evaluation (rollout + backward)")
    axes[0].set_ylabel("loss (mm², mean squared distance)")
    axes[0].set_title("loss of every evaluation")
    axes[0].legend(fontsize=6)
    for ax, c in zip(axes[1:], cases):
        for f in c["fits"]:
            for k, style in zip(c["spec"]["true"], ("-", "--", ":")):
                ratio = [v[k] / c["spec"]["true"][k] for v in f["values"]] + [f["final_values"][k] / c["spec"]["true"][k]]
                ax.semilogy(ratio, style, color="C0" if f["optimizer"] == "lbfgs" else "C1",
                            label=f"{f['optimizer']}: {k}")
        ax.axhline(1.0, color="gray", lw=0.8)
        ax.set_xlabel("loss evaluation")
        ax.set_ylabel("value / true value")
        res = c["spec"]
        ax.set_title(f"{c['name']} (target N={res['target_res'][0]} M={res['target_res'][1]}, "
                     f"fit N={res['fit_res'][0]} M={res['fit_res'][1]})", fontsize=8)
        ax.legend(fontsize=6)
    for ax in axes[len(cases) + 1:]:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(out / "identification.png", dpi=110)
    plt.close(fig)
    profiles = results.get("profiles") or []
    if profiles:
        fig, axes = plt.subplots(1, len(profiles), figsize=(5 * len(profiles), 3.8), squeeze=False)
        for ax, p in zip(axes[0], profiles):
            for r in p["rows"]:
                ax.semilogy(p["grid"], r["loss"], ".-", label=f"N = {r['n']}, M = {r['m']}")
            true = next(c["spec"]["true"][p["field"]] for c in cases if c["name"] == p["case"])
            ax.axvline(true, color="gray", lw=0.8)
            floor = min(min(r["loss"]) for r in p["rows"] if (r["n"], r["m"]) != (64, 8))
            ax.set_ylim(bottom=0.3 * floor)  # the target's own resolution reaches 0 at the true value
            if p["field"] != "integrity_transition":
                ax.set_xscale("log")
            ax.set_xlabel(p["field"])
            ax.set_ylabel("loss vs the N = 64, M = 8 target (mm²)")
            ax.set_title(f"{p['case']}: others at their true values")
            ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(out / "identification_profiles.png", dpi=110)
        plt.close(fig)
    scans = results.get("scans") or {}
    if scans:
        fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
        for label, s in scans.items():
            rows = s["rows"]
            axes[0].plot([r["t"] for r in rows], [r["loss"] for r in rows], ".-", label=label)
            if "dloss_dt" in rows[0]:
                axes[1].plot([r["t"] for r in rows], [r["dloss_dt"] for r in rows], ".-", label=f"{label}: autograd")
                fd = [(a["t"] + b["t"]) / 2 for a, b in zip(rows, rows[1:])]
                sl = [(b["loss"] - a["loss"]) / (b["t"] - a["t"]) for a, b in zip(rows, rows[1:])]
                axes[1].plot(fd, sl, "x", label=f"{label}: secant of the scan")
        axes[0].axvline(0.5, color="gray", lw=0.8)
        axes[1].axvline(0.5, color="gray", lw=0.8)
        axes[1].axhline(0.0, color="gray", lw=0.8)
        axes[0].set_xlabel("integrity_transition t")
        axes[0].set_ylabel("loss (mm²)")
        axes[0].set_yscale("log")
        axes[1].set_xlabel("integrity_transition t")
        axes[1].set_ylabel("dloss/dt (mm²)")
        axes[1].set_yscale("symlog", linthresh=10)
        for ax in axes:
            if ax.get_legend_handles_labels()[0]:
                ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(out / "identification_transition.png", dpi=110)
        plt.close(fig)


def run_case(name: str, args, log=print) -> dict:
    spec = case_spec(name, args.quick)
    t0 = time.perf_counter()
    target = case_target(spec)
    log(f"[{name}] target at N, M = {spec['target_res']}: {time.perf_counter() - t0:.1f} s")
    sens = sensitivity(spec, target)
    log(f"[{name}] loss at the true values {sens['loss_at_truth_mm2']:.4g} mm²; RMS change for ×2: {sens['rms_change_mm']}")
    sim = case_simulator(spec, spec["start"])
    fd = fd_check(sim, spec["poses"], target, directions=args.fd_directions, steps=tuple(args.fd_steps))
    for r in fd["directions"]:
        log(f"[{name}] FD d={['%.2f' % x for x in r['d']]}: autograd {r['autograd']:.8g}  fd {r['fd']}  rel {r['rel']}")
    if fd["worst_rel"] > args.fd_tolerance:
        log(f"[{name}] gradient check FAILED (worst relative difference {fd['worst_rel']:.2e} > {args.fd_tolerance:g})")
        if not spec["name"].startswith("coaster"):
            raise SystemExit(f"{name}: the rollout gradient does not match finite differences; no fit reported")
    fits = []
    for optimizer, count in spec["fits"]:
        count = min(count, args.max_evals) if args.max_evals else count
        log(f"[{name}] {optimizer}, {count} evaluations at most, from {spec['start']}")
        sim = case_simulator(spec, spec["start"])
        hist = fit(sim, spec["poses"], target, iterations=count, lr=args.lr, lr_final=args.lr_final,
                   optimizer=optimizer, log=log)
        log(f"[{name}] {optimizer}: fitted {hist['final_values']} (true {spec['true']}) in {hist['iterations']} "
            f"evaluations, {hist['wall_s']:.0f} s; final loss {hist['final_loss']:.4g} mm²")
        fits.append(hist)
    keep = {k: v for k, v in spec.items() if k in ("name", "true", "start", "target_res", "fit_res", "what", "base")}
    return {"name": name, "spec": keep, "frames": len(spec["poses"]), "sensitivity": sens, "fd": fd, "fits": fits,
            "_target": target, "_spec": spec}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", nargs="+", default=["shake", "shake_control", "shake_default", "coaster",
                                                   "coaster_control"])
    ap.add_argument("--max-evals", type=int, default=0, help="cap every fit's loss evaluations (0: each case's own)")
    ap.add_argument("--lr", type=float, default=0.1, help="Adam learning rate on the log-values / logits")
    ap.add_argument("--lr-final", type=float, default=0.01)
    ap.add_argument("--fd-directions", type=int, default=3)
    ap.add_argument("--fd-steps", type=float, nargs="+", default=[1e-3, 1e-4, 1e-6])
    ap.add_argument("--fd-tolerance", type=float, default=1e-4)
    ap.add_argument("--no-scan", action="store_true", help="skip the transition scans")
    ap.add_argument("--no-memory", action="store_true", help="skip the memory subprocesses")
    ap.add_argument("--quick", action="store_true", help="fewer strands, frames and iterations")
    ap.add_argument("--out", default=str(REPO / "docs"))
    ap.add_argument("--render-only", action="store_true", help="rewrite the page and plots from the JSON")
    ap.add_argument("--scale-only", action="store_true",
                    help="run the fit at scale (1,000 strands, head contact, hair–hair, per-strand drag), keep the "
                         "JSON's other results, rewrite the page")
    ap.add_argument("--scale-evals", type=int, default=12, help="loss evaluations of the fit at scale")
    ap.add_argument("--scale-optimizer", default="lbfgs", choices=("adam", "lbfgs"),
                    help="adam: every per-strand value moves at the learning rate from the first step")
    ap.add_argument("--scale-lr", type=float, default=0.25, help="Adam's first learning rate (log-values)")
    ap.add_argument("--memory-only", action="store_true",
                    help="rerun the memory probes of the JSON's cases, keep its other results, rewrite the page")
    ap.add_argument("--memory-probe", help=argparse.SUPPRESS)
    ap.add_argument("--probe-checkpoint", default="every frame", choices=CHECKPOINT_MODES, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    if args.memory_probe:
        print(json.dumps(memory_probe(args.memory_probe, args.probe_checkpoint, args.quick)))
        return 0
    out = Path(args.out)
    if args.scale_only:
        results = json.loads((out / "identification.json").read_text())
        results["scale"] = run_scale(args, log=lambda msg: print(msg, flush=True))
        results["meta"]["scale_command"] = ("python scripts/identify.py " + shown_args(argv)).strip()
        results["narrative"] = kept_discussion(out / "identification.md")
        (out / "identification.json").write_text(json.dumps(results, indent=1))
        render(results, out)
        print(f"wrote the fit at scale into {out / 'identification.md'}")
        return 0
    if args.memory_only:
        results = json.loads((out / "identification.json").read_text())
        names = dict.fromkeys(r["case"] for r in results["memory"])
        results["memory"] = [memory_in_subprocess(name, ck, args.quick) for name in names for ck in CHECKPOINT_MODES]
        results["meta"]["memory_command"] = ("python scripts/identify.py " + shown_args(argv)).strip()
        results["narrative"] = kept_discussion(out / "identification.md")
        (out / "identification.json").write_text(json.dumps(results, indent=1))
        render(results, out)
        print(f"reran the memory rows of {out / 'identification.md'}")
        return 0
    if args.render_only:
        results = json.loads((out / "identification.json").read_text())
        results["narrative"] = kept_discussion(out / "identification.md")
        render(results, out)
        plot(results, out)
        print(f"rewrote {out / 'identification.md'} and the plots from {out / 'identification.json'}")
        return 0
    if args.quick:
        args.max_evals = min(args.max_evals or 6, 6)
    t0 = time.perf_counter()
    load_start = round(os.getloadavg()[0], 2)
    log = lambda msg: print(msg, flush=True)  # noqa: E731
    cases = [run_case(name, args, log) for name in args.cases]
    scans = {}
    if not args.no_scan:
        for c in cases:
            if not c["name"].startswith("coaster"):
                continue
            spec, target = c["_spec"], c["_target"]
            control = c["name"] == "coaster_control"
            coarse = [round(0.2 + 0.025 * i, 4) for i in range(25)] if not args.quick else [0.3, 0.5, 0.7]
            print(f"[{c['name']}] scanning t over {len(coarse)} points", flush=True)
            # the gradient along the scan where it is cheap (M = 2); the loss alone at M = 8
            scans[f"{c['name']} (coarse)"] = transition_scan(spec, target, coarse, grad=control)
            if control and not args.quick:
                fine_ts = [round(0.45 + 0.005 * i, 4) for i in range(21)]
                scans[f"{c['name']} (fine)"] = transition_scan(spec, target, fine_ts)
    profiles = []
    if not args.no_scan:
        for c in cases:
            if c["name"] in ("shake", "coaster"):
                field, grid = (("drag", [round(1.5 * 2 ** (k / 4), 4) for k in range(-8, 5)]) if c["name"] == "shake"
                               else ("integrity_transition", [round(0.1 + 0.05 * k, 3) for k in range(17)]))
                if args.quick:
                    grid = grid[::4]
                print(f"[{c['name']}] loss profile along {field} at N, M = {PROFILE_RESOLUTIONS}", flush=True)
                profiles.append(resolution_profiles(c["_spec"], c["_target"], field, grid))
                print("  best: " + ", ".join(f"N={r['n']} M={r['m']}: {r['best']}" for r in profiles[-1]["rows"]),
                      flush=True)
    memory = []
    if not args.no_memory:
        for name in dict.fromkeys(n if not n.endswith("_control") else n[: -len("_control")] for n in args.cases):
            if name not in ("shake", "coaster"):
                continue
            for ck in CHECKPOINT_MODES:
                r = memory_in_subprocess(name, ck, args.quick)
                print(f"[memory] {r}", flush=True)
                memory.append(r)
    out = Path(args.out)
    results = {"meta": {"command": ("python scripts/identify.py " + shown_args(argv)).strip(),
                        "wall_s": time.perf_counter() - t0, "machine": machine_info(), "load_start": load_start,
                        "load_end": round(os.getloadavg()[0], 2)},
               "fd_steps": args.fd_steps,
               "cases": [{k: v for k, v in c.items() if not k.startswith("_")} for c in cases],
               "scans": scans, "profiles": profiles, "memory": memory}
    results["narrative"] = kept_discussion(out / "identification.md")
    old = out / "identification.json"
    if old.exists() and not args.quick:  # the fit at scale is its own run (--scale-only): keep it, with its command
        try:
            prev = json.loads(old.read_text())
        except ValueError:
            prev = {}
        if prev.get("scale"):
            results["scale"] = prev["scale"]
            results["meta"]["scale_command"] = prev.get("meta", {}).get("scale_command")
    (out / "identification.json").write_text(json.dumps(results, indent=1))
    render(results, out)
    plot(results, out)
    print(f"wrote {out / 'identification.md'} in {results['meta']['wall_s'] / 60:.1f} min")
    return 0


if __name__ == "__main__":
    sys.exit(main())
