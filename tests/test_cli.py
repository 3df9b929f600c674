"""The ams-torch command line end to end on a tiny scene."""
import json
import os
import signal
import subprocess
import sys
import time

import h5py
import pytest
import imageio.v3 as iio
import numpy as np
from helpers import sha

from ams_torch.apps.cli import main, read_sequence
from ams_torch.apps.datagen import generate, shard_filename
from ams_torch.apps.recipe import load_recipe

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
    # and out to animated USD: the time samples are the HDF5 frames
    pytest.importorskip("pxr")
    from pxr import Usd, UsdGeom

    usd = tmp_path / "hair.usda"
    assert main(["export", str(h5), "--usd", str(usd), "--quiet"]) == 0
    stage = Usd.Stage.Open(str(usd))
    curves = [UsdGeom.BasisCurves(p) for p in stage.Traverse() if p.IsA(UsdGeom.BasisCurves)]
    assert len(curves) == 1
    points = curves[0].GetPointsAttr()
    samples = points.GetTimeSamples()
    assert len(samples) == 4
    np.testing.assert_array_equal(np.asarray(points.Get(samples[-1])), seq["positions"][-1].reshape(-1, 3))
    assert main(["export", str(tmp_path / "missing.h5"), "--usd", str(usd)]) == 2


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


# -- expected failures: one line, exit status 2 (item 5) ------------------------------------------
def _one_error_line(capsys, argv) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in err, err
    return lines[0]


def test_bad_devices_fail_up_front(tmp_path, capsys):
    import torch

    scene = tmp_path / "tiny.toml"
    scene.write_text(TINY)
    run = ["simulate", str(scene), "--out", str(tmp_path / "o"), "--quiet", "--no-video", "--device"]
    assert _one_error_line(capsys, run + ["tpu"]) == \
        "error: --device 'tpu' is not a device this library runs on; use cpu, cuda or cuda:N"
    assert "is not a device" in _one_error_line(capsys, run + ["cuda:x"])
    if torch.version.cuda is None:
        msg = _one_error_line(capsys, run + ["cuda"])
        assert msg == f"error: --device cuda: this torch build ({torch.__version__}) has no CUDA support; use " \
                      f"--device cpu, or install a CUDA build of torch"
    elif torch.cuda.device_count() == 0:
        assert "no CUDA device is visible" in _one_error_line(capsys, run + ["cuda"])
    else:
        n = torch.cuda.device_count()
        assert f"there {'is' if n == 1 else 'are'} {n} CUDA device(s)" in _one_error_line(capsys, run + [f"cuda:{n}"])
    assert not (tmp_path / "o").exists()  # refused before anything was built or written
    gen = ["generate", str(scene), "--out", str(tmp_path / "g"), "--device", "tpu"]
    assert "is not a device" in _one_error_line(capsys, gen)


def test_divergence_says_whether_the_input_was_finite(tmp_path, capsys):
    nan_amp = tmp_path / "nan.toml"
    nan_amp.write_text(TINY.replace('type = "shake"', 'type = "shake"\namplitude = nan'))
    out = ["--out", str(tmp_path / "o"), "--quiet", "--no-video"]
    assert _one_error_line(capsys, ["simulate", str(nan_amp)] + out) == \
        f"error: {nan_amp}: [motion].amplitude must be a finite number; got nan"
    poses = tmp_path / "poses.npz"
    np.savez(poses, translations=np.array([[0.0, 0.0, 0.0], [np.nan, 0.0, 0.0], [0.0, 0.0, 0.0]]),
             rotvecs=np.zeros((3, 3)), dt=0.02)
    recorded = tmp_path / "recorded.toml"
    recorded.write_text(TINY.replace('type = "shake"', f'type = "recorded"\npath = "{poses.name}"'))
    msg = _one_error_line(capsys, ["simulate", str(recorded)] + out)  # refused when read, or when simulated
    assert msg.startswith(f"error: {recorded}: ") and "[motion]" in msg and "finite" in msg
    stiff = tmp_path / "fast.toml"  # finite input that the divergence guard stops: the source's advice stands
    stiff.write_text(TINY + "[params]\nmax_relative_speed = 1e-6\n")
    msg = _one_error_line(capsys, ["simulate", str(stiff)] + out)
    assert "diverged at frame 1" in msg and "not finite" not in msg
    from ams_torch import SimulationDiverged

    with pytest.raises(SimulationDiverged):  # --debug: the exception itself, with its traceback
        main(["--debug", "simulate", str(stiff)] + out)


