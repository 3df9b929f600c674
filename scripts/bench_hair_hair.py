"""Benchmark the hair–hair stage (SPEC §6): native kernels vs the torch definition, per frame.

    .venv/bin/python scripts/bench_hair_hair.py                 # CPU, the default grid of cases
    .venv/bin/python scripts/bench_hair_hair.py --device cuda   # GPU (synchronised timings)
    .venv/bin/python scripts/bench_hair_hair.py --strands 200 --resolutions 16 --reps 2 \\
        --collision-cases --out /tmp/hh                         # smoke test

Cases: strands × 32 particles (``head_groom`` from ``tests/test_hair_hair.py``) at each grid
resolution, default config (FLIP 0.95, 50 Jacobi sweeps, no detailed collisions), plus a few
cases with detailed collisions (which run in torch on both backends, after the grid part). The
groom is posed by a moving head, slightly compressed and given random velocities so every part
of the stage has work. Each case: one warm-up call per backend (it also builds the native
kernels on first use), then timed calls with the backends interleaved (torch, native, torch,
native, ...) so that both see the same machine load, up to ``--reps`` each or until
``--case-cap`` seconds are spent (at least one each); min and median per backend, the load
average before and after the case and the torch thread count are reported. The native result is
checked against the torch one (max relative velocity difference). Writes ``<out>.json`` and
``<out>.md`` (default ``docs/benchmarks/hair_hair``).
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from ams_torch._bench import machine, sync  # noqa: E402
from ams_torch.geometry.pose import Pose  # noqa: E402
from ams_torch.solver import build as _native  # noqa: E402
from ams_torch.stages.hair_hair import HairHair, hair_hair_stage  # noqa: E402
from test_hair_hair import head_groom  # noqa: E402  (the tests' input factory)

MASS = 1e-6  # kg per particle
DT = 1.0 / 60.0
BACKENDS = ("torch", "native")


def make_inputs(strands, particles, device, dtype, seed=0):
    rest = head_groom(strands, particles, seed=seed, dtype=dtype).to(device)
    pose = Pose.from_rotvec([0.1, 0.4, -0.05], [0.0, 1.6, 0.0], [0.3, 0.0, -0.2], [0.0, 1.5, 0.5],
                            device=device, dtype=dtype)
    g = torch.Generator(device="cpu").manual_seed(seed)
    noise = torch.randn(rest.shape, generator=g, dtype=dtype).to(device)
    local = rest * 0.97 + 2e-3 * noise  # a little compressed and jittered: the pressure has work
    x = pose.to_world(local)
    v = pose.velocity_at(x) + 0.2 * torch.randn(rest.shape, generator=g, dtype=dtype).to(device)
    return rest, x, v, pose


def _load() -> float:
    return round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else float("nan")


def bench_case(strands, particles, resolution, detailed, device, dtype, reps, case_cap, backends):
    rest, x, v, pose = make_inputs(strands, particles, device, dtype)
    cfg = HairHair(resolution=resolution, detailed_collisions=detailed)
    t0 = time.perf_counter()
    grid = cfg.build(rest, MASS, device=device, dtype=dtype)
    sync(device)
    build_ms = (time.perf_counter() - t0) * 1e3
    free = torch.ones(particles, dtype=torch.bool, device=device)
    free[:2] = False
    run = lambda b: hair_hair_stage(grid, x, v, MASS, pose, DT, free, backend=b)  # noqa: E731
    load_before = _load()
    times = {b: [] for b in backends}
    with torch.no_grad():
        outs = {b: run(b) for b in backends}  # warm-up (and the native build on first use)
        sync(device)
        start = time.perf_counter()
        while (min(len(t) for t in times.values()) < reps
               and (not times[backends[0]] or time.perf_counter() - start < case_cap)):
            for b in backends:
                t = time.perf_counter()
                run(b)
                sync(device)
                times[b].append((time.perf_counter() - t) * 1e3)
    row = {"strands": strands, "particles_per_strand": particles, "resolution": resolution,
           "detailed_collisions": detailed, "dtype": str(dtype).replace("torch.", ""), "build_ms": build_ms,
           "load_avg_before": load_before, "load_avg_after": _load(), "threads": torch.get_num_threads()}
    for b in backends:
        row[f"{b}_median_ms"] = statistics.median(times[b])
        row[f"{b}_min_ms"] = min(times[b])
        row[f"{b}_repetitions"] = len(times[b])
    if "torch" in outs and "native" in outs:
        dv_ref = outs["torch"][1] - v
        row["native_vs_torch_dv_rel"] = float((outs["native"][1] - outs["torch"][1]).abs().max()
                                              / dv_ref.abs().max().clamp_min(1e-30))
        row["speedup_median"] = row["torch_median_ms"] / row["native_median_ms"]
    return row


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    ap.add_argument("--strands", type=int, nargs="+", default=[1_000, 10_000, 100_000])
    ap.add_argument("--particles", type=int, default=32)
    ap.add_argument("--resolutions", type=int, nargs="+", default=[32, 64, 128])
    ap.add_argument("--collision-cases", type=str, nargs="*", default=["10000:64"],
                    help="strands:resolution cases also timed with detailed collisions")
    ap.add_argument("--backends", nargs="+", default=list(BACKENDS), choices=BACKENDS)
    ap.add_argument("--reps", type=int, default=5, help="timed calls per backend and case")
    ap.add_argument("--case-cap", type=float, default=20.0, help="seconds of timed calls per case (after one each)")
    ap.add_argument("--threads", type=int, default=0,
                    help="torch CPU threads (0: torch's default). On a machine shared with other jobs, "
                         "1 avoids OpenMP threads waiting on busy cores")
    ap.add_argument("--note", default="", help="a line added to the report (e.g. how loaded the machine was)")
    ap.add_argument("--out", default=str(ROOT / "docs" / "benchmarks" / "hair_hair"))
    args = ap.parse_args(argv)
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        ap.error("--device cuda but CUDA is not available")
    dtype = getattr(torch, args.dtype)
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    backends = tuple(args.backends)
    if "native" in backends:
        kind = "grid_cuda" if device.type == "cuda" else "grid_cpu"
        if _native.native_ops(kind) is None:
            ap.error(f"native grid kernels unavailable: {_native.native_status()[kind]['reason']}")

    cases = [(s, r, False) for s in args.strands for r in args.resolutions]
    cases += [(int(c.split(":")[0]), int(c.split(":")[1]), True) for c in args.collision_cases]
    rows = []
    t_all = time.perf_counter()
    for s, r, det in cases:
        row = bench_case(s, args.particles, r, det, device, dtype, args.reps, args.case_cap, backends)
        rows.append(row)
        timing = "  ".join(f"{b} median {row[f'{b}_median_ms']:8.2f} ms (min {row[f'{b}_min_ms']:.2f}, "
                           f"n={row[f'{b}_repetitions']})" for b in backends)
        extra = f"  x{row['speedup_median']:.1f}, dv rel {row['native_vs_torch_dv_rel']:.1e}" \
            if "speedup_median" in row else ""
        print(f"{s:>7} strands × {args.particles}  {r:>3}³  collisions={'on ' if det else 'off'}  {timing}{extra}  "
              f"(load {row['load_avg_before']} → {row['load_avg_after']})", flush=True)
    total = time.perf_counter() - t_all

    result = {
        "benchmark": "hair_hair_stage per frame (SPEC §6), native kernels vs torch definition",
        "machine": machine(device), "device": str(device), "dtype": args.dtype,
        "config": "HairHair defaults (flip 0.95, 50 Jacobi sweeps, ω 0.6, staggered grid, momentum-conserving "
                  "pressure), 2 pinned particles per strand",
        "timing": f"one warm-up call per backend, then backends interleaved, up to {args.reps} calls each or "
                  f"{args.case_cap:.0f} s per case; min and median wall-clock ms, device synchronised",
        "threads": torch.get_num_threads(),
        "note": args.note,
        "total_seconds": total,
        "rows": rows,
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(result, indent=2) + "\n")
    head = " | ".join(f"{b} median ms | {b} min ms" for b in backends)
    lines = [
        "# Hair–hair stage: cost per frame",
        "",
        f"Machine: {result['machine']}  ",
        f"Device: `{device}`, {args.dtype}, {result['threads']} torch threads. Config: {result['config']}.  ",
        f"Timing: {result['timing']}. Rerun: `.venv/bin/python scripts/bench_hair_hair.py"
        f"{' --device ' + args.device if device.type != 'cpu' else ''}`.",
        *([f"Note: {args.note}", ""] if args.note else [""]),
        f"| strands × particles | grid | detailed collisions | {head} | speed-up (median) | load avg | build ms |",
        "|---|---|---|" + "---|---|" * len(backends) + "---|---|---|",
    ]
    for row in rows:
        cells = " | ".join(f"{row[f'{b}_median_ms']:.2f} | {row[f'{b}_min_ms']:.2f}" for b in backends)
        speed = f"{row['speedup_median']:.1f}×" if "speedup_median" in row else "–"
        lines.append(f"| {row['strands']:,} × {row['particles_per_strand']} | {row['resolution']}³ | "
                     f"{'on' if row['detailed_collisions'] else 'off'} | {cells} | {speed} | "
                     f"{row['load_avg_before']}–{row['load_avg_after']} | {row['build_ms']:.0f} |")
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print(f"wrote {out.with_suffix('.json')} and {out.with_suffix('.md')} ({total:.0f} s)")


if __name__ == "__main__":
    main()
