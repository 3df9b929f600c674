"""Benchmark whole frames: the fused native path against the torch definition, per stage.

    .venv/bin/python scripts/bench_frame.py                      # CPU → docs/benchmarks/frame.{md,json}
    .venv/bin/python scripts/bench_frame.py --device cuda --strands 10000 100000 --resolution 128
    .venv/bin/python scripts/bench_frame.py --quick --out /tmp/frame   # smoke test
    .venv/bin/python scripts/bench_frame.py --scenes dynamics --strands 10000 --no-memory --profile 5 --out /tmp/f

Scenes (N = 32 particles, the default head):

- ``dynamics``: strands hanging from the head (``hanging_groom``), shaken; no hair–hair, no
  collisions (the strand dynamics alone: substeps of assembly + solve, follow-the-leader).
- ``every_stage``: the same groom with head collisions (64³ SDF) and hair–hair on a grid
  (``--resolution``, default 64).
- ``default``: the ``make demo`` scene itself (``datasets/scenes/default.toml``: 1,000 grown
  straight strands, head collisions, hair–hair 64³); with ``--default-resolutions 64 128`` also
  the same scene with a 128³ grid (records ``default-r128``), for the hair–hair stage's cost
  against R (issue 26: R = 128 within 2× of R = 64, ≤ 3 ms).

Each case builds one simulator per path (``backend="native"`` and ``"torch"``), warms both up,
then times frames interleaved (native, torch, native, ...) so both see the same machine load:
min and median ms/frame, the stages' share (``dynamics``, ``hair_hair``, ``collisions``, the rest
as ``other``), the ops per frame (top-level ATen operators and custom ops in the profiler, i.e.
what is dispatched per frame), and the peak memory per particle beyond the state (the torch
allocator's peak during a frame, from the profiler's memory events, over S·N; the native kernels'
per-thread scratch is outside the allocator and not included). Paths too slow for a case are
skipped (``--torch-max-strands``).

Memory: on Linux the script re-executes itself with glibc's malloc told to keep freed memory
(``KEEP_FREED``: no trimming, no per-block mmap, 256 MB top pad). With glibc's defaults each
path's frames page-fault on the memory the other path's frames just returned to the system (the
torch path frees ~1 KB per particle of temporaries per frame), which on this VM measured 14 ms
instead of 8 ms for a native dynamics frame at 4k × 32 that takes 8 ms when run alone, and
200 ms instead of 150 ms for the torch frame; with freed memory kept, each path costs what it
costs alone. ``--system-malloc`` measures with glibc's defaults. JSON records:
``{"scene", "S", "N", "device", "path", "stage", "median_ms", "min_ms", "ops_per_frame",
"peak_bytes_per_particle"}``.
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

import ams_torch as at  # noqa: E402
from ams_torch._bench import machine, machine_info, shown_args, stage_timer, sync  # noqa: E402
from ams_torch.geometry.sdf import SDFGrid  # noqa: E402
from ams_torch.grooms.head import hanging_groom  # noqa: E402
from ams_torch.apps.motion import Shake  # noqa: E402

STAGES = ("dynamics", "hair_hair", "collisions")
#: glibc malloc settings of the timing process (read by glibc at start-up: see the module docstring)
KEEP_FREED = {"MALLOC_TRIM_THRESHOLD_": "4000000000", "MALLOC_MMAP_THRESHOLD_": "1000000000",
              "MALLOC_TOP_PAD_": "268435456"}
PATHS = ("native", "torch")


def _load() -> float:
    return round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else float("nan")


def build_case(scene: str, strands: int, device, dtype, resolution: int, head, grid) -> dict:
    """Simulators of both paths for a case, their initial states and a motion. ``default-rR``: the
    default scene with its hair–hair grid at resolution R."""
    if scene.startswith("default"):
        import dataclasses

        from ams_torch.apps.scene import build, load_scene

        spec = load_scene(str(ROOT / "datasets" / "scenes" / "default.toml"))
        sims = {}
        for path in PATHS:
            run = build(spec, device=device, dtype=dtype)
            old = run.sim
            hh = old.hair_hair
            if scene != "default":
                hh = dataclasses.replace(hh, resolution=int(scene.split("-r")[1]))
            sims[path] = at.Simulator(old.model.rest_positions, old.params, device=device, dtype=dtype,
                                      pose=old.initial_pose, hair_hair=hh, colliders=old.colliders or None,
                                      backend=path)
    else:
        rest = hanging_groom(head, strands, 32, 0.25, sdf=grid, seed=1)
        hh = at.HairHair(resolution=resolution) if scene == "every_stage" else None
        cols = [at.MeshCollider(grid)] if scene == "every_stage" else None
        sims = {p: at.Simulator(rest, at.Params(), device=device, dtype=dtype, hair_hair=hh, colliders=cols,
                                backend=p) for p in PATHS}
    poses = Shake(amplitude=0.6, frequency=1.5).poses(240, 1 / 60, device=device, dtype=dtype)
    return {"sims": sims, "states": {p: s.initial_state() for p, s in sims.items()}, "poses": poses, "k": 0}


def frame(case: dict, path: str, device, timer=None) -> float:
    """One frame of one path; returns wall ms (device synchronised)."""
    sim = case["sims"][path]
    pose = case["poses"][case["k"] % len(case["poses"])]
    sync(device)
    t = time.perf_counter()
    case["states"][path] = sim.step(case["states"][path], pose, timer=timer)
    sync(device)
    return (time.perf_counter() - t) * 1e3


VIEWS = {"aten::reshape", "aten::view", "aten::expand", "aten::expand_as", "aten::unsqueeze", "aten::squeeze",
         "aten::select", "aten::slice", "aten::permute", "aten::transpose", "aten::t", "aten::as_strided",
         "aten::alias", "aten::detach", "aten::reshape_as", "aten::view_as", "aten::contiguous", "aten::item",
         "aten::_local_scalar_dense",
         # allocations without a kernel (an op's unused empty output)
         "aten::empty", "aten::new_empty", "aten::empty_like"}


def ops_per_frame(case: dict, path: str, device) -> tuple:
    """(operators dispatched in one frame, those of them that compute: not views; what launches
    kernels on a GPU). ``item`` is the divergence guard's read, outside the step."""
    from torch.profiler import ProfilerActivity, profile

    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if torch.device(device).type == "cuda" else [])
    with profile(activities=acts) as prof:
        frame(case, path, device)
    ops, computing = 0, 0
    for evt in prof.events():
        if evt.device_type != torch.autograd.DeviceType.CPU or evt.name.startswith("ams_torch.") or \
                evt.name.startswith("[memory]") or evt.name.startswith("Profiler"):
            continue
        parent = evt.cpu_parent
        while parent is not None and parent.name.startswith("ams_torch."):
            parent = parent.cpu_parent  # our record_function labels are not operators
        if parent is None:
            ops += 1
            computing += evt.name not in VIEWS
    return ops, computing