def test_generate_flags_are_validated(tmp_path, capsys):
    recipe = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "datasets", "tiny.toml")
    out = str(tmp_path / "d")
    gen = ["generate", recipe, "--out", out, "--quiet"]
    cases = [
        (["--shards", "-2"], "error: --shards must be an integer >= 1 (the number of shard files); got -2"),
        (["--shards", "0"], "error: --shards must be an integer >= 1 (the number of shard files); got 0"),
        (["--shard", "1/4", "--shards", "2"], "error: --shard 1/4 is shard 1 of 4, but --shards says 2; give one of "
                                              "them (or the same n in both)"),
        (["--shard", "3/3"], "error: --shard 3/3: shards are numbered from 0, so i must be in 0..2 (e.g. 2/3 is the "
                             "last of 3)"),
        (["--shard", "one/3"], "error: --shard must look like i/n with 0 <= i < n (e.g. 0/4 is the first of 4 shards); "
                               "got 'one/3'"),
        (["--shard", "0/4"], "error: 4 shards for 3 batch group(s): a shard would be empty; use at most 3 shards (or "
                             "more sequences / a smaller batch)"),
        (["--shard", "0/2", "--backend", "ray"], "error: --shard selects one shard for the local backend; with "
                                                  "--backend ray use --shards N (Ray runs every shard)"),
        (["--sequences", "0"], "error: --sequences must be a positive integer; got 0"),
    ]
    for extra, expected in cases:
        assert _one_error_line(capsys, gen + extra) == expected
    assert not os.path.exists(out) or not [n for n in os.listdir(out) if n != ".lock"]
    with pytest.raises(SystemExit) as done:
        main(["generate", "--help"])
    assert done.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "generate only shard I of N, numbered from 0: 0 <= I < N (0/4 is the first of 4, 3/4 the last" in text


