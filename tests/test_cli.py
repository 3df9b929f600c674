"""The ams-torch command line end to end on a tiny scene."""
import json
import os

import h5py
import imageio.v3 as iio
import numpy as np

from ams_torch.apps.cli import main, read_sequence

TINY = """
name = "tiny"
frames = 4
[head]
mesh = "sphere"
radius = 0.1
[groom]
kind = "sphere"
strands = 12
particles = 8
length = 0.1
[stages]
collisions = true
[motion]
type = "shake"
[wind]
speed = 2.0
[render]
size = 2.0
"""


def test_simulate_writes_hdf5_and_video(tmp_path, capsys):
    scene = tmp_path / "tiny.toml"
    scene.write_text(TINY)
    out = tmp_path / "out"
    assert main(["simulate", str(scene), "--out", str(out), "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "ms/frame: solve" in printed and "collisions" in printed and "wind" in printed
    h5 = out / "sequence.h5"
    with h5py.File(h5, "r") as f:
        assert f["positions"].shape == (4, 12, 8, 3)
        assert f["rotations"].shape == (4, 3, 3) and f["translations"].shape == (4, 3)
        assert json.loads(f.attrs["scene"])["name"] == "tiny"
        assert json.loads(f.attrs["params"])["num_pinned"] == 2
        assert np.isfinite(f["positions"][()]).all()
    assert not [p for p in os.listdir(out) if ".tmp" in p]  # atomic writes leave no temporaries
    final = np.load(out / "final.npz")
    with h5py.File(h5, "r") as f:
        assert np.array_equal(final["positions"], f["positions"][-1])  # the last frame, as simulated
        assert np.array_equal(final["rest_positions"], f["rest_positions"][()])
    assert final["velocities"].shape == (12, 8, 3) and int(final["frame"]) == 4
    assert iio.imread(out / "final.png").ndim == 3
    frames = iio.imread(out / "video.mp4")
    assert frames.shape[0] == 4 and frames.shape[-1] == 3
    # render again from the file, every other frame, and to a PNG
    assert main(["render", str(h5), "--out", str(tmp_path / "again.mp4"), "--every", "2", "--quiet"]) == 0
    assert iio.imread(tmp_path / "again.mp4").shape[0] == 2
    assert main(["render", str(h5), "--out", str(tmp_path / "last.png"), "--quiet"]) == 0
    assert iio.imread(tmp_path / "last.png").ndim == 3
    seq = read_sequence(str(h5))
    assert seq["positions"].shape == (4, 12, 8, 3) and seq["dt"] > 0


def test_frames_override_and_bad_scene(tmp_path, capsys):
    scene = tmp_path / "tiny.toml"
    scene.write_text(TINY)
    assert main(["simulate", str(scene), "--out", str(tmp_path / "o"), "--frames", "2", "--no-video", "--quiet"]) == 0
    with h5py.File(tmp_path / "o" / "sequence.h5", "r") as f:
        assert f["positions"].shape[0] == 2
    assert not (tmp_path / "o" / "video.mp4").exists()
    bad = tmp_path / "bad.toml"
    bad.write_text(TINY.replace("length = 0.1", "length = -0.1"))
    assert main(["simulate", str(bad), "--out", str(tmp_path / "b"), "--quiet"]) == 2
    assert "[groom].length" in capsys.readouterr().err


def test_info(capsys):
    assert main(["info"]) == 0
    out = capsys.readouterr().out
    assert "torch" in out and "native solver" in out and "cuda" in out
