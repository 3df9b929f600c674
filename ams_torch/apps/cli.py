"""The ``ams-torch`` command line: simulate a scene, render a sequence, generate and validate datasets.

    ams-torch [--debug] simulate SCENE.toml [--frames F] [--scale s] [--device cpu|cuda|cuda:N]
                                  [--dtype float32|float64] [--out DIR] [--no-video] [--max-memory SIZE]
        → DIR/sequence.h5 (streamed frame by frame; a run that fails keeps its frames in
          DIR/sequence.partial.h5) (dataset ``positions`` (F, S, N, 3) float32 m, world frame;
          ``rotations`` (F, 3, 3), ``translations`` (F, 3) m head poses; ``rest_positions``
          (S, N, 3); ``collider_rotations``/``collider_translations`` (F, C, 3, 3)/(F, C, 3) when
          the scene has [[colliders]]; attrs ``scene``, ``params``, ``ms_per_frame`` (JSON), ``dt`` s) and
          DIR/final.npz (the last frame: positions, velocities, rest_positions, head pose),
          DIR/final.png (a picture of it) and DIR/video.mp4; prints ms/frame per stage.
    ams-torch render FILE.h5|DATASET_DIR [--sequence K] [--out video.mp4|frame.png] [--view front|side|back]
                                  [--every k]
    ams-torch generate RECIPE.toml|SUITE_FOLDER --out DIR [--shard i/n | --shards n] [--backend local|ray] [--wait]
                                  [--max-memory SIZE]
        → DIR/<name>-shard-<i>-of-<n>.h5 (shards numbered from 0; layout: docs/dataset_format.md);
          resumes a killed run; one run per folder at a time (a lock file).
    ams-torch validate DIR|FILE [--allow-partial]
        exit 0: complete and sound; 1: problems found (each listed); 2: could not run.
    ams-torch export SEQUENCE.h5 --usd OUT.usd[a|c] [--every k] [--width m]
        → animated USD (BasisCurves with time-sampled points, the head and colliders as meshes
          with time-sampled transforms; docs/assets.md), for Blender, Houdini, Omniverse, Unreal.
    ams-torch bench-interp DATASET_OR_SUITE --methods M1,M2,pkg.mod:factory --guides 64,256 --out DIR
                                  [--train] [--device cuda] [--guide-source alone|dense|both]
        → DIR/results.json, DIR/leaderboard.md and plots: guide-to-dense interpolation methods scored
          against the dense simulation (baselines/bench.py; a suite of datasets/bench/ is generated first).
    ams-torch info

Expected failures (bad input, a bad file, a simulation that diverged, a busy output folder, a
full disk, memory that ran out) print one line ``error: <problem>`` on stderr and exit with
status 2; ``--debug`` (before the command) shows the traceback instead. Outputs are written
whole or not at all (docs/reliability.md).
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from typing import Optional

import numpy as np

from ams_torch.apps.sequence import read_sequence, write_final, write_sequence  # noqa: F401 - re-exported

__all__ = ["main", "write_sequence", "write_final", "read_sequence"]


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

    m = load_mesh(mesh, **{k: head[k] for k in ("scale", "up_axis", "transform") if k in head})
    return m.vertices, m.faces, None


def _render(seq: dict, scene: dict, path: str, view: Optional[str] = None, every: Optional[int] = None,
            progress: bool = False, head=None) -> str:
    """Render positions (F, S, N, 3) m of ``seq`` with the head (vertices, faces, radius) given or
    drawn from ``scene``; colliders outlined from their stored world poses."""
    from ams_torch.apps.render import render_sequence

    r = scene.get("render", {})
    v, f, radius = head if head is not None else _head_for_render(scene)
    fps = r.get("fps", 1.0 / seq["dt"])
    return render_sequence(seq["positions"], path, rotations=seq.get("rotations"),
                           translations=seq.get("translations"), fps=fps, every=every or r.get("every", 1),
                           progress=progress, colliders=scene.get("colliders", []),
                           collider_rotations=seq.get("collider_rotations"),
                           collider_translations=seq.get("collider_translations"), head_vertices=v, head_faces=f,
                           head_radius=radius, view=view or r.get("view", "front"), size=r.get("size", 4.0),
                           title=scene.get("name", ""))


def parse_device(text: Optional[str]):
    """A torch.device from ``--device``: ``cpu``, ``cuda`` or ``cuda:N`` (N < the number of CUDA
    devices); None: cuda when available, else cpu. A clear ValueError otherwise."""
    import torch

    if text is None:
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    t = str(text).strip().lower()
    kind, _, num = t.partition(":")
    if t == "cpu":
        return torch.device("cpu")
    if kind != "cuda" or (num and not num.isdigit()):
        raise ValueError(f"--device {text!r} is not a device this library runs on; use cpu, cuda or cuda:N")
    if torch.version.cuda is None:
        raise ValueError(f"--device {text}: this torch build ({torch.__version__}) has no CUDA support; use "
                         f"--device cpu, or install a CUDA build of torch")
    count = torch.cuda.device_count()
    if count == 0:
        raise ValueError(f"--device {text}: torch was built with CUDA {torch.version.cuda} but no CUDA device is "
                         f"visible (driver missing, or CUDA_VISIBLE_DEVICES hides them); use --device cpu")
    if num and int(num) >= count:
        raise ValueError(f"--device {text}: there {'is' if count == 1 else 'are'} {count} CUDA device(s) "
                         f"(cuda:0{f' .. cuda:{count - 1}' if count > 1 else ''})")
    return torch.device(t)


def _cmd_simulate(args) -> int:
    import torch

    from ams_torch import SimulationDiverged
    from ams_torch.apps.atomic import remove_stale
    from ams_torch.apps.datagen import nonfinite_inputs
    from ams_torch.apps.scene import build, load_scene, simulate
    from ams_torch.apps.scene.limits import check_memory
    from ams_torch.apps.sequence import SequenceWriter, open_sequence

    device = parse_device(args.device)
    overrides = {k: getattr(args, k) for k in ("frames", "scale") if getattr(args, k) is not None}
    scene = load_scene(args.scene, overrides)
    dtype = {"float32": torch.float32, "float64": torch.float64}[args.dtype]
    check_memory(scene, dtype.itemsize, 1, device, _max_memory(args), where=args.scene)  # before allocating
    os.makedirs(args.out, exist_ok=True)
    outputs = {k: os.path.join(args.out, k) for k in ("sequence.h5", "final.npz", "final.png", "video.mp4")}
    for path in outputs.values():
        remove_stale(path)  # temporaries of a run that was killed
    t0 = time.perf_counter()
    run = build(scene, device=device, dtype=dtype)
    s, n = run.sim.model.rest_positions.shape[:2]
    stages = [k for k, on in scene["stages"].items() if on]
    print(f"scene {scene['name']}: {s} strands x {n} particles on {device} ({args.dtype}), "
          f"{scene['frames']} frames of {run.sim.params.dt * 1e3:.2f} ms, stages: {', '.join(stages) or 'none'}; "
          f"built in {time.perf_counter() - t0:.1f} s")
    writer = SequenceWriter(outputs["sequence.h5"], scene, run.sim.params, run.rest, len(scene["colliders"]))
    try:
        result = simulate(run, progress=not args.quiet, record=writer.frame, keep=False)
    except BaseException as err:
        kept = writer.abort(keep=not isinstance(err, OSError))
        if kept:
            print(f"note: the {writer.count} frame(s) simulated before the failure are in {kept}", flush=True)
        if not isinstance(err, (SimulationDiverged, ValueError)):
            raise
        motions = [("[motion]", run.motion)] + [(f"[colliders[{i}].motion]", m) for i, m in enumerate(run.collider_motions)]
        bad = nonfinite_inputs(run.rest, motions, scene["frames"], run.sim.params.dt, [run.wind], run.sim.params)
        if bad:  # a NaN input: diverged, or refused by the step
            at = f" at frame {err.frame}" if isinstance(err, SimulationDiverged) else ""
            raise ValueError(f"{args.scene}: the scene input is not finite: {bad}; the simulation stopped{at}. "
                             f"This is not a stability problem (more substeps will not help): fix the input") from None
        raise
    h5 = writer.finish(result["ms_per_frame"])
    print("ms/frame: " + ", ".join(f"{k} {v:.1f}" for k, v in result["ms_per_frame"].items())
          + f" (after the first frame, which took {result['first_frame_ms']:.0f} ms)")
    print(f"wrote {h5}")
    final = write_final(outputs["final.npz"], result, run.rest)
    print(f"wrote {final}")
    with open_sequence(h5) as seq:
        png = _render(seq, scene, outputs["final.png"])  # a .png path draws the last frame
        print(f"wrote {png}")
        if not args.no_video:
            video = _render(seq, scene, outputs["video.mp4"], progress=not args.quiet)
            print(f"wrote {video}")
    return 0


def _is_dataset(path: str) -> bool:
    from ams_torch.apps.data import FORMAT
    from ams_torch.apps.sequence import open_sequence

    if os.path.isdir(path):
        return True
    if not os.path.isfile(path):
        raise FileNotFoundError(f"no such file to render {path!r}")
    try:
        with open_sequence(path):
            return False
    except ValueError as err:
        problem = err
    import h5py

    try:
        with h5py.File(path, "r") as f:  # not a simulate sequence: perhaps a dataset file
            if f.attrs.get("format") == FORMAT:
                return True
    except (OSError, ValueError):
        pass
    raise problem


def _cmd_render(args) -> int:
    from ams_torch.apps.sequence import open_sequence
    from ams_torch.apps.video import check_picture_path

    if args.out is not None:
        check_picture_path(args.out)
    _positive("--every", args.every)
    if _is_dataset(args.file):
        from ams_torch.apps.data import read_dataset_sequence

        seq = read_dataset_sequence(args.file, args.sequence)
        head = seq["meshes"]["head"]
        drawn = (head.get("vertices"), head.get("faces"), None)
        base = args.file if os.path.isdir(args.file) else os.path.dirname(os.path.abspath(args.file))
        out = args.out or os.path.join(base, f"seq_{seq['index']:06d}.mp4")
        print(f"rendering sequence {seq['index']} of {seq['file']}")
    else:
        if args.sequence is not None:
            raise ValueError(f"--sequence picks a sequence of a dataset; {args.file} is a simulate sequence file "
                             f"(one sequence)")
        out = args.out or os.path.join(os.path.dirname(os.path.abspath(args.file)), "video.mp4")
        with open_sequence(args.file) as seq:
            path = _render(seq, seq["scene"], out, view=args.view, every=args.every, progress=not args.quiet)
        print(f"wrote {path}")
        return 0
    path = _render(seq, seq["scene"], out, view=args.view, every=args.every, progress=not args.quiet, head=drawn)
    print(f"wrote {path}")
    return 0


def _cmd_export(args) -> int:
    from ams_torch.apps.export import export_usd

    if not os.path.isfile(args.sequence):
        raise FileNotFoundError(f"{args.sequence}: no such sequence file")
    path = export_usd(args.sequence, args.usd, every=args.every, width=args.width, progress=not args.quiet)
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
        from ams_torch.native import build as _native

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


def _positive(name: str, v, integer: bool = True):
    if v is not None and not v > 0:
        raise ValueError(f"{name} must be a positive {'integer' if integer else 'number'}; got {v}")
    return v


def _max_memory(args):
    """Bytes of ``--max-memory``, or None (the memory available)."""
    from ams_torch.apps.scene.limits import parse_size

    return None if args.max_memory is None else parse_size(args.max_memory)


def _generate_shards(args, recipe) -> tuple:
    """(shards to generate or None for all, number of shards) from --shard/--shards, validated."""
    from ams_torch.apps.datagen import parse_shard

    if args.shards is not None and args.shards < 1:
        raise ValueError(f"--shards must be an integer >= 1 (the number of shard files); got {args.shards}")
    if args.shard is None:
        return None, args.shards or 1
    if args.backend == "ray":
        raise ValueError("--shard selects one shard for the local backend; with --backend ray use --shards N "
                         "(Ray runs every shard)")
    i, n = parse_shard(args.shard)
    if args.shards is not None and args.shards != n:
        raise ValueError(f"--shard {args.shard} is shard {i} of {n}, but --shards says {args.shards}; give one "
                         f"of them (or the same n in both)")
    return [i], n


def _cmd_generate(args) -> int:
    from ams_torch.apps.datagen import generate, generate_ray
    from ams_torch.apps.recipe import load_recipe
    from ams_torch.apps.recipe.core import check_recipe_memory

    for name in ("sequences", "threads"):
        _positive(f"--{name}", getattr(args, name))
    _positive("--cpus-per-task", args.cpus_per_task, integer=False)
    device = None if args.device is None else str(parse_device(args.device))
    if os.path.isdir(args.recipe):  # a suite: every recipe of the folder, each into OUT/<recipe name>
        from ams_torch.apps.datagen import generate_suite
        from ams_torch.apps.datagen.suite import suite_recipes

        shards, n = _generate_shards(args, None)
        for r in suite_recipes(args.recipe, {"sequences": args.sequences} if args.sequences is not None else None)[0]:
            check_recipe_memory(r, device, _max_memory(args))  # every recipe of the suite, before allocating
        if args.threads:
            import torch

            torch.set_num_threads(args.threads)
        t0 = time.perf_counter()
        done = generate_suite(args.recipe, args.out, shards=shards, num_shards=n, device=device, backend=args.backend,
                              sequences=args.sequences, progress=not args.quiet, log=lambda s: print(s, flush=True),
                              wait=args.wait, ray_address=args.ray_address, cpus_per_task=args.cpus_per_task)
        print(f"wrote {len(done)} dataset(s) under {args.out} in {time.perf_counter() - t0:.1f} s")
        return 0
    recipe = load_recipe(args.recipe, {"sequences": args.sequences} if args.sequences is not None else None)
    shards, n = _generate_shards(args, recipe)
    check_recipe_memory(recipe, device, _max_memory(args))  # the largest batch group, before allocating
    if args.threads:
        import torch

        torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    print(f"recipe {recipe.name}: {recipe.num_sequences} sequences x {recipe.frames} frames in "
          f"{recipe.num_groups} batch group(s) of up to {recipe.batch}; output {args.out}, "
          f"{'shard ' + str(shards[0]) + ' of ' + str(n) + ' (0-based)' if shards else str(n) + ' shard(s)'}")
    log = lambda s: print(s, flush=True)  # noqa: E731 - seen at once when stdout is a file
    if args.backend == "ray":
        paths = generate_ray(recipe, args.out, n, address=args.ray_address, device=device,
                             cpus_per_task=args.cpus_per_task, progress=not args.quiet, log=log, wait=args.wait)
    else:
        paths = generate(recipe, args.out, shards=shards, num_shards=n, device=device, progress=not args.quiet,
                         log=log, wait=args.wait)
    for p in paths:
        print(f"wrote {p}")
    print(f"done in {time.perf_counter() - t0:.1f} s")
    return 0


def _cmd_validate(args) -> int:
    from ams_torch.apps.data import validate

    report = validate(args.path, progress=not args.quiet, allow_partial=args.allow_partial)
    for path, found in report.files.items():
        if found:
            print(f"FAIL {path}")
            for p in found:
                print(f"  - {p}")
        elif not args.quiet:
            print(f"ok   {path}")
    for p in report.problems:
        print(f"problem: {p}")
    for n in report.notes:
        print(f"note: {n}")
    bad = sum(1 for found in report.files.values() if found)
    count = sum(len(f) for f in report.files.values()) + len(report.problems)
    files = f"{len(report.files) - bad} of {len(report.files)} file(s) sound"
    if report.ok:
        what = "partial dataset sound so far" if args.allow_partial and report.notes else "dataset complete and sound"
        print(f"{what}: {files}")
        return 0
    print(f"{count} problem(s) found: {files}")
    return 1


def _cmd_bench_interp(args) -> int:
    from baselines import bench  # the benchmark ships beside ams_torch (package ``baselines``)

    guides = _int_list("--guides", args.guides)
    sizes = [] if args.cost_sizes.strip().lower() in ("", "none", "0") else _int_list("--cost-sizes", args.cost_sizes)
    device = str(parse_device(args.device)) if args.device else "cpu"
    if args.threads:
        import torch

        torch.set_num_threads(args.threads)
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    results = bench.run(args.source, methods, guides, args.out, train=args.train, retrain=args.retrain,
                        device=device, guide_source=args.guide_source,
                        splits=[s for s in args.splits.split(",") if s] if args.splits else None,
                        options=bench.parse_options(args.option or []), cost_sizes=sizes, cost_frames=args.cost_frames,
                        cost_dataset=args.cost_dataset,
                        progress=not args.quiet, command=["ams-torch"] + (args.argv or []))
    scored = sum(1 for r in results["rows"] if not r["method"].startswith("("))
    print(f"wrote {os.path.join(args.out, 'results.json')} ({scored} rows: method x guides x sequence) and "
          f"{os.path.join(args.out, 'leaderboard.md')}")
    return 0


def _int_list(flag: str, text: str) -> list:
    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise ValueError(f"{flag} must be comma-separated integers; got {text!r}") from None
    if not values or any(v < 1 for v in values):
        raise ValueError(f"{flag} must be comma-separated integers >= 1; got {text!r}")
    return values


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="ams-torch", description="Dense hair simulation with the AMS model.")
    ap.add_argument("--debug", action="store_true", help="show the traceback of a failure (default: one line)")
    sub = ap.add_subparsers(dest="command", required=True)
    sp = sub.add_parser("simulate", help="simulate a scene file (TOML)")
    sp.add_argument("scene")
    sp.add_argument("--frames", type=int)
    sp.add_argument("--scale", type=float, help="multiply the groom's strand count")
    sp.add_argument("--device", help="cpu, cuda or cuda:N (default: cuda when available)")
    sp.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    sp.add_argument("--out", default="out")
    sp.add_argument("--no-video", action="store_true")
    sp.add_argument("--max-memory", metavar="SIZE", help="refuse a scene whose estimated memory exceeds SIZE (8G, "
                    "512M, bytes; default: the memory available)")
    sp.add_argument("--quiet", action="store_true", help="no progress bars")
    sp.set_defaults(fn=_cmd_simulate)
    rp = sub.add_parser("render", help="render a sequence.h5, or a sequence of a dataset, to MP4 (or PNG)")
    rp.add_argument("file", help="a sequence.h5 of `simulate`, or a dataset folder/file of `generate`")
    rp.add_argument("--sequence", type=int, help="dataset only: the sequence index to render (default: the first)")
    rp.add_argument("--out", help="video.mp4, or a .png for the last frame")
    rp.add_argument("--view", choices=("front", "side", "back"))
    rp.add_argument("--every", type=int)
    rp.add_argument("--quiet", action="store_true")
    rp.set_defaults(fn=_cmd_render)
    gp = sub.add_parser("generate", help="simulate a dataset recipe (TOML) into sharded HDF5 files")
    gp.add_argument("recipe", help="a recipe (TOML), or a suite folder of recipes (each into OUT/<recipe name>)")
    gp.add_argument("--out", required=True, help="output folder (one HDF5 file per shard; one dataset per folder)")
    gp.add_argument("--shard", metavar="I/N", help="generate only shard I of N, numbered from 0: 0 <= I < N "
                    "(0/4 is the first of 4, 3/4 the last; file <name>-shard-0000I-of-0000N.h5); local backend")
    gp.add_argument("--shards", type=int, metavar="N", help="number of shards (default 1); without --shard, "
                    "generate all N")
    gp.add_argument("--sequences", type=int, help="override the recipe's number of sequences")
    gp.add_argument("--backend", choices=("local", "ray"), default="local",
                    help="local: this process; ray: one Ray task per batch group")
    gp.add_argument("--wait", action="store_true", help="if another generate run holds --out, wait for it to "
                    "finish instead of failing")
    gp.add_argument("--ray-address", help="join this Ray cluster (default: start a private one on 127.0.0.1)")
    gp.add_argument("--cpus-per-task", type=float, default=1.0, help="Ray CPUs per batch-group task")
    gp.add_argument("--device", help="cpu, cuda or cuda:N (default cpu; Ray tasks take a GPU each when there are GPUs)")
    gp.add_argument("--threads", type=int, help="torch CPU threads")
    gp.add_argument("--max-memory", metavar="SIZE", help="refuse a recipe whose largest batch group's estimated memory "
                    "exceeds SIZE (8G, 512M, bytes; default: the memory available)")
    gp.add_argument("--quiet", action="store_true", help="no progress bars")
    gp.set_defaults(fn=_cmd_generate)
    vp = sub.add_parser("validate", help="check a dataset: every file sound and together complete "
                        "(exit 0: complete and sound, 1: problems found, 2: could not run)")
    vp.add_argument("path", help="a dataset folder or file")
    vp.add_argument("--allow-partial", action="store_true", help="a run in progress: missing or unfinished shards "
                    "are notes, not problems")
    vp.add_argument("--quiet", action="store_true")
    vp.set_defaults(fn=_cmd_validate)
    ep = sub.add_parser("export", help="write a simulate sequence.h5 as animated USD (needs usd-core)")
    ep.add_argument("sequence", help="a sequence.h5 written by ams-torch simulate")
    ep.add_argument("--usd", required=True, help="output .usd, .usda or .usdc")
    ep.add_argument("--every", type=int, default=1, help="write every k-th frame")
    ep.add_argument("--width", type=float, help="strand diameter, metres (default 70 µm)")
    ep.add_argument("--quiet", action="store_true", help="no progress bar")
    ep.set_defaults(fn=_cmd_export)
    bp = sub.add_parser("bench-interp", help="score guide-to-dense interpolation methods against dense simulation")
    bp.add_argument("source", help="a dataset (folder or file) of `generate`, or a suite of datasets/bench/ "
                    "(mini, standard, full), generated into OUT/data first")
    bp.add_argument("--methods", required=True, help="comma-separated: built-in names (rigid, nearest, skinning, "
                    "blend, skinning+pushout, upsampler, temporal, collision, agnostic), package.module:factory, or entry "
                    "points of the group ams_torch.interpolators")
    bp.add_argument("--guides", required=True, help="comma-separated guide counts, e.g. 64,256")
    bp.add_argument("--out", required=True, help="output folder (results.json, leaderboard.md, plots, models/)")
    bp.add_argument("--train", action="store_true", help="fit learned methods that have no trained model in OUT/models")
    bp.add_argument("--retrain", action="store_true", help="fit learned methods even when OUT/models has them")
    bp.add_argument("--device", help="cpu, cuda or cuda:N (default cpu)")
    bp.add_argument("--guide-source", choices=("alone", "dense", "both"), default="alone",
                    help="the guide input: simulated alone (default), the dense run's copies, or both")
    bp.add_argument("--splits", help="comma-separated held-out splits to score (default: all but train and valid)")
    bp.add_argument("--option", action="append", metavar="METHOD.KEY=VALUE",
                    help="an option for a method's factory (repeatable), e.g. upsampler.steps=2000")
    bp.add_argument("--cost-sizes", default="10000,100000", help="dense strand counts of the cost measurement "
                    "(comma-separated; 'none' skips it)")
    bp.add_argument("--cost-frames", type=int, default=3, help="frames timed per cost measurement")
    bp.add_argument("--cost-dataset", help="the dataset of a suite whose scene the cost measurement regrows "
                    "(default: the first)")
    bp.add_argument("--threads", type=int, help="torch CPU threads")
    bp.add_argument("--quiet", action="store_true", help="no progress bars")
    bp.set_defaults(fn=_cmd_bench_interp)
    ip = sub.add_parser("info", help="versions, devices, native solver status")
    ip.set_defaults(fn=_cmd_info)
    return ap


def _expected() -> tuple:
    """The exception classes that are the user's problem (bad input, files, divergence), not bugs."""
    from ams_torch import SimulationDiverged

    return (ValueError, OSError, ImportError, SimulationDiverged)


def main(argv=None) -> int:
    """Run the command line; returns the exit status (0 success, 1 problems found by validate,
    2 an expected failure, printed as one ``error:`` line unless ``--debug``, 130 interrupted)."""
    args = _parser().parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)
    try:
        return args.fn(args)
    except KeyboardInterrupt:
        if args.debug:
            raise
        print("error: interrupted", file=sys.stderr)
        return 130
    except _expected() as err:
        if args.debug:
            raise
        print(f"error: {' '.join(str(err).split()) or type(err).__name__}", file=sys.stderr)
        return 2
    except (MemoryError, RuntimeError) as err:  # the allocators' words for running out of memory
        text = " ".join(str(err).split())
        if args.debug or not (isinstance(err, MemoryError) or any(w in text for w in _OUT_OF_MEMORY)):
            raise
        print(f"error: out of memory ({text[:200] or type(err).__name__}); the scene or recipe is larger than this "
              f"machine holds: lower its sizes, or give --max-memory to have them checked first", file=sys.stderr)
        return 2


_OUT_OF_MEMORY = ("out of memory", "can't allocate memory", "std::bad_alloc", "Cannot allocate memory")


if __name__ == "__main__":
    sys.exit(main())