def test_render_a_dataset_sequence_and_corrupt_files(tmp_path, capsys):
    from ams_torch.apps.datagen import generate
    from ams_torch.apps.recipe import parse_recipe

    r = parse_recipe({"name": "mini", "sequences": 2, "frames": 3, "head": {"mesh": "sphere"},
                      "groom": {"kind": "sphere", "strands": 10, "particles": 6}, "motion": {"type": "nod"},
                      "split": {"train": 1.0}})
    path = generate(r, str(tmp_path / "ds"), progress=False, log=lambda s: None)[0]
    assert main(["render", str(tmp_path / "ds"), "--sequence", "1", "--out", str(tmp_path / "s1.png"), "--quiet"]) == 0
    assert "rendering sequence 1 of" in capsys.readouterr().out
    assert iio.imread(tmp_path / "s1.png").ndim == 3
    assert main(["render", path, "--every", "2", "--quiet"]) == 0  # a shard file; default out beside it
    assert iio.imread(tmp_path / "ds" / "seq_000000.mp4").shape[0] == 2
    assert "no sequences found" in _one_error_line(capsys, ["render", path, "--sequence", "7", "--quiet"])
    data = open(path, "rb").read()
    bad = tmp_path / "truncated.h5"
    bad.write_bytes(data[: len(data) // 3])
    assert _one_error_line(capsys, ["render", str(bad), "--quiet"]).startswith(
        f"error: {bad}: cannot be opened as HDF5 (truncated or corrupt file)")
    scene = tmp_path / "tiny.toml"
    scene.write_text(TINY)
    assert main(["simulate", str(scene), "--out", str(tmp_path / "o"), "--quiet", "--no-video"]) == 0
    seq = open(tmp_path / "o" / "sequence.h5", "rb").read()
    (tmp_path / "cut.h5").write_bytes(seq[: len(seq) // 2])
    assert "cannot be opened as HDF5" in _one_error_line(capsys, ["render", str(tmp_path / "cut.h5"), "--quiet"])
    assert _one_error_line(capsys, ["render", str(tmp_path / "nothing.h5")]) == \
        f"error: no such file to render {str(tmp_path / 'nothing.h5')!r}"
    assert "--sequence picks a sequence of a dataset" in _one_error_line(
        capsys, ["render", str(tmp_path / "o" / "sequence.h5"), "--sequence", "0"])


def test_nonfinite_inputs_are_named():
    """What the CLI and generate say when a run stops and its input was never finite."""
    import torch

    from ams_torch.apps.datagen import nonfinite_inputs
    from ams_torch.apps.datagen.simulate import _diverged
    from ams_torch.apps.motion import Motion, Shake
    from ams_torch import SimulationDiverged

    class Late(Motion):  # NaN from t = 0.03 s on
        def state(self, t):
            z = np.zeros(3)
            return z, z + (np.nan if t > 0.03 else 0.0), z, z

    rest = torch.zeros(2, 4, 3)
    assert nonfinite_inputs(rest, [("[motion]", Shake())], 5, 0.02) is None
    bad = nonfinite_inputs(rest, [("[motion]", Shake()), ("[colliders[0].motion]", Late())], 5, 0.02)
    assert bad.startswith("[colliders[0].motion]: the pose at t = 0.04 s (frame 2) holds NaN/Inf")
    rest[1, 2, 0] = float("inf")
    assert nonfinite_inputs(rest, [], 5, 0.02) == "the groom's rest positions hold NaN/Inf (strand 1)"
    err = _diverged(SimulationDiverged("simulation diverged at frame 2", frame=2, strands=[[0]]), "r.toml: group 0", bad)
    assert str(err).startswith("r.toml: group 0: the scene input is not finite: [colliders[0].motion]") and err.frame == 2
    assert err.bad_input
    assert "at frame 2. This is not a stability problem (more substeps will not help)" in str(err)


# -- generate on the command line: the tiny recipe, two runs on one folder, a killed run --------
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SMALL = """
name = "small"
sequences = 8
frames = 12
batch = 2
[head]
mesh = "sphere"
[groom]
kind = "sphere"
strands = 24
particles = 8
length = { uniform = [0.08, 0.14] }
[stages]
collisions = true
[motion]
type = { choice = ["shake", "nod"] }
[store]
guides = 4
"""


def _kill_tree(proc):
    if proc.poll() is None:
        proc.kill()
        proc.wait()


def test_two_runs_lock_and_a_killed_run_resumes_bit_for_bit(tmp_path):
    """Items 11 and the crash safety: a second generate on the same folder is refused (naming the
    first's pid), a third waits (--wait); the first is killed (SIGKILL: its lock dies with it),
    the third resumes and writes the same bytes as an uninterrupted run."""
    recipe = tmp_path / "small.toml"
    recipe.write_text(SMALL)
    recipe = str(recipe)
    r = load_recipe(recipe)
    out = tmp_path / "killed"
    work = out / ".partial" / os.path.splitext(shard_filename(r, 0, 1))[0]
    cmd = [sys.executable, "-m", "ams_torch.apps.cli", "generate", recipe, "--out", str(out), "--quiet"]
    first = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    waiting = refused = None
    try:
        clean = generate(r, str(tmp_path / "clean"), progress=False, log=lambda s: None)[0]  # while the first run starts
        deadline = time.time() + 120
        while time.time() < deadline and first.poll() is None:
            if work.is_dir() and any(n.startswith("group-") and n.endswith(".h5") for n in os.listdir(work)):
                break
            time.sleep(0.01)
        first.send_signal(signal.SIGSTOP)  # hold it (and its lock) while the others start
        assert first.poll() is None, "the generator finished before it could be stopped"
        log = open(tmp_path / "waiting.log", "w")
        refused = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        waiting = subprocess.Popen(cmd + ["--wait"], stdout=log, stderr=subprocess.STDOUT)
        stdout, stderr = refused.communicate(timeout=120)
        assert refused.returncode == 2, stdout + stderr
        err = stderr.strip().splitlines()
        assert len(err) == 1 and err[0].startswith(f"error: {out} is locked by another generate run (pid {first.pid} ")
        deadline = time.time() + 120
        while time.time() < deadline and "waiting for" not in (tmp_path / "waiting.log").read_text():
            time.sleep(0.05)
        assert f"another generate run holds it (pid {first.pid}" in (tmp_path / "waiting.log").read_text()
        first.send_signal(signal.SIGKILL)
        first.wait()
        assert waiting.wait(timeout=300) == 0, (tmp_path / "waiting.log").read_text()
    finally:
        for p in (first, refused, waiting):
            if p is not None:
                _kill_tree(p)
    printed = (tmp_path / "waiting.log").read_text()
    assert "batch groups already done" in printed  # finished groups were not simulated again
    assert sha(out / shard_filename(r, 0, 1)) == sha(clean)
    assert not (out / ".partial").exists() and not [n for n in os.listdir(out) if ".tmp" in n]


def test_cli_generate_tiny_recipe_and_validate(tmp_path, capsys):
    from ams_torch.apps.data import HairSequenceDataset

    out = str(tmp_path / "tiny")
    t0 = time.perf_counter()
    assert main(["generate", os.path.join(ROOT, "datasets", "tiny.toml"), "--out", out, "--quiet"]) == 0
    print(f"\n[datasets] tiny.toml generated in {time.perf_counter() - t0:.1f} s")
    assert main(["validate", out]) == 0
    assert "dataset complete and sound: 1 of 1 file(s) sound" in capsys.readouterr().out
    ds = HairSequenceDataset(out, window=10, stride=10)
    item = ds[0]
    assert item["positions"].shape == (10, 128, 12, 3) and item["guide_positions"].shape == (10, 16, 12, 3)
    assert ds.sequence_arrays(0)["root_triangles"].shape == (128,)  # root binding of the grown groom
    assert {s[2] for s in HairSequenceDataset(out, split="test").sequences}  # tiny.toml keeps a test group