def profile_table(case: dict, path: str, device, frames: int) -> str:
    """The profiler's operators of ``frames`` frames of one path, by self time (ms per call:
    the native kernels' own cost, e.g. ``ams_torch_cpu::frame_finish``)."""
    from torch.profiler import ProfilerActivity, profile

    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if torch.device(device).type == "cuda" else [])
    with profile(activities=acts) as prof:
        for _ in range(frames):
            frame(case, path, device)
    key = "self_cuda_time_total" if torch.device(device).type == "cuda" else "self_cpu_time_total"
    return prof.key_averages().table(sort_by=key, row_limit=10)


def _rss(field: str) -> int:
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) * 1024 for line in f if line.startswith(field + ":"))


def memory_probe(scene: str, strands: int, path: str, device: str, dtype: str, resolution: int) -> int:
    """Peak resident memory of one frame beyond what is resident before it (the state, the model,
    the libraries), bytes: run in a fresh process with large blocks on mmap
    (MALLOC_MMAP_THRESHOLD_), so freed temporaries leave the resident set; the peak counter is
    reset just before the frame (/proc/self/clear_refs = 5). CPU only."""
    torch.set_num_threads(1)
    head = at.default_head(4)
    grid = SDFGrid.from_mesh(head, resolution=64)
    case = build_case(scene, strands, torch.device(device), getattr(torch, dtype), resolution, head, grid)
    case["sims"] = {path: case["sims"][path]}
    frame(case, path, device)
    frame(case, path, device)
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")
    base = _rss("VmRSS")
    frame(case, path, device)
    return _rss("VmHWM") - base


