"""Regenerate docs/scenes/<scene>.png: four frames of each shipped scene side by side.

    .venv/bin/python docs/scenes/make_strips.py [--scale 0.3] [scene names...]

Grooms are scaled down (``--scale``, default 0.3 of the scene's strand count) to keep this a
few minutes on a 2-core CPU; the frames shown are spread over the whole run.
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

from ams_torch.apps.cli import _head_for_render
from ams_torch.apps.render import render_strip
from ams_torch.apps.scene import SCENE_DIR, build, load_scene, simulate

HERE = os.path.dirname(os.path.abspath(__file__))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("names", nargs="*")
    ap.add_argument("--scale", type=float, default=0.3)
    args = ap.parse_args(argv)
    names = args.names or sorted(os.path.splitext(p)[0] for p in os.listdir(SCENE_DIR) if p.endswith(".toml"))
    for name in names:
        scene = load_scene(os.path.join(SCENE_DIR, f"{name}.toml"))
        if scene["groom"].get("strands", 1000) > 50:
            scene["scale"] = args.scale
        t0 = time.perf_counter()
        run = build(scene)
        res = simulate(run)
        f = res["positions"].shape[0]
        picks = sorted({0, f // 3, (2 * f) // 3, f - 1})
        dt = run.sim.params.dt
        v, faces, radius = _head_for_render(scene)
        r = scene.get("render", {})
        path = os.path.join(HERE, f"{name}.png")
        render_strip(res["positions"], path, picks, res["rotations"], res["translations"],
                     labels=[f"{name} t = {(k + 1) * dt:.2f} s" for k in picks], colliders=scene["colliders"],
                     collider_rotations=res.get("collider_rotations"),
                     collider_translations=res.get("collider_translations"), head_vertices=v, head_faces=faces,
                     head_radius=radius, view=r.get("view", "front"), size=3.0, dpi=90)
        ms = ", ".join(f"{k} {x:.1f}" for k, x in res["ms_per_frame"].items())
        print(f"{name}: {res['positions'].shape[1]} strands, {f} frames in {time.perf_counter() - t0:.1f} s "
              f"(ms/frame: {ms}) → {path} ({os.path.getsize(path) // 1024} KB)", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
