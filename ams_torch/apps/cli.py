"""The ``ams-torch`` command line: simulate a scene, render a saved sequence, report the setup.

    ams-torch simulate SCENE.toml [--frames F] [--scale s] [--device cpu|cuda] [--dtype float32|float64]
                                  [--out DIR] [--no-video]
        → DIR/sequence.h5 (dataset ``positions`` (F, S, N, 3) float32 m, world frame;
          ``rotations`` (F, 3, 3), ``translations`` (F, 3) m head poses; ``rest_positions``
          (S, N, 3); ``collider_rotations``/``collider_translations`` (F, C, 3, 3)/(F, C, 3) when
          the scene has [[colliders]]; attrs ``scene``, ``params``, ``ms_per_frame`` (JSON), ``dt`` s) and
          DIR/final.npz (the last frame: positions, velocities, rest_positions, head pose),
          DIR/final.png (a picture of it) and DIR/video.mp4; prints ms/frame per stage.
    ams-torch render FILE.h5 [--out video.mp4|frame.png] [--view front|side|back] [--every k]
    ams-torch generate RECIPE.toml --out DIR [--shard i/n | --shards n] [--backend local|ray]
        → DIR/<name>-shard-<i>-of-<n>.h5 (layout: docs/dataset_format.md); resumes a killed run.
    ams-torch validate DIR|FILE   (exit status 0 only when every file is sound)
    ams-torch info
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from typing import Optional

import numpy as np

__all__ = ["main", "write_sequence", "write_final", "read_sequence"]


def write_sequence(path: str, result: dict, scene: dict, params, rest: np.ndarray) -> str:
    """Write a simulation result to HDF5 atomically (temporary name, then ``os.replace``)."""
    import h5py

    tmp = f"{path}.tmp{os.getpid()}"
    with h5py.File(tmp, "w") as f:
        f.create_dataset("positions", data=result["positions"].astype(np.float32), compression="gzip",
                         compression_opts=1, chunks=(1,) + result["positions"].shape[1:])
        f.create_dataset("rotations", data=result["rotations"].astype(np.float32))
        f.create_dataset("translations", data=result["translations"].astype(np.float32))
        f.create_dataset("rest_positions", data=np.asarray(rest, dtype=np.float32))
        for k in ("collider_rotations", "collider_translations"):
            if k in result:
                f.create_dataset(k, data=result[k].astype(np.float32))
        f.attrs["scene"] = json.dumps(scene)
        f.attrs["params"] = json.dumps(params.to_dict())
        f.attrs["ms_per_frame"] = json.dumps(result["ms_per_frame"])
        f.attrs["dt"] = float(params.dt)
        f.attrs["units"] = "metres, seconds; world frame, +y up"
    os.replace(tmp, path)
    return path


def write_final(path: str, result: dict, rest: np.ndarray) -> str:
    """Write the last frame of a run to ``.npz`` atomically: ``positions`` and ``velocities``
    (S, N, 3) float32 (m, m/s, world), ``rest_positions`` (S, N, 3) m head frame, ``rotation``
    (3, 3) and ``translation`` (3,) m the head pose, ``frame`` and ``time`` (s)."""
    state = result["state"]
    x, v = state.x.detach().cpu().float().numpy(), state.v.detach().cpu().float().numpy()
    tmp = f"{path}.tmp{os.getpid()}.npz"
    np.savez(tmp, positions=x, velocities=v, rest_positions=np.asarray(rest, dtype=np.float32),
             rotation=result["rotations"][-1].astype(np.float32),
             translation=result["translations"][-1].astype(np.float32),
             frame=np.int64(state.frame), time=np.float64(state.time))
    os.replace(tmp, path)
    return path


def read_sequence(path: str) -> dict:
    """Read a sequence written by :func:`write_sequence`: positions (F, S, N, 3), rotations,
    translations, rest_positions (and collider_rotations (F, C, 3, 3), collider_translations
    (F, C, 3) when the scene has colliders) and the parsed ``scene``/``params``/``ms_per_frame``, ``dt``."""
    import h5py

    if not os.path.isfile(path):
        raise FileNotFoundError(f"no such sequence file {path!r}")
    with h5py.File(path, "r") as f:
        if "positions" not in f:
            raise ValueError(f"{path}: no 'positions' dataset (not an ams-torch sequence)")
        out = {k: f[k][()] for k in ("positions", "rotations", "translations", "rest_positions",
                                     "collider_rotations", "collider_translations") if k in f}
        for k in ("scene", "params", "ms_per_frame"):
            out[k] = json.loads(f.attrs[k]) if k in f.attrs else {}
        out["dt"] = float(f.attrs.get("dt", 1.0 / 60.0))
    return out


def _head_for_render(scene: dict):
    """(vertices, faces, radius) to draw the scene's head (a coarse default head for speed)."""
    head = scene.get("head", {})
    mesh = head.get("mesh", "default")
    if mesh == "default":
        from ams_torch.grooms.head import default_head

        m = default_head(min(3, int(head.get("subdivisions", 3))))
        return m.vertices, m.faces, None
    if mesh == "sphere":
        return None, None, float(head.get("radius", 0.1))
    if mesh == "none":
        return None, None, None
    from ams_torch.geometry.mesh import load_mesh

    m = load_mesh(mesh)
    return m.vertices, m.faces, None