def peak_bytes(scene: str, strands: int, path: str, args) -> float:
    """Run :func:`memory_probe` in a subprocess; NaN where it cannot run (not Linux, or CUDA)."""
    import subprocess

    if args.device != "cpu" or not os.path.exists("/proc/self/clear_refs"):
        return float("nan")
    env = dict(os.environ, MALLOC_MMAP_THRESHOLD_="65536", MALLOC_TRIM_THRESHOLD_="0", MALLOC_TOP_PAD_="0")
    cmd = [sys.executable, __file__, "--memory-probe", scene, str(strands), path, "--dtype", args.dtype,
           "--resolution", str(args.resolution)]
    out = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=3600)
    try:
        return float(out.stdout.strip().splitlines()[-1])
    except (ValueError, IndexError):
        return float("nan")


def run_case(scene: str, strands: int, args, head, grid, paths) -> list:
    device, dtype = torch.device(args.device), getattr(torch, args.dtype)
    case = build_case(scene, strands, device, dtype, args.resolution, head, grid)
    s = case["sims"]["native"].model.num_strands
    n = case["sims"]["native"].model.num_particles
    for path in paths:  # warm-up: builds/loads kernels, fills the caching allocator
        frame(case, path, device)
        frame(case, path, device)
    times = {p: [] for p in paths}
    stages = {p: {} for p in paths}
    load0 = _load()
    t_case = time.perf_counter()
    for rep in range(args.reps):
        for path in paths:
            acc = {}
            times[path].append(frame(case, path, device, stage_timer(device, acc)))
            for k, v in acc.items():
                stages[path].setdefault(k, []).append(v * 1e3)
        case["k"] += 1
        if time.perf_counter() - t_case > args.case_cap and rep >= 1:
            break
    if args.profile:
        print(profile_table(case, "native", device, args.profile), flush=True)
    records = []
    for path in paths:
        ops, computing = ops_per_frame(case, path, device)
        peak = peak_bytes(scene, strands, path, args) if args.memory else float("nan")
        base = {"scene": scene, "S": s, "N": n, "device": device.type, "path": path, "ops_per_frame": ops,
                "computing_ops_per_frame": computing, "peak_bytes_per_particle": peak / (s * n),
                "reps": len(times[path]), "load_avg": [load0, _load()]}
        records.append(dict(base, stage="total", median_ms=statistics.median(times[path]), min_ms=min(times[path])))
        staged = [0.0] * len(times[path])
        for name in STAGES:
            vals = stages[path].get(name)
            if vals:
                staged = [a + b for a, b in zip(staged, vals)]
                records.append(dict(base, stage=name, median_ms=statistics.median(vals), min_ms=min(vals)))
        other = [t - st for t, st in zip(times[path], staged)]
        records.append(dict(base, stage="other", median_ms=statistics.median(other), min_ms=min(other)))
        print(f"{scene:12s} S={s:6d} {path:6s} {statistics.median(times[path]):9.2f} ms (min {min(times[path]):.2f}) "
              f"ops {ops:5d} ({computing} computing) peak {peak / (s * n):7.1f} B/particle", flush=True)
    return records


