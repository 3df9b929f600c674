"""Dataset generation and reading throughput (``ams-torch generate`` and HairSequenceDataset).

Sections (``--sections``, default all four):

* ``sim``: batched simulation alone, the cost that dataset generation scales with: B scenes of
  one groom (grown ``straight`` preset on the default head, head collisions on a 64³ SDF,
  hair–hair on a ``--resolution`` grid, native kernels) under B different head shakes, for
  ``--sim-strands`` (default 1,000 and 10,000) × 32 and B ∈ ``--sim-batches`` (default 1 2 4 8).
  Reported: ms per frame of the batch, sequence-frames per second, per core (÷ torch threads),
  and the batching ratio cost(B) / (B · cost(1)) against the target ≤ 0.6 from B = 4.
* ``ray``: the Ray backend (``generate_ray``) on a private loopback cluster of 1 and then 2
  worker CPUs, the same recipe (hair–hair on) each time: wall seconds and the speed-up.
* ``gen``, ``read``: as below.

Generation: one recipe (default: 1,000 grown strands × 32 particles on the default head, head
collisions, random head motions, 30 frames per sequence, 8 sequences) generated end to end with
``batch`` ∈ {1, 4} (sequences per batched simulation), timed as wall clock including growth,
SDF loading, simulation and HDF5 writes. Throughput is frames × strands per second.

Reading: the generated dataset (float32, shuffle + gzip), and copies of it stored as float16 +
gzip, float32 + lzf and float32 uncompressed, read through ``HairSequenceDataset(window=8)``
with ``DataLoader(batch_size=4, shuffle=True, num_workers ∈ {0, 1, 2})`` for up to --read-seconds
per case (after one warm-up batch). Reported: windows/s and MB/s of float32 tensors delivered.

Writes docs/benchmarks/datasets.json and docs/benchmarks/datasets.md.

    python scripts/bench_datasets.py            # default sizes, a few minutes on 2 CPU cores
    python scripts/bench_datasets.py --quick    # 200 strands × 16, 4 sequences of 10 frames
    python scripts/bench_datasets.py --sections sim ray --threads 2   # the issue-26 throughput tables
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from ams_torch._bench import machine, machine_info, shown_args  # noqa: E402
from ams_torch.apps.data import HairSequenceDataset  # noqa: E402
from ams_torch.apps.data.format import (FRAME_DIGESTS, FRAMED, SEQ_PREFIX, array_digest,  # noqa: E402
                                         sequence_checksum)
from ams_torch.apps.data.metadata import ATTRS_DIGEST, attrs_digest  # noqa: E402
from ams_torch.apps.datagen import generate  # noqa: E402
from ams_torch.apps.recipe import parse_recipe  # noqa: E402

SECTIONS = ("sim", "ray", "gen", "read")
BATCH_TARGET = 0.6  # issue 26: batching B scenes costs ≤ 0.6·B of one scene, from B = 4


def bench_recipe(strands: int, particles: int, frames: int, sequences: int, batch: int,
                 hair_hair: int = 0) -> dict:
    """The benchmark recipe; ``hair_hair`` > 0 turns the stage on at that grid resolution."""
    extra = {"hair_hair": {"resolution": hair_hair}} if hair_hair else {}
    return {
        "name": f"bench-b{batch}", "sequences": sequences, "frames": frames, "batch": batch,
        "head": {"mesh": "default", "subdivisions": 4, "sdf_resolution": 64},
        "groom": {"preset": {"choice": ["straight", "wavy", "bob"]}, "strands": strands, "particles": particles},
        "stages": {"collisions": True, "hair_hair": bool(hair_hair)}, **extra,
        "motion": {"type": {"choice": ["shake", "nod", "random"]},
                   "shake": {"amplitude": {"uniform": [0.3, 0.9]}, "frequency": {"uniform": [0.8, 2.0]}},
                   "random": {"keys": 3}},
        "store": {"guides": 64 if strands >= 64 else 0},
    }


def _batched_shakes(frames: int, dt: float, scenes: int):
    """One pose batch (B, 3, 3) per frame: B head shakes of different amplitudes and frequencies."""
    from ams_torch.geometry.pose import Pose
    from ams_torch.apps.motion import Shake

    runs = [Shake(amplitude=0.3 + 0.6 * b / max(1, scenes - 1), frequency=0.8 + 1.2 * b / max(
        1, scenes - 1)).poses(frames, dt) for b in range(scenes)]
    return [Pose(*(torch.stack([getattr(r[k], f) for r in runs]) for f in
                   ("rotation", "translation", "linear_velocity", "angular_velocity")), check=False)
            for k in range(frames)]


def bench_simulation(strands: int, particles: int, batches, frames: int, resolution: int, warmup: int = 2) -> list:
    """Batched simulation throughput (the ``sim`` section): one record per B."""
    import ams_torch as at

    groom = at.preset("straight", strands=strands, particles=particles, seed=0)
    head = at.MeshCollider(at.default_head(4), resolution=64)
    sim = at.Simulator(groom.rest_positions, at.Params(), hair_hair=at.HairHair(resolution=resolution),
                       colliders=[head], backend="native")
    threads = torch.get_num_threads()
    out = []
    for b in batches:
        poses = _batched_shakes(warmup + frames, sim.params.dt, b)
        state = sim.initial_state(poses[0])
        for k in range(warmup):
            state = sim.step(state, poses[k])
        wall, cpu = time.perf_counter(), time.process_time()
        for k in range(warmup, warmup + frames):
            state = sim.step(state, poses[k])
        sim.check(state)
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
        ms = 1e3 * wall / frames
        rec = {"strands": strands, "particles": particles, "batch": b, "frames": frames, "resolution": resolution,
               "threads": threads, "ms_per_frame": ms, "cpu_ms_per_frame": 1e3 * cpu / frames,
               "sequence_frames_per_s": 1e3 * b / ms, "sequence_frames_per_s_per_core": 1e3 * b / ms / threads,
               "grid_capacity": sim.hair_hair_grid.capacity}
        out.append(rec)
    one = next((r for r in out if r["batch"] == 1), None)
    for r in out:
        r["batch_ratio"] = r["ms_per_frame"] / (r["batch"] * one["ms_per_frame"]) if one else float("nan")
    return out


def bench_ray(strands: int, particles: int, frames: int, sequences: int, batch: int, resolution: int, workers,
              tmp: str) -> list:
    """The Ray backend on a private loopback cluster of w worker CPUs, for each w (``ray`` section)."""
    from ams_torch.apps.datagen.ray_backend import generate_ray, start_local_ray

    recipe = parse_recipe(bench_recipe(strands, particles, frames, sequences, batch, resolution), where="ray bench")
    out = []
    before = os.environ.get("OMP_NUM_THREADS")
    for w in workers:
        folder = os.path.join(tmp, f"ray-{w}")
        os.environ["OMP_NUM_THREADS"] = "1"  # one thread per task: w tasks on w CPUs
        ray = start_local_ray(num_cpus=w)
        try:
            t0 = time.perf_counter()
            generate_ray(recipe, folder, num_shards=1, progress=False, log=lambda s: None)
            sec = time.perf_counter() - t0
        finally:
            ray.shutdown()
            if before is None:
                os.environ.pop("OMP_NUM_THREADS", None)
            else:
                os.environ["OMP_NUM_THREADS"] = before
        out.append({"workers": w, "seconds": sec, "strands": strands, "particles": particles, "frames": frames,
                    "sequences": sequences, "batch": batch, "resolution": resolution,
                    "sequence_frames_per_s": frames * sequences / sec})
    for r in out:
        r["speedup"] = out[0]["seconds"] / r["seconds"]
    return out


def copy_with_storage(src: str, dst: str, precision: str, compression: str) -> None:
    """Copy a dataset file, rewriting the per-frame arrays (positions, velocities, guide
    positions) of every sequence with other storage settings. Everything else (header, /mask,
    /scene, the small arrays) is copied as it is; the rewritten arrays' checksums (per frame,
    whole array) and the sequence checksum are recomputed, so the copy reads and verifies like a
    generated file."""
    filters = {} if compression == "none" else {"compression": compression, "shuffle": True}
    dtype = np.float16 if precision == "float16" else np.float32
    with h5py.File(src, "r") as a, h5py.File(dst, "w") as b:
        for k, v in a.attrs.items():
            b.attrs[k] = v
        for name in a:
            if not name.startswith(SEQ_PREFIX):
                a.copy(a[name], b, name)
                continue
            g = b.create_group(name)
            for k, v in a[name].attrs.items():
                g.attrs[k] = v
            digests = {}
            for key in a[name]:
                if key == FRAME_DIGESTS:
                    continue
                d = a[name][key]
                if key in FRAMED:
                    data = np.ascontiguousarray(d[()].astype(dtype))
                    out = g.create_dataset(key, data=data, chunks=(1,) + d.shape[1:], fletcher32=True, **filters)
                    for k, v in d.attrs.items():
                        out.attrs[k] = v
                    out.attrs["sha256"] = array_digest([data])
                    g.create_dataset(f"{FRAME_DIGESTS}/{key}", data=np.stack(
                        [np.frombuffer(hashlib.sha256(f.tobytes()).digest(), np.uint8) for f in data]))
                else:
                    a[name].copy(d, g, key)
                    out = g[key]
                digests[key] = (out.dtype.str, out.shape, out.attrs["sha256"])
            g.attrs["checksum"] = sequence_checksum(digests)
            g.attrs[ATTRS_DIGEST] = attrs_digest(g.attrs)  # the attributes' digest covers the new checksum


def read_throughput(folder: str, workers: int, seconds: float, window: int = 8, batch_size: int = 4) -> dict:
    ds = HairSequenceDataset(folder, window=window)
    loader = torch.utils.data.DataLoader(ds, batch_size=batch_size, shuffle=True, num_workers=workers,
                                         generator=torch.Generator().manual_seed(0), persistent_workers=False)
    it = iter(loader)
    next(it)  # warm-up: worker start, first file opens
    n_items, n_bytes, t0 = 0, 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        try:
            b = next(it)
        except StopIteration:
            it = iter(loader)
            continue
        n_items += b["positions"].shape[0]
        n_bytes += sum(v.numel() * v.element_size() for v in b.values() if isinstance(v, torch.Tensor))
    dt = time.perf_counter() - t0
    del it
    return {"windows_per_s": n_items / dt, "mb_per_s": n_bytes / dt / 1e6, "window": window,
            "batch_size": batch_size, "items": n_items}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sections", nargs="+", default=list(SECTIONS), choices=SECTIONS)
    ap.add_argument("--strands", type=int, default=1000)
    ap.add_argument("--particles", type=int, default=32)
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--sequences", type=int, default=8)
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 4])
    ap.add_argument("--small", type=lambda t: tuple(int(v) for v in t.split("x")), nargs="*", default=[(200, 16)],
                    help="further groom sizes SxN for the generation table (default 200x16)")
    ap.add_argument("--workers", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--read-seconds", type=float, default=8.0)
    ap.add_argument("--sim-strands", type=int, nargs="+", default=[1000, 10000])
    ap.add_argument("--sim-batches", type=int, nargs="+", default=[1, 2, 4, 8])
    ap.add_argument("--sim-frames", type=int, default=20)
    ap.add_argument("--resolution", type=int, default=64, help="hair–hair grid of the sim and ray sections")
    ap.add_argument("--ray-workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--ray-sequences", type=int, default=8)
    ap.add_argument("--ray-batch", type=int, default=2)
    ap.add_argument("--threads", type=int, help="torch threads for generation")
    ap.add_argument("--quick", action="store_true", help="200 strands x 16, 4 sequences of 10 frames")
    ap.add_argument("--note", default="")
    ap.add_argument("--out", default=str(REPO / "docs" / "benchmarks"))
    args = ap.parse_args(argv)
    if args.quick:
        args.strands, args.particles, args.frames, args.sequences, args.read_seconds = 200, 16, 10, 4, 2.0
        args.small = []
        args.sim_strands, args.sim_frames, args.ray_sequences = [200], 5, 4
    if args.threads:
        torch.set_num_threads(args.threads)
    info = machine_info("cpu")
    t_start = time.perf_counter()
    tmp = tempfile.mkdtemp(prefix="ams_bench_datasets_")
    records = {"machine": machine("cpu"), "info": info, "sections": args.sections, "generation": [], "reading": [],
               "simulation": [], "ray": []}
    try:
        if "sim" in args.sections:
            for strands in args.sim_strands:
                for rec in bench_simulation(strands, args.particles, args.sim_batches, args.sim_frames, args.resolution):
                    records["simulation"].append(rec)
                    print(f"simulate {strands}x{args.particles} B={rec['batch']}: {rec['ms_per_frame']:.1f} ms/frame, "
                          f"{rec['sequence_frames_per_s_per_core']:.1f} sequence-frames/s per core, "
                          f"batch ratio {rec['batch_ratio']:.2f}", flush=True)
        if "ray" in args.sections:
            for rec in bench_ray(args.strands, args.particles, args.frames, args.ray_sequences, args.ray_batch,
                                 args.resolution, args.ray_workers, tmp):
                records["ray"].append(rec)
                print(f"ray {rec['workers']} worker(s): {rec['seconds']:.1f} s, speed-up {rec['speedup']:.2f}",
                      flush=True)
        if "gen" not in args.sections and "read" not in args.sections:
            raise _Done

        # each size first warms the caches (head SDF, growth SDF, native solver build)
        folders = {}
        if "gen" not in args.sections:  # reading needs a generated dataset: generate the first size only
            args.small, args.batches = [], args.batches[:1]
        sizes = [(args.strands, args.particles)] + [(s, n) for s, n in args.small if (s, n) != (args.strands, args.particles)]
        for strands, particles in sizes:
            warm = parse_recipe(bench_recipe(strands, particles, 2, 1, 1), where="warm-up")
            generate(warm, os.path.join(tmp, f"warm-{strands}"), progress=False, log=lambda s: None)
            for batch in args.batches:
                r = parse_recipe(bench_recipe(strands, particles, args.frames, args.sequences, batch),
                                 where=f"batch {batch}")
                out = os.path.join(tmp, f"gen-{strands}x{particles}-b{batch}")
                t0 = time.perf_counter()
                paths = generate(r, out, progress=False, log=lambda s: None)
                sec = time.perf_counter() - t0
                size = sum(os.path.getsize(p) for p in paths)
                rec = {"strands": strands, "particles": particles, "frames": args.frames,
                       "sequences": args.sequences, "batch": batch, "seconds": sec,
                       "frame_strands_per_s": args.frames * args.sequences * strands / sec,
                       "ms_per_sequence_frame": 1e3 * sec / (args.frames * args.sequences), "file_mb": size / 1e6}
                records["generation"].append(rec)
                folders[(strands, batch)] = out
                print(f"generate {strands}x{particles} batch={batch}: {sec:.1f} s, "
                      f"{rec['frame_strands_per_s']:.3g} frame·strands/s, "
                      f"{rec['ms_per_sequence_frame']:.1f} ms per sequence-frame, {size / 1e6:.1f} MB", flush=True)
        if "read" not in args.sections:
            raise _Done
        base = folders[(args.strands, args.batches[0])]
        src = next(os.path.join(base, n) for n in os.listdir(base) if n.endswith(".h5"))
        variants = {"float32 + gzip": base}
        for prec, comp in (("float16", "gzip"), ("float32", "lzf"), ("float32", "none")):
            d = os.path.join(tmp, f"{prec}-{comp}")
            os.makedirs(d)
            copy_with_storage(src, os.path.join(d, os.path.basename(src)), prec, comp)
            variants[f"{prec} + {comp}"] = d
        for label, folder in variants.items():
            size = sum(os.path.getsize(os.path.join(folder, n)) for n in os.listdir(folder) if n.endswith(".h5"))
            for w in args.workers:
                rec = {"storage": label, "workers": w, "file_mb": size / 1e6,
                       **read_throughput(folder, w, args.read_seconds)}
                records["reading"].append(rec)
                print(f"read {label:15s} workers={w}: {rec['windows_per_s']:.1f} windows/s, "
                      f"{rec['mb_per_s']:.0f} MB/s ({size / 1e6:.1f} MB on disk)", flush=True)
    except _Done:
        pass
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    records["seconds"] = time.perf_counter() - t_start
    records["argv"] = (" " + shown_args(argv)) if shown_args(argv) else ""
    records["load_avg_1min_at_end"] = round(os.getloadavg()[0], 2)
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "datasets.json"), "w") as f:
        json.dump(records, f, indent=1)
    write_md(records, args, os.path.join(args.out, "datasets.md"))
    print(f"wrote {args.out}/datasets.json and datasets.md ({records['seconds']:.0f} s)")


class _Done(Exception):
    """The sections asked for are done."""


def _sim_lines(rec: dict) -> list:
    sims = rec["simulation"]
    if not sims:
        return []
    r0 = sims[0]
    lines = ["## Batched simulation (the cost dataset generation scales with)", "",
             f"One groom (grown `straight` preset, N = {r0['particles']}) on the default head, head collisions "
             f"(64³ SDF), hair–hair on a {r0['resolution']}³ grid, native kernels, {r0['threads']} torch thread(s); "
             f"B scenes under B different head shakes run as one batched simulation, {r0['frames']} timed frames "
             "after 2 warm-up frames. Sequence-frames/s = B / (seconds per frame); per core = ÷ threads. Batch "
             f"ratio = cost(B) / (B · cost(1)); target ≤ {BATCH_TARGET} from B = 4.", "",
             "| strands | B | ms / frame (batch) | CPU ms / frame | sequence-frames / s | per core | batch ratio | |",
             "|---:|---:|---:|---:|---:|---:|---:|---|"]
    for r in sims:
        ok = "" if r["batch"] < 4 else ("met" if r["batch_ratio"] <= BATCH_TARGET else "not met")
        lines.append(f"| {r['strands']:,} | {r['batch']} | {r['ms_per_frame']:.1f} | {r['cpu_ms_per_frame']:.1f} | "
                     f"{r['sequence_frames_per_s']:.1f} | {r['sequence_frames_per_s_per_core']:.1f} | "
                     f"{r['batch_ratio']:.2f} | {ok} |")
    return lines + [""] + _batch_model_lines(sims)


def batch_model(sims: list) -> dict:
    """Per strand count, the least-squares line cost(B) = shared + per_scene · B (ms per frame) over
    the batch sizes measured: what a frame pays once (Python between kernels, thread start-up, a
    scene-independent pass) and what each scene adds."""
    out = {}
    for s in sorted({r["strands"] for r in sims}):
        pts = [(r["batch"], r["ms_per_frame"]) for r in sims if r["strands"] == s]
        if len({b for b, _ in pts}) < 2:
            continue
        n = len(pts)
        mb, mt = sum(b for b, _ in pts) / n, sum(t for _, t in pts) / n
        slope = sum((b - mb) * (t - mt) for b, t in pts) / sum((b - mb) ** 2 for b, _ in pts)
        out[s] = {"shared_ms": mt - slope * mb, "per_scene_ms": slope}
    return out


def _batch_model_lines(sims: list) -> list:
    model = batch_model(sims)
    if not model:
        return []
    parts = [f"{s:,} strands: {m['shared_ms']:.1f} ms shared + {m['per_scene_ms']:.1f} ms per scene"
             for s, m in model.items()]
    need = (4 - 4 * BATCH_TARGET) / (4 * BATCH_TARGET - 1)  # ratio(4) <= target  <=>  shared >= need * per_scene
    return [f"Why the ratio stays where it is: fitted per frame, {'; '.join(parts)}. With cost(B) = shared + B · "
            f"per-scene, the ratio at B = 4 is (shared + 4 · per-scene) / (4 · (shared + per-scene)), at most "
            f"{BATCH_TARGET} only when the shared part is at least {need:.2f}× one scene's own work. Every stage's "
            "work here is per scene (each scene has its own strands, contacts and grid), so on a CPU that the "
            "single scene already keeps busy batching saves only the shared overhead; the 0.6 target needs a "
            "device that one scene leaves mostly idle (a GPU), where B scenes fill the same launches.", ""]


def _ray_lines(rec: dict) -> list:
    rays = rec["ray"]
    if not rays:
        return []
    r0 = rays[0]
    lines = ["## The Ray backend on a loopback cluster", "",
             f"`generate_ray` of one recipe ({r0['strands']:,} × {r0['particles']} grown strands, head collisions, "
             f"hair–hair {r0['resolution']}³, {r0['sequences']} sequences of {r0['frames']} frames in batch groups "
             f"of {r0['batch']}: {r0['sequences'] // r0['batch']} tasks) on a private Ray cluster bound to 127.0.0.1 "
             "with 1, then 2, worker CPUs (one torch thread per task), wall clock including Ray's start of the "
             "tasks and the shard assembly.", "",
             "| worker CPUs | seconds | sequence-frames / s | speed-up |", "|---:|---:|---:|---:|"]
    for r in rays:
        lines.append(f"| {r['workers']} | {r['seconds']:.1f} | {r['sequence_frames_per_s']:.1f} | {r['speedup']:.2f}× |")
    return lines + [""]


def _gen_lines(rec: dict) -> list:
    if not rec["generation"]:
        return []
    g0 = rec["generation"][0]
    sizes = sorted({(r["strands"], r["particles"]) for r in rec["generation"]}, reverse=True)
    lines = [
        "## Generation (`ams-torch generate`, one shard, wall clock end to end)", "",
        f"Recipe: {' or '.join(f'{a:,} × {b}' for a, b in sizes)} (strands × particles) grown on the default head (preset drawn "
        f"from straight / wavy / bob), head collisions (64³ SDF), random shake / nod / keyframe motions, "
        f"{g0['frames']} frames per sequence, {g0['sequences']} sequences, float32, shuffle + gzip, 64 guides "
        f"stored. `batch` sequences share a groom and run as one batched simulation.", "",
        "| strands × particles | batch | seconds | frame·strands / s | ms per sequence-frame | file MB |",
        "|---|---|---|---|---|---|",
    ]
    for r in rec["generation"]:
        lines.append(f"| {r['strands']:,} × {r['particles']} | {r['batch']} | {r['seconds']:.1f} | "
                     f"{r['frame_strands_per_s']:,.0f} | {r['ms_per_sequence_frame']:.1f} | {r['file_mb']:.1f} |")
    for s_, n_ in sizes:
        rows = [r for r in rec["generation"] if (r["strands"], r["particles"]) == (s_, n_)]
        if len(rows) > 1:
            a, b = rows[0], rows[-1]
            lines += ["", f"{s_:,} × {n_}: batching {b['batch']} sequences per simulation gives "
                          f"{a['seconds'] / b['seconds']:.2f}× the throughput of batch {a['batch']}."]
    return lines + [""]


def _read_lines(rec: dict) -> list:
    if not rec["reading"]:
        return []
    lines = ["## Reading (`HairSequenceDataset(window=8)` + `DataLoader(batch_size=4, shuffle=True)`)", "",
             "MB/s counts the float32 tensors delivered (positions, guide positions, head poses).", "",
             "| storage | file MB | workers | windows / s | MB / s |", "|---|---|---|---|---|"]
    for r in rec["reading"]:
        lines.append(f"| {r['storage']} | {r['file_mb']:.1f} | {r['workers']} | {r['windows_per_s']:.1f} | "
                     f"{r['mb_per_s']:.0f} |")
    best = {}
    for r in rec["reading"]:
        if r["storage"] not in best or r["windows_per_s"] > best[r["storage"]]["windows_per_s"]:
            best[r["storage"]] = r
    lines += ["", "Fastest per storage: " + "; ".join(f"{k}: {v['workers']} worker(s), {v['windows_per_s']:.0f} windows/s"
                                                   for k, v in best.items()) + ". A worker hands every window "
              "to the main process through shared memory (one 8-frame window of the dense groom is "
              f"{rec['reading'][0]['mb_per_s'] / max(rec['reading'][0]['windows_per_s'], 1e-9):.1f} MB), so "
              "workers pay off only when decompression, not that copy, is the bottleneck and cores are free."]
    lines += ["", "float16 storage halves the file; its rounding error is at most 2⁻¹¹ of a coordinate (0.12 mm at "
                  "0.25 m; `tests/test_datasets.py` measures it). Uncompressed files read fastest here, gzip "
                  "saves about a fifth of the disk on float32 positions."]
    return lines + [""]


def write_md(rec: dict, args, path: str) -> None:
    lines = [
        "# Datasets: simulation, generation and read throughput", "",
        f"Machine: {rec['machine']}  ",
        f"Load average (1 min): {rec['info']['load_avg_1min_at_start']} at the start, "
        f"{rec['load_avg_1min_at_end']} at the end (other processes inflate the timings).  ",
        f"Run: `.venv/bin/python scripts/bench_datasets.py{rec['argv']}` "
        f"({rec['seconds']:.0f} s).{' ' + args.note if args.note else ''}", "",
    ]
    lines += _sim_lines(rec) + _ray_lines(rec) + _gen_lines(rec) + _read_lines(rec)
    with open(path, "w") as f:
        f.write("\n".join(lines).rstrip() + "\n")


if __name__ == "__main__":
    main()