def _render(seq: dict, scene: dict, path: str, view: Optional[str] = None, every: Optional[int] = None,
            progress: bool = False) -> str:
    from ams_torch.apps.render import render_sequence

    r = scene.get("render", {})
    v, f, radius = _head_for_render(scene)
    fps = r.get("fps", 1.0 / seq["dt"])
    return render_sequence(seq["positions"], path, rotations=seq.get("rotations"),
                           translations=seq.get("translations"), fps=fps, every=every or r.get("every", 1),
                           progress=progress, colliders=scene.get("colliders", []),
                           collider_rotations=seq.get("collider_rotations"),
                           collider_translations=seq.get("collider_translations"), head_vertices=v, head_faces=f, head_radius=radius,
                           view=view or r.get("view", "front"), size=r.get("size", 4.0), title=scene.get("name", ""))


def _cmd_simulate(args) -> int:
    import torch

    from ams_torch.apps.scene import build, load_scene, simulate

    overrides = {}
    if args.frames is not None:
        overrides["frames"] = args.frames
    if args.scale is not None:
        overrides["scale"] = args.scale
    scene = load_scene(args.scene, overrides)
    dtype = {"float32": torch.float32, "float64": torch.float64}[args.dtype]
    device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
    os.makedirs(args.out, exist_ok=True)
    t0 = time.perf_counter()
    run = build(scene, device=device, dtype=dtype)
    s, n = run.sim.model.rest_positions.shape[:2]
    stages = [k for k, on in scene["stages"].items() if on]
    print(f"scene {scene['name']}: {s} strands x {n} particles on {device} ({args.dtype}), "
          f"{scene['frames']} frames of {run.sim.params.dt * 1e3:.2f} ms, stages: {', '.join(stages) or 'none'}; "
          f"built in {time.perf_counter() - t0:.1f} s")
    result = simulate(run, progress=not args.quiet)
    if not np.isfinite(result["positions"]).all():
        print("error: the simulation produced non-finite positions", file=sys.stderr)
        return 1
    h5 = write_sequence(os.path.join(args.out, "sequence.h5"), result, scene, run.sim.params, run.rest)
    print("ms/frame: " + ", ".join(f"{k} {v:.1f}" for k, v in result["ms_per_frame"].items()))
    print(f"wrote {h5}")
    final = write_final(os.path.join(args.out, "final.npz"), result, run.rest)
    print(f"wrote {final}")
    seq = read_sequence(h5)
    png = _render(seq, scene, os.path.join(args.out, "final.png"))  # a .png path draws the last frame
    print(f"wrote {png}")
    if not args.no_video:
        video = _render(seq, scene, os.path.join(args.out, "video.mp4"), progress=not args.quiet)
        print(f"wrote {video}")
    return 0


def _cmd_render(args) -> int:
    seq = read_sequence(args.file)
    out = args.out or os.path.join(os.path.dirname(os.path.abspath(args.file)), "video.mp4")
    path = _render(seq, seq["scene"], out, view=args.view, every=args.every, progress=not args.quiet)
    print(f"wrote {path}")
    return 0


def _cmd_info(args) -> int:
    import platform

    import torch

    from ams_torch import __version__

    print(f"ams_torch {__version__}, torch {torch.__version__}, python {platform.python_version()}, "
          f"numpy {np.__version__}")
    print(f"cpu: {os.cpu_count()} cores, torch threads {torch.get_num_threads()}")
    if torch.cuda.is_available():
        for i in range(torch.cuda.device_count()):
            p = torch.cuda.get_device_properties(i)
            print(f"cuda:{i}: {p.name}, {p.total_memory / 2**30:.1f} GiB, CUDA {torch.version.cuda}")
    else:
        print("cuda: not available")
    try:
        from ams_torch.solver import build as _native

        status = _native.native_status()
        print("native solver: " + ", ".join(f"{k}={v}" for k, v in status.items()))
    except (ImportError, AttributeError) as err:
        print(f"native solver: status unavailable ({err})")
    try:
        import imageio_ffmpeg

        print(f"video: imageio-ffmpeg {imageio_ffmpeg.__version__}")
    except ImportError:
        print("video: imageio-ffmpeg not installed (MP4 output unavailable)")
    return 0