def _targets(by: dict) -> list:
    """The issue's CPU targets against this run's records (where the run has the rows)."""
    def total(scene, s, path):
        return by.get((scene, s, path), {}).get("total")

    rows = []
    d = total("default", 1000, "native")
    if d:
        rows.append(f"| default scene, every stage, ms/frame (issue 26) | ≤ 6 | {d['median_ms']:.2f} median, "
                    f"{d['min_ms']:.2f} min | {'met' if d['median_ms'] <= 6 else 'not met'} |")
    dt = total("default", 1000, "torch")
    if dt:
        rows.append(f"| default scene, the torch path (the definition), ms/frame (issue 25) | ≤ 65 | "
                    f"{dt['median_ms']:.2f} median, {dt['min_ms']:.2f} min | {'met' if dt['median_ms'] <= 65 else 'not met'} |")
    hh64 = by.get(("default", 1000, "native"), {}).get("hair_hair")
    hh128 = by.get(("default-r128", 1000, "native"), {}).get("hair_hair")
    if hh64 and hh128:
        ratio = hh128["median_ms"] / hh64["median_ms"]
        rows.append(f"| default scene, hair–hair stage at 128³ over 64³ (issue 26) | ≤ 2× | {ratio:.2f}× | "
                    f"{'met' if ratio <= 2 else 'not met'} |")
    if hh128:
        rows.append(f"| default scene, hair–hair stage at 128³, ms (issue 26) | ≤ 3 | {hh128['median_ms']:.2f} median | "
                    f"{'met' if hh128['median_ms'] <= 3 else 'not met'} |")
    n, t = total("dynamics", 10000, "native"), total("dynamics", 10000, "torch")
    if n and t:
        ratio, ratio_min = t["median_ms"] / n["median_ms"], t["min_ms"] / n["min_ms"]
        rows.append(f"| dynamics only 10k × 32, torch / native | ≥ 25× | {ratio:.1f}× median, {ratio_min:.1f}× min "
                    f"| {'met' if ratio >= 25 else 'not met'} |")
    natives = [st["total"] for (_, _, path), st in by.items() if path == "native"]
    if natives:
        worst = max(r["computing_ops_per_frame"] for r in natives)
        dispatched = max(r["ops_per_frame"] for r in natives)
        rows.append(f"| ops per frame, native, any S | ≤ 40 | {worst} computing ({dispatched} dispatched, views "
                    f"included) | {'met' if worst <= 40 else 'not met'} |")
    big = [st["total"] for (_, s, path), st in by.items() if path == "native" and s >= 100000]
    peak = [r["peak_bytes_per_particle"] for r in big if r["peak_bytes_per_particle"] == r["peak_bytes_per_particle"]]
    if peak:
        rows.append(f"| peak memory beyond the state at 100k × 32, B/particle | ≤ 300 | {max(peak):.0f} | "
                    f"{'met' if max(peak) <= 300 else 'not met'} |")
    if not rows:
        return []
    return ["", "## The issue's CPU targets", "", "| target | goal | this run | |", "|---|---|---|---|"] + rows


