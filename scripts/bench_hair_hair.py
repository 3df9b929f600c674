"""Benchmark the hair–hair stage (SPEC §6): cost per frame, warmed up, median over repetitions.

    .venv/bin/python scripts/bench_hair_hair.py                 # CPU, the default grid of cases
    .venv/bin/python scripts/bench_hair_hair.py --device cuda   # GPU (synchronised timings)

Cases: strands × 32 particles (``head_groom`` from ``tests/test_hair_hair.py``) at
each grid resolution, default config (FLIP 0.95, 50 Jacobi sweeps, no detailed collisions),
plus a few cases with detailed collisions. The groom is posed by a moving head, slightly
compressed and given random velocities so every part of the stage has work. Each case: one
warm-up call, then up to ``--reps`` timed calls or until ``--case-cap`` seconds are spent
(at least one). Writes ``docs/benchmarks/hair_hair.json`` and ``.md``.
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
from ams_torch.stages.hair_hair import HairHair, hair_hair_stage  # noqa: E402
from ams_torch.geometry.pose import Pose  # noqa: E402
from test_hair_hair import head_groom  # noqa: E402  (the tests' input factory)

MASS = 1e-6  # kg per particle
DT = 1.0 / 60.0


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


def bench_case(strands, particles, resolution, detailed, device, dtype, reps, case_cap):
    rest, x, v, pose = make_inputs(strands, particles, device, dtype)
    cfg = HairHair(resolution=resolution, detailed_collisions=detailed)
    t0 = time.perf_counter()
    grid = cfg.build(rest, MASS, device=device, dtype=dtype)
    sync(device)
    build_ms = (time.perf_counter() - t0) * 1e3
    free = torch.ones(particles, dtype=torch.bool, device=device)
    free[:2] = False
    with torch.no_grad():
        hair_hair_stage(grid, x, v, MASS, pose, DT, free)  # warm-up
        sync(device)
        times = []
        start = time.perf_counter()
        while len(times) < reps and (not times or time.perf_counter() - start < case_cap):
            t = time.perf_counter()
            hair_hair_stage(grid, x, v, MASS, pose, DT, free)
            sync(device)
            times.append((time.perf_counter() - t) * 1e3)
    return {
        "strands": strands, "particles_per_strand": particles, "resolution": resolution,
        "detailed_collisions": detailed, "dtype": str(dtype).replace("torch.", ""),
        "median_ms": statistics.median(times), "min_ms": min(times), "max_ms": max(times),
        "repetitions": len(times), "build_ms": build_ms,
    }


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    ap.add_argument("--strands", type=int, nargs="+", default=[10_000, 100_000])
    ap.add_argument("--particles", type=int, default=32)
    ap.add_argument("--resolutions", type=int, nargs="+", default=[32, 64, 128])
    ap.add_argument("--collision-cases", type=str, nargs="*", default=["10000:64"],
                    help="strands:resolution cases also timed with detailed collisions")
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--case-cap", type=float, default=20.0, help="seconds of timed calls per case (after one)")
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

    cases = [(s, r, False) for s in args.strands for r in args.resolutions]
    cases += [(int(c.split(":")[0]), int(c.split(":")[1]), True) for c in args.collision_cases]
    rows = []
    t_all = time.perf_counter()
    for s, r, det in cases:
        row = bench_case(s, args.particles, r, det, device, dtype, args.reps, args.case_cap)
        rows.append(row)
        print(f"{s:>7} strands × {args.particles}  {r:>3}³  collisions={'on ' if det else 'off'}  "
              f"median {row['median_ms']:9.1f} ms  (n={row['repetitions']}, min {row['min_ms']:.1f}, "
              f"max {row['max_ms']:.1f}; build {row['build_ms']:.0f} ms)", flush=True)
    total = time.perf_counter() - t_all

    result = {
        "benchmark": "hair_hair_stage per frame (SPEC §6)",
        "machine": machine(device), "device": str(device), "dtype": args.dtype,
        "config": "HairHair defaults (flip 0.95, 50 Jacobi sweeps, ω 0.6, staggered grid), "
                  "2 pinned particles per strand",
        "timing": f"one warm-up call, then up to {args.reps} calls or {args.case_cap:.0f} s per case; "
                  "median wall-clock ms, device synchronised",
        "threads": torch.get_num_threads(),
        "note": args.note,
        "total_seconds": total,
        "rows": rows,
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(result, indent=2) + "\n")
    lines = [
        "# Hair–hair stage: cost per frame",
        "",
        f"Machine: {result['machine']}  ",
        f"Device: `{device}`, {args.dtype}. Config: {result['config']}.  ",
        f"Timing: {result['timing']}. Rerun: `.venv/bin/python scripts/bench_hair_hair.py"
        f"{' --device ' + args.device if device.type != 'cpu' else ''}`.",
        *([f"Note: {args.note}", ""] if args.note else [""]),
        "| strands × particles | grid | detailed collisions | median ms | min ms | max ms | reps | build ms |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        lines.append(f"| {row['strands']:,} × {row['particles_per_strand']} | {row['resolution']}³ | "
                     f"{'on' if row['detailed_collisions'] else 'off'} | {row['median_ms']:.1f} | "
                     f"{row['min_ms']:.1f} | {row['max_ms']:.1f} | {row['repetitions']} | {row['build_ms']:.0f} |")
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print(f"wrote {out.with_suffix('.json')} and {out.with_suffix('.md')} ({total:.0f} s)")


if __name__ == "__main__":
    main()
