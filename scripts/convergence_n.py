"""Convergence in N (particles per strand) at fixed dt and M, against a converged reference (SPEC §13).

Two studies, both float64:

- **Presets** (``straight``, ``wavy``, ``curly``): 6 strands of each grown preset (seed 0, grown
  at 1025 particles and resampled to every N from that one polyline), shaken 0.6 rad at 1.5 Hz
  about +y for 60 frames with M = 4 substeps, no colliders; and ``wavy_head``, the wavy strands
  colliding with the default head. The error is the RMS distance (mm) at
  17 material points per strand (rest arc-length fractions) to the N = 512 run at the end of the
  run, for N = 16, 32, 64 (the errors judged); N = 128 is shown as well, and the reference's own
  resolution is checked: N = 512 against N = 1024 must be at most 1/5 of the smallest error judged
  (with an N = 256 reference, N = 256 against 512 was 0.25 of it on the clumped curly preset).
  Targets: monotone, observed order ≥ 0.9, and the N = 16 → 64 error ratio ≥ 4 against N = 128
  and against the reference. The per-particle material (``Params.paper`` style constants) is shown
  beside the per-length one (the library default).
- **Cantilever**: a planar circular arc (0.1 m, curvature 10 m⁻¹) clamped at its root, with bend
  and torsion springs only (B_b = B_t = 3.2768e-11 N·m⁴, no biphasic coupling), under a small
  in-plane load (gravity 0.05 m/s²); the static tip deflection, from the library's own implicit
  step with Δt = 10⁴ s (one linear solve: ``x₁ − x₀ = Δt² (m + Δt² K)⁻¹ f`` = K⁻¹ f to 1e-12),
  against the inextensible Euler–Bernoulli curved beam of bending stiffness c² (B_b/4 + 4 B_t)
  (docs/material.md).

    .venv/bin/python scripts/convergence_n.py            # → docs/material_convergence.{md,json,png}
    .venv/bin/python scripts/convergence_n.py --quick    # 3 strands, 30 frames

Strands are independent without hair–hair, so a few strands of a groom are exact; they are the
preset's own (wavy and curly grow in clumps by default, so the strands drawn depend on it).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import ams_torch as at  # noqa: E402
from ams_torch._bench import machine_info, shown_args  # noqa: E402
from ams_torch.grooms.groom import resample_strands  # noqa: E402
from ams_torch.apps.motion import Shake  # noqa: E402
from ams_torch.testing import at_material_points  # noqa: E402

F64 = torch.float64
NS = (16, 32, 64)  # the particle counts whose errors are judged
SHOWN = 128  # shown beside them (the reference), not judged
REF_N = 512  # N = 256 against 512 missed the 1/5 check on the clumped curly preset (0.25)
CHECK_N = 1024
POINTS = 17
PRESETS = ("straight", "wavy", "curly")
CASES = PRESETS + ("wavy_head",)  # the last: the wavy preset colliding with the head
MATERIALS = {"per_length": {}, "per_particle": {"material": "per_particle"}}
CANTILEVER_NS = (16, 32, 64, 128, 256)
TARGET_ORDER, TARGET_RATIO, TARGET_REF = 0.9, 4.0, 0.2


def preset_case(name: str, strands: int = 6, frames: int = 60, seed: int = 0, collide: bool = False) -> dict:
    """``strands`` strands of the grown preset ``name`` (grown at 1025 particles), shaken;
    ``collide``: colliding with the default head (64³ SDF)."""
    from ams_torch.geometry.sdf import SDFGrid

    head = at.default_head(4)
    groom = at.preset(name, strands=strands, particles=1025, seed=seed, mesh=head)
    poses = Shake(amplitude=0.6, frequency=1.5).poses(frames, 1 / 60, dtype=F64)
    colliders = [at.MeshCollider(SDFGrid.from_mesh(head, resolution=64))] if collide else []
    return {"name": name + ("_head" if collide else ""), "fine": groom.rest_positions.double(), "poses": poses,
            "colliders": colliders,
            "what": f"{strands} strands of the {name} preset (seed {seed}), {frames} frames of a 0.6 rad, 1.5 Hz "
                    f"shake about +y, " + ("colliding with the default head (64³ SDF, the default substep contact)"
                                           if collide else "no colliders")}


def run(case: dict, material: str, n: int, substeps: int, **changes) -> tuple:
    """(rest (S, n, 3), positions at the end (S, n, 3)) of a case at n particles, float64."""
    rest = resample_strands(case["fine"], n)
    params = at.Params(substeps=substeps, **MATERIALS[material], **changes)
    sim = at.Simulator(rest, params, dtype=F64, colliders=case.get("colliders") or None)
    state = sim.initial_state()
    for pose in case["poses"]:
        state = sim.step(state, pose)
    return rest, state.x


def rms_mm(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(((a - b) ** 2).sum(-1).mean().sqrt()) * 1e3


def observed_order(ns, errors) -> float:
    """Least-squares slope of −log(error) against log(N): the observed order of convergence."""
    x = torch.log(torch.tensor(ns, dtype=F64))
    y = torch.log(torch.tensor(errors, dtype=F64))
    x = x - x.mean()
    return float(-(x * (y - y.mean())).sum() / (x * x).sum())


def convergence(case: dict, material: str = "per_length", substeps: int = 4, ns=NS, ref_n: int = REF_N,
                check_n: int = CHECK_N, shown=(SHOWN,), time_check: bool = True, **changes) -> dict:
    """Errors (mm, at ``POINTS`` material points) of ``ns`` against ``ref_n``, the reference's check
    against ``check_n``, the errors of ``shown`` (not judged), the N = ``ns[0]`` → ``ns[-1]`` ratio
    against ``ref_n`` and against ``shown[0]`` (when it exceeds every judged N), and the time error
    of the reference (``ref_n`` at 2M against M)."""
    runs = {}
    for n in sorted(set(ns) | set(shown) | {ref_n, check_n}):
        rest, x = run(case, material, n, substeps, **changes)
        runs[n] = at_material_points(rest, x, POINTS)
    errors = [rms_mm(runs[n], runs[ref_n]) for n in ns]
    out = {"scene": case["name"], "material": material, "substeps": substeps, "particles": list(ns),
           "reference": ref_n, "rms_error_mm": errors, "order": observed_order(ns, errors),
           "pairwise_orders": [math.log2(a / b) for a, b in zip(errors, errors[1:])],
           "monotone": all(b < a for a, b in zip(errors, errors[1:])), "ratio": errors[0] / errors[-1],
           "shown": {str(n): rms_mm(runs[n], runs[ref_n]) for n in shown},
           "reference_check": {"particles": check_n, "rms_error_mm": rms_mm(runs[ref_n], runs[check_n])}}
    out["reference_check"]["over_smallest"] = out["reference_check"]["rms_error_mm"] / min(errors)
    alt = [n for n in shown if n > max(ns)]
    if alt:
        e = [rms_mm(runs[n], runs[alt[0]]) for n in ns]
        out["against_" + str(alt[0])] = {"rms_error_mm": e, "ratio": e[0] / e[-1],
                                        "monotone": all(b < a for a, b in zip(e, e[1:]))}
    if time_check:
        rest, x = run(case, material, ref_n, 2 * substeps, **changes)
        out["time_error_mm"] = rms_mm(at_material_points(rest, x, POINTS), runs[ref_n])
    return out


# ------------------------------------------------------------------------------ cantilever
def arc(n: int, length: float = 0.1, curvature: float = 10.0) -> torch.Tensor:
    """(1, n, 3) m: a planar circular arc in the xy plane, tangent +x at the root, curving toward +y."""
    s = torch.linspace(0, length, n, dtype=F64)
    phi = curvature * s
    return torch.stack((torch.sin(phi) / curvature, (1 - torch.cos(phi)) / curvature, torch.zeros_like(s)), -1)[None]


def euler_bernoulli_tip(length: float, curvature: float, load, bending: float, points: int = 20001) -> np.ndarray:
    """Small-deflection tip displacement (2,) m of an inextensible clamped circular arc (:func:`arc`)
    under a uniform load per length ``load`` (2,) N/m in its plane, bending stiffness ``bending`` N·m²:
    δr_tip = ∫ M(s)/B ẑ × (r_tip − r(s)) ds with M(s) = ẑ · ∫_s^L (r(s') − r(s)) × w ds'."""
    s = np.linspace(0.0, length, points)
    ds = s[1] - s[0]
    r = np.stack([np.sin(curvature * s) / curvature, (1 - np.cos(curvature * s)) / curvature], 1)
    w = np.asarray(load, dtype=np.float64)
    weights = np.full(points, ds)
    weights[0] = weights[-1] = ds / 2  # trapezoid
    tail = np.cumsum((weights)[::-1])[::-1]  # ∫_s^L ds'
    tail_r = np.cumsum((r * weights[:, None])[::-1], 0)[::-1]  # ∫_s^L r ds'
    moment = (tail_r[:, 0] - r[:, 0] * tail) * w[1] - (tail_r[:, 1] - r[:, 1] * tail) * w[0]
    lever = r[-1] - r
    turn = np.stack([-lever[:, 1], lever[:, 0]], 1) * (moment / bending)[:, None]
    return (turn * weights[:, None]).sum(0)


def uncoupled_rigidities(rest: torch.Tensor, stretch: float, bend: float, torsion: float) -> tuple:
    """Per-spring rigidities (B_b (1, N−2), B_t (1, N−3)) that make the per-length springs
    κ = B / ℓ⁵ exactly, i.e. undo the stretch-coupling factor s (the conversion before it): the
    fixed point of B' = B / s(B'), by iteration."""
    from ams_torch.sim.material import stretch_coupling_factor

    ell_b = (rest[:, 2:] - rest[:, :-2]).norm(dim=-1) / 2
    ell_t = (rest[:, 3:] - rest[:, :-3]).norm(dim=-1) / 3
    bb, bt = torch.full_like(ell_b, bend), torch.full_like(ell_t, torsion)
    for _ in range(200):
        bt_b = torch.cat([bt, bt[:, -1:]], -1)
        sb = stretch_coupling_factor(ell_b, stretch, bb, bt_b)
        st = stretch_coupling_factor(ell_t, stretch, bb[:, :-1], bt)
        bb, bt = bend / sb, torsion / st
    return bb, bt


def cantilever_deflection(n: int, length: float = 0.1, curvature: float = 10.0, gravity: float = 0.05,
                          bend: float = 3.2768e-11, torsion: float = 3.2768e-11, coupling: bool = True,
                          **changes) -> dict:
    """Static tip deflection of the spring model (bend and torsion springs, edges, no biphasic
    coupling) of :func:`arc` at n particles under gravity (0, −gravity, 0), and its ratio to
    :func:`euler_bernoulli_tip` with B = c² (B_b/4 + 4 B_t). One implicit step of Δt = 10⁴ s is the
    linear static solve. ``coupling=False``: the springs without the stretch-coupling factor
    (κ = B/ℓ⁵, :func:`uncoupled_rigidities`). Returns {"tip_mm": (2,), "euler_bernoulli_mm": (2,), "ratio": |δ| / |δ_EB|}."""
    rest = arc(n, length, curvature)
    rig_b, rig_t = (bend, torsion) if coupling else uncoupled_rigidities(rest, changes.get("stretch_rigidity", 8e-3),
                                                                         bend, torsion)
    params = at.Params(**{**dict(dt=1e4, substeps=1, bend_rigidity=rig_b, torsion_rigidity=rig_t, integrity_rate=0.0,
                                 angular_rigidity=0.0, sag_free=False, inextensibility=False, drag=0.0,
                                 stiffness_cap=1e12, gravity=(0.0, -gravity, 0.0), max_relative_speed=1e12), **changes})
    sim = at.Simulator(rest, params, dtype=F64)
    state = sim.step(sim.initial_state(), None)
    tip = (state.x[0, -1] - rest[0, -1])[:2].numpy()
    b = curvature ** 2 * (bend / 4 + 4 * torsion)
    ref = euler_bernoulli_tip(length, curvature, (0.0, -gravity * params.linear_density), b)
    return {"particles": n, "tip_mm": (tip * 1e3).tolist(), "euler_bernoulli_mm": (ref * 1e3).tolist(),
            "ratio": float(np.linalg.norm(tip) / np.linalg.norm(ref))}


def cantilever_study(ns=CANTILEVER_NS, **changes) -> dict:
    rows = [cantilever_deflection(n, **changes) for n in ns]
    errors = [abs(r["ratio"] - 1) for r in rows]
    return {"scene": "cantilever", "particles": list(ns), "rows": rows, "relative_error": errors,
            "order": observed_order(ns, errors), "monotone": all(b < a for a, b in zip(errors, errors[1:]))}


# ------------------------------------------------------------------------------ report
def verdict(r: dict) -> bool:
    ok = r["monotone"] and r["order"] >= TARGET_ORDER and r["ratio"] >= TARGET_RATIO
    alt = [v for k, v in r.items() if k.startswith("against_")]
    ok = ok and all(a["monotone"] and a["ratio"] >= TARGET_RATIO for a in alt)
    return ok and r["reference_check"]["over_smallest"] <= TARGET_REF


def render(records: list, cant: dict, meta: dict, out: Path) -> None:
    lines = ["# Convergence in N against converged references", "",
             f"Generated by `{meta['command']}` in {meta['wall_s'] / 60:.1f} min on {meta['machine']['cpu']} "
             f"({meta['machine']['cpu_cores']} cores), torch {meta['machine']['torch']}, 1 thread, float64. "
             "Raw numbers: [`material_convergence.json`](material_convergence.json). The material, its "
             "derivation and what these numbers decided are in [`material.md`](material.md).", "",
             "## Presets", "",
             f"Each strand is one fine polyline (the preset grown at 1025 particles) resampled to N particles; the "
             f"error is the RMS distance (mm) to the N = {REF_N} run at {POINTS} fixed material points per strand "
             f"(rest arc-length fractions), at the end of the run. dt = 1/60 s and M fixed for every N. Targets: "
             f"monotone, observed order ≥ {TARGET_ORDER}, N = {NS[0]} → {NS[-1]} ratio ≥ {TARGET_RATIO:g} against "
             f"N = {REF_N} and against N = {SHOWN}, and the reference resolved: N = {REF_N} against N = {CHECK_N} "
             f"at most {TARGET_REF:g}× the smallest error judged.", ""]
    for case in meta["cases"]:
        lines.append(f"- **{case['name']}**: {case['what']}.")
    head = " | ".join(f"N = {n}" for n in NS)
    lines += ["", f"| preset | material | M | {head} | N = {SHOWN} (not judged) | order | ratio {NS[0]}→{NS[-1]} "
              f"| against N = {SHOWN}, N = {', '.join(str(n) for n in NS)} (ratio) | N = {REF_N} vs {CHECK_N} (× smallest) "
              "| time error (mm) "
              "| targets |", "|---|---|---|" + "---|" * len(NS) + "---|---|---|---|---|---|---|"]
    for r in records:
        alt = r.get(f"against_{SHOWN}", {"rms_error_mm": [], "ratio": float("nan")})
        rc = r["reference_check"]
        lines.append(f"| {r['scene']} | {r['material']} | {r['substeps']} | " +
                     " | ".join(f"{e:.3g}" for e in r["rms_error_mm"]) + f" | {r['shown'][str(SHOWN)]:.3g} | "
                     f"{r['order']:.2f} | {r['ratio']:.2f} | " + ", ".join(f"{e:.3g}" for e in alt["rms_error_mm"]) +
                     f" ({alt['ratio']:.2f}) | {rc['rms_error_mm']:.3g} ({rc['over_smallest']:.2f}) | "
                     f"{r.get('time_error_mm', float('nan')):.2g} | {'met' if verdict(r) else '**not met**'} |")
    misses = []
    for r in records:
        if verdict(r):
            continue
        why = []
        if not r["monotone"]:
            why.append("not monotone")
        if r["order"] < TARGET_ORDER:
            why.append(f"order {r['order']:.2f} < {TARGET_ORDER}")
        if r["ratio"] < TARGET_RATIO:
            why.append(f"ratio {r['ratio']:.2f} < {TARGET_RATIO:g}")
        for k, a in r.items():
            if k.startswith("against_") and not (a["monotone"] and a["ratio"] >= TARGET_RATIO):
                why.append(f"{k.replace('_', ' N = ')}: ratio {a['ratio']:.2f}")
        over = r["reference_check"]["over_smallest"]
        if over > TARGET_REF:
            why.append(f"reference check {over:.2f}× the smallest error judged (> {TARGET_REF:g}: the N = {REF_N} "
                       f"reference carries up to ≈ {over:.0%} of that error)")
        misses.append(f"{r['scene']} {r['material']}: " + "; ".join(why))
    if misses:
        lines += ["", "Targets missed, by how much: " + ". ".join(misses) + "."]
    lines += ["", "Order: least-squares slope of −log(error) against log(N) over the judged N (1 = first order). "
              "Pairwise orders (log₂ of successive ratios): " +
              "; ".join(f"{r['scene']} {r['material']}: " + ", ".join(f"{o:.2f}" for o in r["pairwise_orders"])
                        for r in records) + ". The time error is the reference against itself at 2M: what the "
              "substeps contribute (the same M for every N, so it does not enter the errors in N).", "",
              "## Cantilever against Euler–Bernoulli", "",
              "A 0.1 m circular arc of curvature 10 m⁻¹, clamped (two pinned particles), bend and torsion springs "
              "B_b = B_t = 3.2768e-11 N·m⁴ with their stretch coupling (`stretch_coupling_factor`), the library's "
              "default edges (EA = 8e-3 N), no biphasic coupling, under gravity 0.05 m/s² in its plane: static tip "
              "deflection (one implicit step of 10⁴ s) over the inextensible Euler–Bernoulli curved beam with "
              "B = c² (B_b/4 + 4 B_t).", "",
              "| N | " + " | ".join(str(n) for n in cant["particles"]) + " | order | monotone |",
              "|---|" + "---|" * len(cant["particles"]) + "---|---|",
              "| deflection / Euler–Bernoulli | " + " | ".join(f"{r['ratio']:.4f}" for r in cant["rows"]) +
              f" | {cant['order']:.2f} | {'yes' if cant['monotone'] else 'no'} |"]
    if "uncoupled" in meta:
        u = meta["uncoupled"]
        lines += ["| without the stretch coupling (κ = B/ℓ⁵) | " + " | ".join(f"{r['ratio']:.4f}" for r in u["rows"]) +
                  f" | {u['order']:.2f} | {'yes' if u['monotone'] else 'no'} |"]
    lines += ["", "![errors against N](material_convergence.png)", ""]
    (out / "material_convergence.md").write_text("\n".join(lines))


def plot(records: list, cant: dict, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(CASES) + 1, figsize=(3.2 * (len(CASES) + 1), 3.4))
    for ax, scene in zip(axes, CASES):
        for r in records:
            if r["scene"] != scene:
                continue
            ax.loglog(r["particles"], r["rms_error_mm"], "o-" if r["material"] == "per_length" else "s--",
                      label=f"{r['material']} (order {r['order']:.2f})")
            if r["material"] == "per_length":
                ns = np.array(NS, dtype=float)
                ax.loglog(NS, r["rms_error_mm"][0] * NS[0] / ns, ":", color="gray", label="first order")
                ax.axhline(r["reference_check"]["rms_error_mm"], color="r", ls="--", lw=0.8,
                           label=f"N = {REF_N} vs {CHECK_N}")
        ax.set_title(scene)
        ax.set_xlabel("particles per strand N")
        ax.set_ylabel(f"RMS error vs N = {REF_N} (mm)")
        ax.legend(fontsize=6)
    ax = axes[-1]
    ax.loglog(cant["particles"], cant["relative_error"], "o-", label=f"order {cant['order']:.2f}")
    ax.set_title("cantilever")
    ax.set_xlabel("particles per strand N")
    ax.set_ylabel("|deflection / Euler–Bernoulli − 1|")
    ax.legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(out / "material_convergence.png", dpi=110)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="3 strands, 30 frames")
    ap.add_argument("--substeps", type=int, default=4)
    ap.add_argument("--out", default=str(REPO / "docs"))
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    cases = [preset_case(p.replace("_head", ""), *((3, 30) if args.quick else ()), collide=p.endswith("_head"))
             for p in CASES]
    records = []
    for case in cases:
        for material in MATERIALS:
            r = convergence(case, material, args.substeps)
            records.append(r)
            print(f"{case['name']:8s} {material:12s} " + " ".join(f"{e:8.3f}" for e in r["rms_error_mm"]) +
                  f"  order {r['order']:.2f} ratio {r['ratio']:.2f}  ref check {r['reference_check']['over_smallest']:.2f}"
                  f"  {'met' if verdict(r) else 'NOT MET'}", flush=True)
    cant = cantilever_study()
    uncoupled = cantilever_study(coupling=False)  # κ = B/ℓ⁵: the conversion without the stretch coupling
    print("cantilever deflection / Euler–Bernoulli: " + ", ".join(f"N={r['particles']}: {r['ratio']:.4f}"
                                                                 for r in cant["rows"]) + f"; order {cant['order']:.2f}")
    out = Path(args.out)
    meta = {"command": ("python scripts/convergence_n.py " + shown_args(argv)).strip(),
            "wall_s": time.perf_counter() - t0, "machine": machine_info(),
            "cases": [{"name": c["name"], "what": c["what"]} for c in cases], "uncoupled": uncoupled}
    (out / "material_convergence.json").write_text(json.dumps({"meta": meta, "records": records, "cantilever": cant},
                                                              indent=1))
    render(records, cant, meta, out)
    plot(records, cant, out)
    print(f"wrote {out / 'material_convergence.md'} in {meta['wall_s']:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
