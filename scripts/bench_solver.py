"""Benchmark of the banded strand solve: native kernel vs plain torch vs dense vs SciPy.

For every strand count S, particle count N and dtype, times the same assembled systems
(the tests' factory, ``tests/native_cases.py::strand_system``) with:

    native  ams_torch.solver.op.solve_banded(check=False) (the registered op; native CPU/CUDA
            kernel), as the simulator's step calls it
    checked the same with check=True (the default): plus one isfinite pass over x, blocks and
            rhs and one host sync, so that a non-SPD or non-finite strand raises LinAlgError
    plain   ams_torch.solver.reference.solve_banded_plain (pure torch block Cholesky)
    dense   torch.linalg.solve on the assembled (S, 3N, 3N) matrices (assembly not timed),
            only where the dense matrices fit in --dense-max-gb
    scipy   scipy.linalg.solveh_banded looped over strands (CPU only; banded storage built
            beforehand, not timed), only for S <= --scipy-max-strands

Each measurement: one warm-up call, then 3 to --repeats timed calls (fewer when a call is slow,
so that one measurement takes about --time-cap seconds); the median is reported. On CUDA the
device is synchronised before every clock read.

Writes ``<out>/solver.json`` (a list of records ``{"S", "N", "dtype", "device", "method",
"median_ms", ...}``, each also carrying ``repeats``, ``threads``, ``torch``, ``cpu``, ``gpu``)
and ``<out>/solver.md`` (tables with speed-up ratios against native).

    python scripts/bench_solver.py               # full grid, ~ minutes on 2 CPU cores
    python scripts/bench_solver.py --quick       # S ∈ {1000, 10000}, N ∈ {16, 32}
    python scripts/bench_solver.py --device cuda
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import os
import sys
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from ams_torch.native import build as _native  # noqa: E402
from ams_torch.solver import op as ops  # noqa: E402
from ams_torch._bench import machine_info, median_ms, shown_args  # noqa: E402
from ams_torch.solver.reference import banded_to_dense, solve_banded_plain  # noqa: E402

METHODS = ("native", "checked", "plain", "dense", "scipy")
DTYPES = {"float32": torch.float32, "float64": torch.float64}


def _load_factory():
    spec = importlib.util.spec_from_file_location("_bench_tests_factory", REPO / "tests" / "native_cases.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.strand_system


def scipy_banded_lower(blocks: torch.Tensor) -> np.ndarray:
    """blocks (S, N, 4, 3, 3) → SciPy lower banded storage (S, 12, 3N): ab[i-j, j] = A[i, j]."""
    s, n = blocks.shape[:2]
    b = blocks.detach().cpu().numpy()
    ab = np.zeros((s, 12, 3 * n), dtype=b.dtype)
    for k in range(4):
        if k >= n:
            break
        cols = 3 * np.arange(n - k)
        for r in range(3):
            for c in range(3):
                if k == 0 and r < c:
                    continue
                ab[:, 3 * k + r - c, cols + c] = b[:, k:, k, r, c]
    return ab


def run(args) -> list[dict]:
    strand_system = _load_factory()
    device = args.device
    info = machine_info(device)
    # Build / load the native kernel before timing anything.
    warm_b, warm_r = strand_system(2, 4, device=device)
    ops.solve_banded(warm_b, warm_r)
    status = _native.native_status()[device]
    print(f"native {device}: built={status['built']} reason={status['reason']}", flush=True)
    records: list[dict] = []
    import scipy.linalg

    for dtype_name in args.dtypes:
        dtype = DTYPES[dtype_name]
        for n in args.particles:
            for s in args.strands:
                blocks, rhs = strand_system(s, n, dtype=dtype, device=device, seed=s + n)
                results = {}

                def record(method, ms, reps):
                    rec = {"S": s, "N": n, "dtype": dtype_name, "device": device, "method": method,
                           "median_ms": round(ms, 4), "repeats": reps, **info}
                    records.append(rec)
                    results[method] = ms

                if "native" in args.methods:
                    x_native = ops.solve_banded(blocks, rhs)
                    record("native", *median_ms(lambda: ops.solve_banded(blocks, rhs, check=False), device,
                                                args.repeats, args.time_cap))
                if "checked" in args.methods:
                    record("checked", *median_ms(lambda: ops.solve_banded(blocks, rhs), device, args.repeats,
                                                 args.time_cap))
                if "plain" in args.methods:
                    x_plain = solve_banded_plain(blocks, rhs)
                    record("plain", *median_ms(lambda: solve_banded_plain(blocks, rhs), device, args.repeats, args.time_cap))
                    if "native" in args.methods:
                        rel = ((x_native - x_plain).double().norm() / x_plain.double().norm()).item()
                        tol = 1e-4 if dtype == torch.float32 else 1e-10
                        assert rel < tol, f"native and plain disagree: {rel:.3g}"
                    del x_plain
                dense_gb = s * (3 * n) ** 2 * blocks.element_size() / 1e9
                if "dense" in args.methods and dense_gb <= args.dense_max_gb:
                    a = banded_to_dense(blocks)
                    r = rhs.reshape(s, 3 * n)
                    record("dense", *median_ms(lambda: torch.linalg.solve(a, r), device, args.repeats, args.time_cap))
                    del a
                if "scipy" in args.methods and device == "cpu" and s <= args.scipy_max_strands:
                    ab = scipy_banded_lower(blocks)
                    rn = rhs.reshape(s, 3 * n).numpy()

                    def scipy_loop():
                        for i in range(s):
                            scipy.linalg.solveh_banded(ab[i], rn[i], lower=True, check_finite=False)

                    record("scipy", *median_ms(scipy_loop, device, args.repeats, args.time_cap))
                    del ab
                line = "  ".join(f"{m}={results[m]:9.2f}ms" for m in METHODS if m in results)
                print(f"{dtype_name} S={s:6d} N={n:3d}  {line}", flush=True)
                del blocks, rhs
    return records


def write_markdown(records: list[dict], path: Path, args) -> None:
    info = {k: records[0][k] for k in ("cpu", "cpu_cores", "threads", "torch", "gpu")} if records else {}
    device = records[0]["device"] if records else args.device
    lines = [
        "# Banded strand solver benchmark",
        "",
        f"Generated by `scripts/bench_solver.py` ({shown_args(hide=('--note',)) or 'default grid'}). Device: **{device}**"
        + (f" ({info.get('gpu')})" if info.get("gpu") else "")
        + f"; CPU: {info.get('cpu')}, {info.get('cpu_cores')} cores, torch threads {info.get('threads')}; "
        f"torch {info.get('torch')}.",
        "",
        "Median wall time per call (ms) of one solve of S strands of N particles (3N unknowns each), "
        "and how many times slower each method is than `native` (`check=False`, as the step calls it). "
        "`checked`: the default `check=True` (one sum over x, rhs and A's diagonal, then one host sync). `dense`: torch.linalg.solve on the "
        f"assembled matrices (assembly not timed; only where they fit in {args.dense_max_gb} GB). `scipy`: "
        "scipy.linalg.solveh_banded looped over strands (only small S). Blank: not run.",
        "",
    ]
    if hasattr(os, "getloadavg"):
        lines += [f"1-minute load average: {records[0]['load_avg_1min_at_start'] if records else '?'} at the start, "
                  f"{os.getloadavg()[0]:.2f} at the end of the run (other processes' load inflates the timings, "
                  "the multi-threaded plain and dense torch paths most).", ""]
    if args.note:
        lines += [args.note, ""]
    by_key: dict = {}
    for r in records:
        by_key.setdefault((r["dtype"], r["S"], r["N"]), {})[r["method"]] = r["median_ms"]
    for dtype_name in args.dtypes:
        lines += [f"## {dtype_name}", "",
                  "| S | N | native ms | checked ms | plain ms | dense ms | scipy ms | checked/native | plain/native "
                  "| dense/native | scipy/native |",
                  "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
        for (dt, s, n), m in sorted(by_key.items(), key=lambda kv: (kv[0][0], kv[0][2], kv[0][1])):
            if dt != dtype_name:
                continue
            cells = [f"{m[k]:.2f}" if k in m else "" for k in METHODS]
            ratios = [f"{m[k] / m['native']:.{2 if k == 'checked' else 1}f}×" if k in m and "native" in m else ""
                      for k in ("checked", "plain", "dense", "scipy")]
            lines.append(f"| {s} | {n} | " + " | ".join(cells + ratios) + " |")
        lines.append("")
    path.write_text("\n".join(lines))


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    p.add_argument("--strands", type=int, nargs="+", help="default 1000 10000 100000 (--quick: 1000 10000)")
    p.add_argument("--particles", type=int, nargs="+", help="default 16 32 64 (--quick: 16 32)")
    p.add_argument("--dtypes", nargs="+", default=["float32", "float64"], choices=tuple(DTYPES))
    p.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    p.add_argument("--repeats", type=int, help="timed calls at most, median reported (default 25; --quick: 3)")
    p.add_argument("--time-cap", type=float, default=1.0, help="seconds per measurement, roughly (at least one timed call)")
    p.add_argument("--dense-max-gb", type=float, default=2.0)
    p.add_argument("--scipy-max-strands", type=int, default=10000)
    p.add_argument("--quick", action="store_true", help="smaller defaults: S ∈ {1000, 10000}, N ∈ {16, 32}, 3 repeats")
    p.add_argument("--out", type=Path, default=REPO / "docs" / "benchmarks")
    p.add_argument("--threads", type=int, default=0, help="torch intra-op threads (0: torch's default)")
    p.add_argument("--note", default="", help="a sentence added to solver.md (e.g. machine load)")
    args = p.parse_args(argv)
    args.strands = args.strands or ([1000, 10000] if args.quick else [1000, 10000, 100000])
    args.particles = args.particles or ([16, 32] if args.quick else [16, 32, 64])
    args.repeats = args.repeats or (3 if args.quick else 25)
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    if args.device == "cuda" and not torch.cuda.is_available():
        p.error("--device cuda: no CUDA device available")
    records = run(args)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "solver.json").write_text("[\n" + ",\n".join(json.dumps(r) for r in records) + "\n]\n")
    write_markdown(records, args.out / "solver.md", args)
    print(f"wrote {args.out / 'solver.json'} and {args.out / 'solver.md'}")


if __name__ == "__main__":
    main()
