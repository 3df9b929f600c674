"""Parity of whole runs: the fused native path against the torch definition, float64 (SPEC §15).

    .venv/bin/python scripts/parity_frames.py                    # the demo, 120 frames → docs/benchmarks/parity.{md,json}
    .venv/bin/python scripts/parity_frames.py --strands 100 --frames 20 --out /tmp/parity

The scene (default: ``datasets/scenes/default.toml``, the ``make demo`` scene: head collisions,
hair–hair 64³, its own head motion) is built twice in float64, once per path
(``Simulator(..., backend="native" | "torch")``), and each run is fed its own output frame after
frame, for both materials (the per-length default and the paper's per-particle constants).
Per frame, the largest |x_native − x_torch| (m) and |v_native − v_torch| (m/s) over every
particle. The bound of the issue is 0.1 mm over the 120-frame demo; the parity tests assert much
tighter bounds on smaller cases.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
import tomllib
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import ams_torch as at  # noqa: E402
from ams_torch._bench import machine, shown_args  # noqa: E402
from ams_torch.apps.scene import build  # noqa: E402
from ams_torch.apps.scene.schema import parse_scene  # noqa: E402
from ams_torch.sim.params import PAPER_UNITS  # noqa: E402

#: the scene's [params] changes per material: the library default, and Params.paper()'s constants
MATERIALS = {"per_length": {}, "per_particle": dict(PAPER_UNITS)}


def _scene(path: str, strands, frames, material: str) -> dict:
    with open(path, "rb") as f:
        raw = tomllib.load(f)
    raw.setdefault("name", Path(path).stem)
    if strands:
        raw.setdefault("groom", {})["strands"] = int(strands)
    if frames:
        raw["frames"] = int(frames)
    raw["params"] = dict(raw.get("params", {}), **MATERIALS[material])
    return parse_scene(raw, where=path, base=str(Path(path).resolve().parent))


def compare(path: str, strands=None, frames=None, material: str = "per_length", progress: bool = False) -> dict:
    """Run the scene on both paths (float64). Returns ``{"frames", "S", "N", "max_dx_m",
    "max_dv_mps", "per_frame_dx_m", "per_frame_dv_mps", "seconds": {path: s}}``."""
    spec = _scene(path, strands, frames, material)
    runs, states, seconds = {}, {}, {}
    for backend in ("native", "torch"):
        run = build(spec, dtype=torch.float64)
        old = run.sim
        run.sim = at.Simulator(old.model.rest_positions, old.params, dtype=torch.float64, pose=old.initial_pose,
                               hair_hair=old.hair_hair, colliders=old.colliders or None, backend=backend)
        runs[backend] = run
        states[backend] = run.sim.initial_state()
        seconds[backend] = 0.0
    n_frames = int(spec["frames"])
    dt = runs["native"].sim.params.dt
    dx, dv = [], []
    it = range(n_frames)
    if progress:
        from tqdm.auto import tqdm

        it = tqdm(it, desc=f"parity {spec['name']} ({material})", unit="frame")
    for k in it:
        for backend, run in runs.items():
            pose = run.motion((k + 1) * dt, dtype=torch.float64)
            t0 = time.perf_counter()
            states[backend] = run.sim.step(states[backend], pose)
            seconds[backend] += time.perf_counter() - t0
        a, b = states["native"], states["torch"]
        dx.append(float((a.x - b.x).abs().max()))
        dv.append(float((a.v - b.v).abs().max()))
    model = runs["native"].sim.model
    return {"frames": n_frames, "S": model.num_strands, "N": model.num_particles, "material": material,
            "max_dx_m": max(dx), "max_dv_mps": max(dv), "final_dx_m": dx[-1], "per_frame_dx_m": dx,
            "per_frame_dv_mps": dv, "seconds": seconds}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default=str(ROOT / "datasets" / "scenes" / "default.toml"))
    ap.add_argument("--strands", type=int, default=None, help="override the groom's strand count")
    ap.add_argument("--frames", type=int, default=None, help="override the scene's frame count")
    ap.add_argument("--materials", nargs="+", default=list(MATERIALS), choices=list(MATERIALS))
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", default=str(ROOT / "docs" / "benchmarks" / "parity"))
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    results = [compare(args.scene, args.strands, args.frames, m, progress=True) for m in args.materials]
    wall = time.perf_counter() - t0
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    meta = {"command": ("python scripts/parity_frames.py " + shown_args(argv)).strip(), "machine": machine("cpu"),
            "scene": Path(args.scene).name, "wall_s": wall}
    (out.parent / (out.name + ".json")).write_text(json.dumps({"meta": meta, "results": results}, indent=1))
    lines = ["# Parity of whole runs: native against torch, float64", "",
             f"Machine: {meta['machine']}. Command: `{meta['command']}` ({wall / 60:.1f} min). Scene "
             f"`{meta['scene']}` (head collisions, hair–hair, its own head motion), both paths fed their own "
             "output frame after frame. Raw per-frame values: "
             f"[`{out.name}.json`]({out.name}.json).", "",
             "| material | S × N | frames | max \\|Δx\\| (m) | at the last frame (m) | max \\|Δv\\| (m/s) | "
             "native s | torch s |", "|---|---|---:|---:|---:|---:|---:|---:|"]
    for r in results:
        lines.append(f"| {r['material']} | {r['S']:,} × {r['N']} | {r['frames']} | {r['max_dx_m']:.3g} | "
                     f"{r['final_dx_m']:.3g} | {r['max_dv_mps']:.3g} | {r['seconds']['native']:.1f} | "
                     f"{r['seconds']['torch']:.1f} |")
    lines += ["", "The issue's bound is 0.1 mm (1e-4 m) over the 120-frame demo."]
    (out.parent / (out.name + ".md")).write_text("\n".join(lines) + "\n")
    for r in results:
        print(f"{r['material']}: max |dx| {r['max_dx_m']:.3g} m, max |dv| {r['max_dv_mps']:.3g} m/s over "
              f"{r['frames']} frames")
    print(f"wrote {out}.md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
