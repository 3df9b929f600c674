"""Measure the per-unit memory costs behind the estimate of ams_torch.apps.scene.limits (peak
resident memory, not time): bytes per simulated particle (torch and native paths, float32, head
collisions and a 32³ hair–hair grid on), bytes per SDF sample while it is built, bytes per
hair–hair grid cell while it is built. Each measurement runs in a fresh child process (peak RSS
is per process) at two sizes; the cost is the difference over the difference in size.

    python scripts/memory_costs.py            # the sizes of docs/reliability.md
    python scripts/memory_costs.py --small    # a quick run (toy sizes)
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

CHILD = r"""
import json, resource, sys, torch
torch.set_num_threads(1)
kind, size, backend = sys.argv[1], int(sys.argv[2]), sys.argv[3]
peak = lambda: resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
if kind == "particles":
    from ams_torch.apps.scene import build, parse_scene, simulate
    scene = parse_scene({"frames": 3, "head": {"mesh": "default", "subdivisions": 2, "sdf_resolution": 32},
                         "groom": {"preset": "straight", "strands": size, "particles": 32},
                         "stages": {"hair_hair": True, "collisions": True}, "hair_hair": {"resolution": 32}})
    base = peak()
    run = build(scene)
    if backend == "torch":
        run.sim.config = run.sim.config.__class__(**{**run.sim.config.__dict__, "backend": "torch"})
    simulate(run, keep=False)
    units = size * 32
elif kind == "sdf":
    from ams_torch.geometry.sdf import SDFGrid
    from ams_torch.grooms.head import default_head
    mesh = default_head(3)
    base = peak()
    units = SDFGrid.from_mesh(mesh, resolution=size, cache=False).values.numel()
else:
    from ams_torch.stages.hair_hair import HairHair, build_hair_hair
    rest = torch.zeros(100, 8, 3)
    rest[:, :, 1] = -torch.linspace(0, 0.2, 8)
    base = peak()
    build_hair_hair(HairHair(resolution=size), rest, torch.full((100, 8), 1e-6))
    units = size ** 3
print(json.dumps({"bytes": peak() - base, "units": units}))
"""


def measure(kind: str, size: int, backend: str = "native") -> dict:
    env = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
    out = subprocess.run([sys.executable, "-c", CHILD, kind, str(size), backend], capture_output=True, text=True,
                         env=env, check=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def cost(kind: str, sizes, backend: str = "native") -> float:
    a, b = (measure(kind, s, backend) for s in sizes)
    return (b["bytes"] - a["bytes"]) / (b["units"] - a["units"])


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--small", action="store_true", help="toy sizes (a quick check that it runs)")
    args = ap.parse_args(argv)
    sizes = {"particles": (200, 800), "sdf": (32, 48), "grid": (16, 32)} if args.small else \
        {"particles": (2000, 8000), "sdf": (96, 192), "grid": (64, 160)}
    rows = [("particle (torch path)", cost("particles", sizes["particles"], "torch")),
            ("particle (native path)", cost("particles", sizes["particles"], "native")),
            ("SDF sample while built", cost("sdf", sizes["sdf"])),
            ("hair-hair grid cell while built", cost("grid", sizes["grid"]))]
    print(f"sizes {sizes}")
    for name, b in rows:
        print(f"{name:34s} {b:8.0f} B")


if __name__ == "__main__":
    main()