def _cmd_generate(args) -> int:
    from ams_torch.apps.datagen import generate, generate_ray, parse_shard
    from ams_torch.apps.recipe import load_recipe

    overrides = {"sequences": args.sequences} if args.sequences is not None else None
    recipe = load_recipe(args.recipe, overrides)
    if args.threads:
        import torch

        torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    print(f"recipe {recipe.name}: {recipe.num_sequences} sequences x {recipe.frames} frames in "
          f"{recipe.num_groups} batch group(s) of up to {recipe.batch}; output {args.out}")
    if args.backend == "ray":
        if args.shard:
            print("error: --shard selects one shard for the local backend; with --backend ray use --shards N",
                  file=sys.stderr)
            return 2
        paths = generate_ray(recipe, args.out, args.shards or 1, address=args.ray_address, device=args.device,
                             cpus_per_task=args.cpus_per_task, progress=not args.quiet)
    else:
        if args.shard:
            i, n = parse_shard(args.shard)
            shards = [i]
        else:
            n = args.shards or 1
            shards = None
        paths = generate(recipe, args.out, shards=shards, num_shards=n, device=args.device, progress=not args.quiet)
    for p in paths:
        print(f"wrote {p}")
    print(f"done in {time.perf_counter() - t0:.1f} s")
    return 0


def _cmd_validate(args) -> int:
    from ams_torch.apps.data import validate

    problems, notes = validate(args.path, progress=not args.quiet)
    bad = 0
    for path, found in problems.items():
        if found:
            bad += 1
            print(f"FAIL {path}")
            for p in found:
                print(f"  - {p}")
        elif not args.quiet:
            print(f"ok   {path}")
    errors = [n for n in notes if n.startswith("error:")]
    for n in notes:
        print(n)
    print(f"{len(problems) - bad} of {len(problems)} file(s) sound")
    return 0 if bad == 0 and not errors else 1


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="ams-torch", description="Dense hair simulation with the AMS model.")
    sub = ap.add_subparsers(dest="command", required=True)
    sp = sub.add_parser("simulate", help="simulate a scene file (TOML)")
    sp.add_argument("scene")
    sp.add_argument("--frames", type=int)
    sp.add_argument("--scale", type=float, help="multiply the groom's strand count")
    sp.add_argument("--device", help="cpu or cuda (default: cuda when available)")
    sp.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    sp.add_argument("--out", default="out")
    sp.add_argument("--no-video", action="store_true")
    sp.add_argument("--quiet", action="store_true", help="no progress bars")
    sp.set_defaults(fn=_cmd_simulate)
    rp = sub.add_parser("render", help="render a sequence.h5 to MP4 (or PNG)")
    rp.add_argument("file")
    rp.add_argument("--out")
    rp.add_argument("--view", choices=("front", "side", "back"))
    rp.add_argument("--every", type=int)
    rp.add_argument("--quiet", action="store_true")
    rp.set_defaults(fn=_cmd_render)
    gp = sub.add_parser("generate", help="simulate a dataset recipe (TOML) into sharded HDF5 files")
    gp.add_argument("recipe")
    gp.add_argument("--out", required=True, help="output folder (one HDF5 file per shard)")
    gp.add_argument("--shard", help="i/n: generate only shard i of n (local backend)")
    gp.add_argument("--shards", type=int, help="number of shards (default 1; with --backend ray, one task each)")
    gp.add_argument("--sequences", type=int, help="override the recipe's number of sequences")
    gp.add_argument("--backend", choices=("local", "ray"), default="local")
    gp.add_argument("--ray-address", help="join this Ray cluster (default: start a private one on 127.0.0.1)")
    gp.add_argument("--cpus-per-task", type=float, default=1.0, help="Ray CPUs per shard task")
    gp.add_argument("--device", help="cpu or cuda (default cpu; Ray tasks take a GPU each when there are GPUs)")
    gp.add_argument("--threads", type=int, help="torch CPU threads")
    gp.add_argument("--quiet", action="store_true", help="no progress bars")
    gp.set_defaults(fn=_cmd_generate)
    vp = sub.add_parser("validate", help="check dataset files (structure, checksums, NaN, frame counts)")
    vp.add_argument("path", help="a dataset folder or file")
    vp.add_argument("--quiet", action="store_true")
    vp.set_defaults(fn=_cmd_validate)
    ip = sub.add_parser("info", help="versions, devices, native solver status")
    ip.set_defaults(fn=_cmd_info)
    args = ap.parse_args(argv)
    from ams_torch.apps.scene import SceneError

    try:
        return args.fn(args)
    except (SceneError, FileNotFoundError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
