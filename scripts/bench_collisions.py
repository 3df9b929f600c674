"""Benchmark hair–solid collisions (SPEC §8): SDF build time and the collision stage per frame.

    .venv/bin/python scripts/bench_collisions.py                 # CPU, default cases
    .venv/bin/python scripts/bench_collisions.py --device cuda   # GPU (synchronised timings)

1. SDF build of the default head (``SDFGrid.from_mesh``, cache off) at each ``--resolutions``,
   and the time to load the same grid from the disk cache.
2. The collision stage as the simulator runs it each frame (``resolve_world_poses`` + ``collide``)
   for strands × 32 particles hanging from the default head's scalp
   (``ams_torch.grooms.head.hanging_groom``), posed by a turning head with velocities, jittered by
   ±4 mm and given random velocities so that a realistic share of particles (reported) is in
   contact. Scenes: the head mesh collider (128³ grid), one analytic sphere (a hand) moving
   through the hair, and both. Each case: one warm-up call, then up to ``--reps`` timed calls
   or until ``--case-cap`` seconds are spent (at least one); the median is reported.

Writes ``docs/benchmarks/collisions.json`` and ``.md`` (the machine is named in both).
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from ams_torch._bench import machine, sync  # noqa: E402
from ams_torch.stages.collide import (  # noqa: E402
    MeshCollider,
    SphereCollider,
    collide,
    collider_distances,
    resolve_world_poses,
)
from ams_torch.grooms.head import default_head, hanging_groom  # noqa: E402
from ams_torch.geometry.pose import Pose  # noqa: E402
from ams_torch.geometry.sdf import SDFGrid  # noqa: E402

DT = 1.0 / 60.0
ROOT = Path(__file__).resolve().parents[1]


def bench_sdf_build(mesh, resolutions):
    """Returns (table rows, {resolution: SDFGrid})."""
    rows, grids = [], {}
    with tempfile.TemporaryDirectory() as tmp:
        for res in resolutions:
            t0 = time.perf_counter()
            grid = SDFGrid.from_mesh(mesh, resolution=res, cache=True, cache_dir=tmp)
            build = time.perf_counter() - t0
            t0 = time.perf_counter()
            SDFGrid.from_mesh(mesh, resolution=res, cache=True, cache_dir=tmp)
            load = time.perf_counter() - t0
            grids[res] = grid
            rows.append(dict(resolution=res, shape=list(grid.shape), voxel_mm=grid.voxel_size * 1e3,
                             faces=len(mesh.faces), build_s=build, cached_load_s=load))
            print(f"SDF {res:4d}: {'x'.join(map(str, grid.shape))}, voxel {grid.voxel_size * 1e3:.2f} mm, "
                  f"build {build:.2f} s, cached load {load * 1e3:.0f} ms", flush=True)
    return rows, grids


def make_inputs(base, strands, device, dtype, seed=0):
    """Tile/jitter the base groom up to ``strands`` strands, pose it, add velocities."""
    gen = torch.Generator().manual_seed(seed)
    reps = -(-strands // base.shape[0])
    rest = base.repeat(reps, 1, 1)[:strands]
    rest = rest + 0.004 * (2 * torch.rand(rest.shape, generator=gen, dtype=rest.dtype) - 1)
    head = Pose.from_rotvec([0.05, 0.6, -0.1], [0.0, 1.6, 0.0], [0.3, 0.0, -0.2], [0.0, 3.0, 0.5],
                            dtype=torch.float64).to(device=device, dtype=dtype)
    x = head.to_world(rest.to(device=device, dtype=dtype))
    v = 0.5 * torch.randn(x.shape, generator=gen, dtype=rest.dtype).to(device=device, dtype=dtype)
    return x, v, head


def time_case(fn, device, reps, cap):
    fn()  # warm-up
    sync(device)
    times = []
    start = time.perf_counter()
    while len(times) < reps and (not times or time.perf_counter() - start < cap):
        t0 = time.perf_counter()
        fn()
        sync(device)
        times.append(time.perf_counter() - t0)
    return statistics.median(times), len(times)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--strands", type=int, nargs="+", default=[1000, 10000, 100000])
    ap.add_argument("--particles", type=int, default=32)
    ap.add_argument("--resolutions", type=int, nargs="+", default=[64, 128])
    ap.add_argument("--collider-resolution", type=int, default=128)
    ap.add_argument("--reps", type=int, default=10)
    ap.add_argument("--case-cap", type=float, default=5.0, help="seconds of timed calls per case")
    ap.add_argument("--threads", type=int, default=1,
                    help="torch CPU threads (default 1: on a shared machine, 2 threads fighting other "
                         "jobs for 2 cores ran small ops ~80x slower here)")
    ap.add_argument("--out", default=str(ROOT / "docs" / "benchmarks" / "collisions"))
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    dtype = torch.float32
    desc = machine(device)
    print(desc, flush=True)

    mesh = default_head()
    sdf_rows, grids = bench_sdf_build(mesh, args.resolutions)

    grid = grids.get(args.collider_resolution)
    if grid is None:
        grid = SDFGrid.from_mesh(mesh, resolution=args.collider_resolution)  # the user's disk cache
    head_collider = MeshCollider(grid, friction=0.5)
    hand = SphereCollider((0.0, 0.0, 0.0), 0.06, friction=0.3)
    hand_pose = Pose.from_rotvec([0.0, 0.0, 0.0], [0.05, 1.55, 0.12], [-1.0, 0.0, -0.5], [0.0, 0.0, 0.0],
                                 device=device, dtype=dtype)
    base = hanging_groom(mesh, 2000, args.particles, 0.2, sdf=grid, seed=0)
    scenes = {
        "head mesh": [head_collider],
        "sphere": [hand],
        "head mesh + sphere": [head_collider, hand],
    }
    rows = []
    for strands in args.strands:
        x, v, head = make_inputs(base, strands, device, dtype)
        free = torch.arange(args.particles, device=device) >= 2
        for name, cols in scenes.items():
            overrides = [hand_pose if c is hand else None for c in cols]

            def stage():
                poses = resolve_world_poses(cols, head, overrides)
                return collide(x, v, DT, cols, poses, free=free)

            poses = resolve_world_poses(cols, head, overrides)
            d = collider_distances(x, cols, poses)
            contacts = float(((d < 0).any(0) & free).float().mean())
            ms, n = time_case(stage, device, args.reps, args.case_cap)
            ms *= 1e3
            rows.append(dict(strands=strands, particles=args.particles, scene=name, ms_per_frame=ms,
                             contact_share=contacts, reps=n,
                             ns_per_particle=ms * 1e6 / (strands * args.particles)))
            print(f"{strands:7d} x {args.particles}  {name:20s} {ms:9.2f} ms/frame  "
                  f"({contacts * 100:.1f} % of free particles in contact, {n} reps)", flush=True)

    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    result = dict(machine=desc, device=str(device), dtype=str(dtype), dt=DT,
                  note="machine shared with other jobs while measuring; medians",
                  sdf_build=sdf_rows, collision_stage=rows)
    suffix = "" if device.type == "cpu" else f"_{device.type}"
    json_path = out.with_name(out.name + suffix + ".json")
    json_path.write_text(json.dumps(result, indent=2) + "\n")
    lines = [
        f"# Hair–solid collision benchmark ({device.type})",
        "",
        f"Machine: {desc}. Produced by `scripts/bench_collisions.py"
        f"{' --device ' + device.type if device.type != 'cpu' else ''}`; the machine was shared with other "
        "jobs, so treat the numbers as upper bounds. Medians of warmed-up calls.",
        "",
        "## SDF build (default head, point-cloud-utils, CPU)",
        "",
        "| resolution | grid | voxel (mm) | build (s) | cached load (ms) |",
        "|---|---|---|---|---|",
    ]
    for r in sdf_rows:
        lines.append(f"| {r['resolution']} | {'×'.join(map(str, r['shape']))} | {r['voxel_mm']:.2f} | "
                     f"{r['build_s']:.2f} | {r['cached_load_s'] * 1e3:.0f} |")
    lines += [
        "",
        f"## Collision stage per frame (`resolve_world_poses` + `collide`, {device.type}, float32, "
        f"head grid {args.collider_resolution})",
        "",
        "| strands × particles | scene | ms / frame | ns / particle | free particles in contact |",
        "|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(f"| {r['strands']:,} × {r['particles']} | {r['scene']} | {r['ms_per_frame']:.2f} | "
                     f"{r['ns_per_particle']:.1f} | {r['contact_share'] * 100:.1f} % |")
    json_path.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print(f"wrote {json_path} and {json_path.with_suffix('.md')}")


if __name__ == "__main__":
    main()
