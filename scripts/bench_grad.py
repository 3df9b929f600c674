"""Benchmark gradient frames: forward with autograd and backward, native against the torch definition,
and the memory of a checkpointed rollout.

    .venv/bin/python scripts/bench_grad.py                        # CPU → docs/benchmarks/grad.{md,json}
    .venv/bin/python scripts/bench_grad.py --device cuda --strands 1000 10000 --torch-max-strands 10000
    .venv/bin/python scripts/bench_grad.py --quick --out /tmp/grad   # smoke run (toy sizes)

Scenes (N = 32 particles, the default head; as ``scripts/bench_frame.py``):

- ``dynamics``: strands hanging from the head, shaken; no hair–hair, no collisions.
- ``every_stage``: the same groom with head collisions (64³ SDF) and hair–hair (``--resolution``).

Each case builds one simulator per path (``backend="native"`` and ``"torch"``) with learnable
integrity rate and drag, and times, interleaved (native, torch, native, ...), per frame:

- ``forward (no grad)``: the frame under ``torch.no_grad()`` (the native path's fused kernels);
- ``forward (grad)``: the frame with x requiring grad and the learnable fields in the graph, split
  per stage by the step's stage timer; on the native path every stage whose adjoint is native runs
  its kernel, the others the torch definition (``ams_torch.native_status()["gradients"]``);
- ``backward``: ``loss.backward()`` of a scalar of that frame's x and v.

Targets of issue 25: the backward of a native frame ≤ 3× its native forward (dynamics only), ≤ 5×
(every stage). Memory: one loss + backward of a ``--memory-frames`` rollout (default 120) of the
every-stage scene at 1k × 32 through :func:`ams_torch.sim.rollout` with a reducer (no state kept
per frame), for each ``checkpoint_every`` in ``--memory-checkpoints``, each in a fresh process: the
rise of the resident high-water mark over the resident size before the rollout (CPU; VmHWM reset
through /proc/self/clear_refs) or the CUDA allocator's peak over its allocation before (CUDA).
Target: ≤ 64 MiB beyond the states with checkpointing.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import subprocess
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

PATHS = ("native", "torch")
STAGES = ("dynamics", "hair_hair", "collisions")
LEARNABLE = ("integrity_rate", "drag")


def _load() -> float:
    return round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else float("nan")


def build_sim(scene: str, strands: int, path: str, device, dtype, resolution: int, head, grid) -> at.Simulator:
    rest = hanging_groom(head, strands, 32, 0.25, sdf=grid, seed=1)
    every = scene == "every_stage"
    return at.Simulator(rest, at.Params(), device=device, dtype=dtype, learnable=LEARNABLE, backend=path,
                        hair_hair=at.HairHair(resolution=resolution) if every else None,
                        colliders=[at.MeshCollider(grid)] if every else None)


def grad_frame(case: dict, path: str, device) -> dict:
    """One frame of one path with autograd, then its backward; the state moves on (detached).
    Returns {"forward": ms, "backward": ms, stage: ms ...}."""
    sim, state = case["sims"][path], case["states"][path]
    pose = case["poses"][case["k"] % len(case["poses"])]
    x = state.x.detach().requires_grad_()
    acc = {}
    sync(device)
    t0 = time.perf_counter()
    new = sim.step(state.replace(x=x), pose, timer=stage_timer(device, acc))
    sync(device)
    t1 = time.perf_counter()
    loss = (case["w"] * new.x).sum() + 1e-2 * (case["w"] * new.v).sum()
    loss.backward()
    sync(device)
    t2 = time.perf_counter()
    for p in sim.parameters():
        p.grad = None
    case["states"][path] = new.detach()
    return {"forward": (t1 - t0) * 1e3, "backward": (t2 - t1) * 1e3, **{k: v * 1e3 for k, v in acc.items()}}


def plain_frame(case: dict, path: str, device) -> float:
    sim, state = case["sims"][path], case["states"][path]
    pose = case["poses"][case["k"] % len(case["poses"])]
    sync(device)
    t0 = time.perf_counter()
    with torch.no_grad():
        case["states"][path] = sim.step(state, pose)
    sync(device)
    return (time.perf_counter() - t0) * 1e3


def gradient_stages(sim: at.Simulator) -> str:
    """Which of this simulator's stages run native kernels in a gradient frame: forward and adjoint, or
    forward only (adjoint recomputed on the torch definition: marked "forward")."""
    status = at.native_status().get("gradients", {})
    if sim.config.backend != "native":
        return "none (torch definition)"
    present = {"dynamics": True, "hair_hair": bool(sim.config.hair_hair), "collisions": bool(sim.config.colliders),
               "finish": True, "plastic_yield": bool(sim.config.nonhookean)}
    out = []
    for name, how in status.items():
        if not present.get(name, False):
            continue
        if how.startswith("native forward and adjoint"):
            out.append(name)
        elif how.startswith("native adjoint"):
            out.append(f"{name} (adjoint)")
        elif how.startswith("native forward"):
            out.append(f"{name} (forward)")
    return ", ".join(out) or "none"


def run_case(scene: str, strands: int, args, head, grid, paths) -> list:
    device, dtype = torch.device(args.device), getattr(torch, args.dtype)
    sims = {p: build_sim(scene, strands, p, device, dtype, args.resolution, head, grid) for p in paths}
    case = {"sims": sims, "states": {p: s.initial_state() for p, s in sims.items()}, "k": 0,
            "poses": Shake(amplitude=0.6, frequency=1.5).poses(240, 1 / 60, device=device, dtype=dtype)}
    case["w"] = torch.randn(case["states"][paths[0]].x.shape, generator=torch.Generator().manual_seed(0),
                            dtype=dtype).to(device)
    for path in paths:  # warm-up
        plain_frame(case, path, device)
        grad_frame(case, path, device)
    rows = {p: {"plain": [], "grad": []} for p in paths}
    load0, t_case = _load(), time.perf_counter()
    for rep in range(args.reps):
        for path in paths:
            rows[path]["plain"].append(plain_frame(case, path, device))
            rows[path]["grad"].append(grad_frame(case, path, device))
        case["k"] += 1
        if time.perf_counter() - t_case > args.case_cap and rep >= 1:
            break
    records = []
    s, n = sims[paths[0]].model.num_strands, sims[paths[0]].model.num_particles
    for path in paths:
        plain = rows[path]["plain"]
        grads = rows[path]["grad"]
        rec = {"scene": scene, "S": s, "N": n, "device": device.type, "dtype": args.dtype, "path": path,
               "reps": len(plain), "load_avg": [load0, _load()], "native_gradient_stages": gradient_stages(sims[path]),
               "forward_nograd_ms": statistics.median(plain), "forward_nograd_min_ms": min(plain)}
        for key in ("forward", "backward") + STAGES:
            vals = [g[key] for g in grads if key in g]
            if vals:
                rec[f"{key}_ms"] = statistics.median(vals)
                rec[f"{key}_min_ms"] = min(vals)
        records.append(rec)
        print(f"{scene:12s} S={s:6d} {path:6s} fwd(no grad) {rec['forward_nograd_ms']:9.2f}  fwd(grad) "
              f"{rec['forward_ms']:9.2f}  bwd {rec['backward_ms']:9.2f} ms/frame", flush=True)
    return records


# -- memory of a rollout ---------------------------------------------------------------------------
def _rss(field: str) -> int:
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) * 1024 for line in f if line.startswith(field + ":"))


def memory_probe(strands: int, frames: int, every: int, path: str, device: str, dtype: str, resolution: int,
                 frame_checkpoints: bool = False) -> dict:
    """One loss + backward of a ``frames`` rollout (every stage) checkpointed every ``every`` frames
    (``frame_checkpoints``: and every frame inside a recomputed segment, ``checkpoint_frames=True``)."""
    torch.set_num_threads(1)
    device, dtype_ = torch.device(device), getattr(torch, dtype)
    head = at.default_head(4)
    grid = SDFGrid.from_mesh(head, resolution=64)
    sim = build_sim("every_stage", strands, path, device, dtype_, resolution, head, grid)
    poses = Shake(amplitude=0.6, frequency=1.5).poses(frames, 1 / 60, device=device, dtype=dtype_)
    w = torch.randn((strands, 32, 3), generator=torch.Generator().manual_seed(0), dtype=dtype_).to(device)

    def once(count):
        out = at.sim.rollout(sim, sim.initial_state(), poses[:count], checkpoint_every=every,
                             checkpoint_frames=frame_checkpoints, reduce=lambda acc, k, s: acc + (w * s.x).sum(),
                             initial=0.0)
        out.value.backward()

    once(2)  # warm-up
    state = sim.initial_state()
    state_bytes = sum(t.numel() * t.element_size() for t in (state.x, state.v, state.ghost_rest, state.sag_offset))
    t0 = time.perf_counter()
    if device.type == "cuda":
        torch.cuda.synchronize(device)
        torch.cuda.reset_peak_memory_stats(device)
        before = torch.cuda.memory_allocated(device)
        once(frames)
        torch.cuda.synchronize(device)
        rise = torch.cuda.max_memory_allocated(device) - before
    else:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        before = _rss("VmRSS")
        once(frames)
        rise = _rss("VmHWM") - before
    return {"S": strands, "frames": frames, "checkpoint_every": every, "checkpoint_frames": frame_checkpoints,
            "path": path, "device": device.type, "peak_rise_MiB": rise / 2 ** 20, "state_MiB": state_bytes / 2 ** 20, "wall_s": time.perf_counter() - t0}


def memory_in_subprocess(args, every: int, path: str, frame_checkpoints: bool = False) -> dict:
    cmd = [sys.executable, os.path.abspath(__file__), "--memory-probe", str(args.memory_strands),
           str(args.memory_frames), str(every), path, "--device", args.device, "--dtype", args.dtype,
           "--resolution", str(args.resolution)] + (["--memory-probe-frames"] if frame_checkpoints else [])
    env = dict(os.environ, MALLOC_MMAP_THRESHOLD_="65536", MALLOC_TRIM_THRESHOLD_="0", MALLOC_TOP_PAD_="0")
    out = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=6 * 3600)
    try:
        return json.loads(out.stdout.strip().splitlines()[-1])
    except (ValueError, IndexError):
        return {"S": args.memory_strands, "frames": args.memory_frames, "checkpoint_every": every,
                "checkpoint_frames": frame_checkpoints, "path": path, "device": args.device, "peak_rise_MiB": float("nan"), "state_MiB": float("nan"),
                "wall_s": float("nan"), "error": _failure(out)}


def memory_repeated(args, every: int, path: str, frame_checkpoints: bool = False) -> dict:
    """:func:`memory_in_subprocess` ``--memory-reps`` times (interleaving is not needed: one probe
    at a time, nothing else running); the median peak, every peak in ``peaks_MiB``."""
    runs = [memory_in_subprocess(args, every, path, frame_checkpoints) for _ in range(max(1, args.memory_reps))]
    ok = [r for r in runs if not r.get("error")]
    if not ok:
        return runs[0]
    peaks = sorted(r["peak_rise_MiB"] for r in ok)
    out = dict(min(ok, key=lambda r: abs(r["peak_rise_MiB"] - statistics.median(peaks))))
    out.update(peak_rise_MiB=statistics.median(peaks), peaks_MiB=peaks, reps=len(runs),
               wall_s=statistics.median(r["wall_s"] for r in ok))
    return out


def _failure(proc) -> str:
    """Why a memory probe gave no result: killed by a signal (SIGKILL: most likely the kernel's
    out-of-memory killer; the machine's memory is named), or its last line of stderr."""
    if proc.returncode is not None and proc.returncode < 0:
        sig = -proc.returncode
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2 ** 30 if hasattr(os, "sysconf") else 0
        return (f"killed by signal {sig}" + (f" (out of memory: the machine has {total:.0f} GiB)" if sig == 9 else ""))
    tail = (proc.stderr or "").strip().splitlines()[-1:]
    return tail[0] if tail else f"exit status {proc.returncode}, no output"


# -- report -----------------------------------------------------------------------------------------
def render(records: list, memory: list, meta: dict, out: Path) -> None:
    f = lambda r, k: f"{r[k]:.2f}" if k in r else "–"  # noqa: E731
    lines = ["# Gradient frames: forward with autograd and backward, native against the torch definition", "",
             f"Machine: {meta['machine']}. Device `{meta['device']}`, {meta['dtype']}. Command: `{meta['command']}` "
             f"({meta['wall_s'] / 60:.1f} min). 1-minute load average: {meta['load_start']} at the start, "
             f"{meta['load_end']} at the end. Raw records: [`grad.json`](grad.json).", "",
             "Both paths timed interleaved in one run, medians (min in the JSON). *Forward (no grad)*: the frame "
             "under `torch.no_grad()`; *forward (grad)*: with x₀ requiring grad and the integrity rate and drag "
             "learnable, per stage from the step's stage timer; *backward*: `loss.backward()` of a scalar of the "
             "frame's x and v. *Native gradient stages*: those whose forward and adjoint run native kernels in a "
             "gradient frame (the others take the torch definition). N = 32, dt = 1/60 s, M = 1.", "",
             "| scene | S | path | native gradient stages | forward, no grad | forward, grad | dynamics | hair–hair | "
             "collisions | backward | forward (grad) + backward | backward / native forward (no grad) |",
             "|---|---:|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    native_fwd = {(r["scene"], r["S"]): r["forward_nograd_ms"] for r in records if r["path"] == "native"}
    for r in records:
        ref = native_fwd.get((r["scene"], r["S"]))
        ratio = f"{r['backward_ms'] / ref:.1f}×" if ref else "–"
        lines.append(f"| {r['scene']} | {r['S']:,} | {r['path']} | {r['native_gradient_stages']} | "
                     f"{f(r, 'forward_nograd_ms')} | {f(r, 'forward_ms')} | {f(r, 'dynamics_ms')} | "
                     f"{f(r, 'hair_hair_ms')} | {f(r, 'collisions_ms')} | {f(r, 'backward_ms')} | "
                     f"{r['forward_ms'] + r['backward_ms']:.2f} | {ratio} |")
    lines += ["", "## Targets (issue 25)", "", "| target | goal | this run |", "|---|---|---|"]
    for scene, goal in (("dynamics", 3.0), ("every_stage", 5.0)):
        for r in records:
            if r["scene"] == scene and r["path"] == "native" and r["S"] == 1000:
                ratio = r["backward_ms"] / r["forward_nograd_ms"]
                lines.append(f"| backward of a native frame / its native forward, {scene}, 1k × 32 | ≤ {goal:g}× | "
                             f"{ratio:.1f}× ({'met' if ratio <= goal else 'not met'}) |")
    st = at.native_status()["gradients"]
    native_stages = [k for k, v in st.items() if v.startswith("native forward and adjoint")]
    forward_only = [k for k, v in st.items() if v.startswith("native forward (")]
    adjoint_only = [k for k, v in st.items() if v.startswith("native adjoint")]
    rest = [k for k in st if k not in native_stages + forward_only + adjoint_only]
    lines += ["", "What runs where in a gradient frame of the native path (`ams_torch.native_status()[\"gradients\"]`): "
              f"native forward and adjoint: {', '.join(native_stages) or 'none'}; torch forward, native adjoint: "
              f"{', '.join(adjoint_only) or 'none'}; native forward, adjoint by the torch definition recomputed in "
              f"the backward pass: {', '.join(forward_only) or 'none'}; torch definition: "
              f"{', '.join(rest) or 'none'} (each with the fallbacks `native_status()` names). The hair–hair grid's adjoint recomputes its forward (P2G, the "
              "pressure) natively inside the backward pass, so its backward costs about two native forwards of the "
              "grid plus the adjoint kernels. The sum *forward (grad) + backward* is the cost of one gradient frame "
              "for a training step."]
    if memory:
        lines += ["", f"## Memory: one loss + backward of a {memory[0]['frames']}-frame rollout (every stage, "
                  f"{memory[0]['S']:,} × 32)", "",
                  "Each row a fresh process: `ams_torch.sim.rollout(..., checkpoint_every=k, checkpoint_frames=…, "
                  "reduce=...)` (no state kept per frame; *checkpoint_frames*: the recomputed segment checkpoints "
                  "each of its frames too, one more forward per frame), the peak rise of resident memory (CPU: VmHWM over VmRSS before the rollout, with "
                  "large blocks on mmap so freed memory leaves the resident set) or of the CUDA allocator.", "",
                  f"Each probe ran {memory[0].get('reps', 1)} times, each in its own process: median, and the "
                  "range.", "",
                  "| path | checkpoint_every | checkpoint_frames | peak rise (MiB), median | range | one state (MiB) | "
                  "wall (s) |",
                  "|---|---:|---|---:|---:|---:|---:|"]
        for m in memory:
            if m.get("error"):
                err = m["error"] if isinstance(m["error"], str) else "; ".join(m["error"]) or "no output"
                lines.append(f"| {m['path']} | {m['checkpoint_every']} | {m.get('checkpoint_frames', False)} | "
                             f"did not finish: {err} | – | – | – |")
                continue
            runs = m.get("peaks_MiB", [m["peak_rise_MiB"]])
            lines.append(f"| {m['path']} | {m['checkpoint_every']} | {m.get('checkpoint_frames', False)} | "
                         f"{m['peak_rise_MiB']:.1f} | "
                         f"{min(runs):.1f}–{max(runs):.1f} | {m['state_MiB']:.2f} | {m['wall_s']:.1f} |")
        done = [m for m in memory if not m.get("error") and m["checkpoint_every"] and m["peak_rise_MiB"] == m["peak_rise_MiB"]]
        if done:
            best = min(done, key=lambda m: m["peak_rise_MiB"])
            met = best["peak_rise_MiB"] < 64
            lines += ["", f"The goal was under 64 MiB beyond the states with checkpointing: {best['peak_rise_MiB']:.0f} "
                      f"MiB (median, the states included) at checkpoint_every = {best['checkpoint_every']}"
                      + (", checkpoint_frames=True" if best.get("checkpoint_frames") else "") + ", "
                      + ("met." if met else f"missed by {best['peak_rise_MiB'] / 64:.1f}×.")
                      + " What autograd keeps per frame of a recomputed segment is the native ops' inputs (the "
                      "state, the per-element coefficients of that frame, x and v at each collision, "
                      "follow-the-leader and hair–hair call: about 4.5 MiB at 1k × 32, three states' worth); with "
                      "checkpoint_frames only each frame's input state is kept while a segment is differentiated, "
                      "and one frame's graph at a time. The checkpoints are one state per segment; the rest is what "
                      "one frame's backward allocates at its peak (the adjoint kernels' workspaces: the grid's "
                      "recomputed pool, the sweeps' history)."]
    if meta.get("note"):
        lines += ["", meta["note"]]
    out.parent.mkdir(parents=True, exist_ok=True)
    (out.parent / (out.name + ".md")).write_text("\n".join(lines) + "\n")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--dtype", default="float32", choices=("float32", "float64"))
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--strands", type=int, nargs="+", default=[1000, 10000])
    ap.add_argument("--scenes", nargs="+", default=["dynamics", "every_stage"])
    ap.add_argument("--resolution", type=int, default=64, help="hair–hair grid of every_stage")
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--case-cap", type=float, default=120.0, help="seconds per case before stopping early")
    ap.add_argument("--torch-max-strands", type=int, default=10000, help="skip the torch path above this")
    ap.add_argument("--memory-strands", type=int, default=1000)
    ap.add_argument("--memory-frames", type=int, default=120)
    ap.add_argument("--memory-checkpoints", type=int, nargs="*", default=None,
                    help="checkpoint_every values of the memory rows (default: 0 and ⌈√frames⌉)")
    ap.add_argument("--memory-frame-checkpoints", type=int, nargs="*", default=None,
                    help="checkpoint_every values of the memory rows with checkpoint_frames=True (default: ⌈√frames⌉)")
    ap.add_argument("--memory-paths", nargs="+", default=["native"], choices=PATHS)
    ap.add_argument("--memory-reps", type=int, default=3, help="fresh-process probes per memory row (median reported)")
    ap.add_argument("--memory-probe", nargs=4, metavar=("S", "FRAMES", "EVERY", "PATH"), help=argparse.SUPPRESS)
    ap.add_argument("--memory-probe-frames", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--quick", action="store_true", help="toy sizes (a smoke run)")
    ap.add_argument("--note", default="")
    ap.add_argument("--out", default=str(ROOT / "docs" / "benchmarks" / "grad"))
    args = ap.parse_args(argv)
    if args.memory_probe:
        s, frames, every, path = args.memory_probe
        print(json.dumps(memory_probe(int(s), int(frames), int(every), path, args.device, args.dtype,
                                      args.resolution, args.memory_probe_frames)))
        return 0
    if args.quick:
        args.strands, args.reps, args.resolution = [16], 2, 8
        args.memory_strands, args.memory_frames = 16, 4
    if args.memory_checkpoints is None:
        args.memory_checkpoints = [0, math.ceil(math.sqrt(args.memory_frames))]
    if args.memory_frame_checkpoints is None:
        args.memory_frame_checkpoints = [math.ceil(math.sqrt(args.memory_frames))]
    torch.set_num_threads(args.threads)
    t0, load_start = time.perf_counter(), _load()
    head = at.default_head(4)
    grid = SDFGrid.from_mesh(head, resolution=64)
    records = []
    for scene in args.scenes:
        for s in args.strands:
            paths = [p for p in PATHS if p == "native" or s <= args.torch_max_strands]
            records += run_case(scene, s, args, head, grid, paths)
    memory = [memory_repeated(args, k, p) for p in args.memory_paths for k in args.memory_checkpoints]
    memory += [memory_repeated(args, k, p, True) for p in args.memory_paths for k in args.memory_frame_checkpoints]
    for m in memory:
        print(f"memory {m}", flush=True)
    out = Path(args.out)
    meta = {"command": ("python scripts/bench_grad.py " + shown_args(argv)).strip(), "machine": machine(args.device),
            "machine_info": machine_info(args.device), "device": args.device, "dtype": args.dtype,
            "wall_s": time.perf_counter() - t0, "load_start": load_start, "load_end": _load(), "note": args.note}
    out.parent.mkdir(parents=True, exist_ok=True)
    (out.parent / (out.name + ".json")).write_text(json.dumps({"meta": meta, "records": records, "memory": memory},
                                                              indent=1))
    render(records, memory, meta, out)
    print(f"wrote {out}.md in {meta['wall_s']:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
