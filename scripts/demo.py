"""`make demo`: simulate the default scene (datasets/scenes/default.toml) through the CLI.

1,000 straight strands × 32 particles grown on the default head, shaking, colliding with the
head; writes OUT/sequence.h5 and OUT/video.mp4 and prints ms/frame per stage. Same as
``ams-torch simulate datasets/scenes/default.toml --out OUT``.
"""
from __future__ import annotations

import argparse
import os
import sys

from ams_torch.apps.cli import main as cli_main

SCENE = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "datasets", "scenes", "default.toml")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", default="out")
    ap.add_argument("--frames", type=int, help="override the scene's frame count")
    ap.add_argument("--scale", type=float, help="multiply the strand count (1.0 = 1,000 strands)")
    ap.add_argument("--device", help="cpu or cuda (default: cuda when available)")
    args = ap.parse_args(argv)
    cmd = ["simulate", SCENE, "--out", args.out]
    for flag in ("frames", "scale", "device"):
        if getattr(args, flag) is not None:
            cmd += [f"--{flag}", str(getattr(args, flag))]
    return cli_main(cmd)


if __name__ == "__main__":
    sys.exit(main())