def render(records: list, meta: dict, out: Path) -> None:
    lines = ["# Whole frames: the fused native path against the torch definition", "",
             f"Machine: {meta['machine']}. Device `{meta['device']}`, {meta['dtype']}. Command: `{meta['command']}` "
             f"({meta['wall_s'] / 60:.1f} min). 1-minute load average: {meta['load_start']} at the start, "
             f"{meta['load_end']} at the end. malloc: {meta.get('malloc', 'glibc defaults')}. "
             "Raw records: [`frame.json`](frame.json).", "",
             "Frames of both paths timed interleaved in one run; min and median ms/frame; stages measured by the "
             "step's stage timer (device synchronised); ops = top-level operators dispatched per frame (profiler), "
             "and in brackets those that compute (not views: what launches kernels on a GPU); peak = the peak "
             "resident memory of a frame beyond what was resident before it (state, model, libraries), over S·N, "
             "measured in a fresh process with large blocks on mmap. N = 32, dt = 1/60 s, M = 1, per-length "
             "material defaults.", "",
             "| scene | S | path | ms/frame median | min | dynamics | hair–hair | collisions | other | ops/frame | "
             "peak B/particle |", "|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    by = {}
    for r in records:
        by.setdefault((r["scene"], r["S"], r["path"]), {})[r["stage"]] = r
    for (scene, s, path), st in by.items():
        tot = st["total"]
        cell = lambda k: f"{st[k]['median_ms']:.2f}" if k in st else "–"  # noqa: E731
        lines.append(f"| {scene} | {s:,} | {path} | {tot['median_ms']:.2f} | {tot['min_ms']:.2f} | {cell('dynamics')} | "
                     f"{cell('hair_hair')} | {cell('collisions')} | {cell('other')} | {tot['ops_per_frame']} "
                     f"({tot['computing_ops_per_frame']}) | {tot['peak_bytes_per_particle']:.0f} |")
    lines += ["", "## Native against torch, same run", "", "| scene | S | torch / native (median) |", "|---|---:|---:|"]
    for (scene, s, path), st in by.items():
        if path == "native" and (scene, s, "torch") in by:
            ratio = by[(scene, s, "torch")]["total"]["median_ms"] / st["total"]["median_ms"]
            lines.append(f"| {scene} | {s:,} | {ratio:.1f}× |")
    lines += _targets(by)
    if meta.get("note"):
        lines += ["", meta["note"]]
    (out.parent / (out.name + ".md")).write_text("\n".join(lines) + "\n")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--dtype", default="float32", choices=("float32", "float64"))
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--strands", type=int, nargs="+", default=[250, 1000, 4000, 10000, 16000, 100000])
    ap.add_argument("--scenes", nargs="+", default=["default", "dynamics", "every_stage"])
    ap.add_argument("--resolution", type=int, default=64, help="hair–hair grid of every_stage")
    ap.add_argument("--default-resolutions", type=int, nargs="+", default=[64],
                    help="hair–hair grids of the default scene (its own is 64; others are recorded as default-rR)")
    ap.add_argument("--reps", type=int, default=7)
    ap.add_argument("--case-cap", type=float, default=60.0, help="seconds per case before stopping early")
    ap.add_argument("--torch-max-strands", type=int, default=16000, help="skip the torch path above this")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--no-memory", dest="memory", action="store_false", help="skip the peak-memory subprocesses")
    ap.add_argument("--memory-probe", nargs=3, metavar=("SCENE", "S", "PATH"), help=argparse.SUPPRESS)
    ap.add_argument("--system-malloc", action="store_true",
                    help="time with glibc's default malloc settings (default: keep freed memory, KEEP_FREED)")
    ap.add_argument("--profile", type=int, default=0, metavar="FRAMES",
                    help="also print the profiler's operators of this many native frames per case (self time)")
    ap.add_argument("--note", default="")
    ap.add_argument("--render", metavar="JSON", help="only rewrite the markdown of an earlier run's JSON")
    ap.add_argument("--out", default=str(ROOT / "docs" / "benchmarks" / "frame"))
    args = ap.parse_args(argv)
    if args.memory_probe:
        scene, strands, path = args.memory_probe
        print(memory_probe(scene, int(strands), path, args.device, args.dtype, args.resolution))
        return 0
    if args.render:
        saved = json.loads(Path(args.render).read_text())
        if args.note:
            saved["meta"]["note"] = args.note
        render(saved["records"], saved["meta"], Path(args.render).with_suffix(""))
        return 0
    if args.quick:
        args.strands, args.reps, args.scenes = [250, 1000], 2, ["dynamics", "every_stage"]
    torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    load_start = _load()
    head = at.default_head(4)
    grid = SDFGrid.from_mesh(head, resolution=64)
    records = []
    for scene in args.scenes:
        names = [scene if r == 64 else f"default-r{r}" for r in args.default_resolutions] if scene == "default" \
            else [scene]
        for name in names:
            for s in ([1000] if scene == "default" else args.strands):
                paths = [p for p in PATHS if p == "native" or s <= args.torch_max_strands]
                records += run_case(name, s, args, head, grid, paths)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    meta = {"command": ("python scripts/bench_frame.py " + shown_args(argv)).strip(), "machine": machine(args.device),
            "machine_info": machine_info(args.device), "device": args.device, "dtype": args.dtype,
            "wall_s": time.perf_counter() - t0, "load_start": load_start, "load_end": _load(), "note": args.note,
            "malloc": _malloc_setting()}
    (out.parent / (out.name + ".json")).write_text(json.dumps({"meta": meta, "records": records}, indent=1))
    render(records, meta, out)
    print(f"wrote {out}.md in {meta['wall_s']:.0f} s")
    return 0


def _malloc_setting() -> str:
    if all(os.environ.get(k) == v for k, v in KEEP_FREED.items()):
        return "freed memory kept (" + ", ".join(f"{k}={v}" for k, v in KEEP_FREED.items()) + ")"
    return "glibc defaults"


def _reexec_keeping_freed_memory(argv) -> None:
    """Re-execute this script with KEEP_FREED in the environment (Linux; glibc reads it at
    start-up), unless it is already set, ``--system-malloc`` is given, or this is a probe."""
    if not sys.platform.startswith("linux") or {"--system-malloc", "--memory-probe", "--render"} & set(argv):
        return
    if _malloc_setting() != "glibc defaults":
        return
    sys.stdout.flush()
    os.execve(sys.executable, [sys.executable, os.path.abspath(__file__), *argv], dict(os.environ, **KEEP_FREED))


if __name__ == "__main__":
    _reexec_keeping_freed_memory(sys.argv[1:])
    sys.exit(main())
