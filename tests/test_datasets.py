"""Dataset recipes, sharded resumable generation, validation, the torch Dataset, the Ray backend."""
import hashlib
import os
import signal
import subprocess
import sys
import time

import h5py
import numpy as np
import pytest
import torch

from ams_torch.apps.cli import main
from ams_torch.apps.data import HairSequenceDataset, validate, validate_file
from ams_torch.apps.datagen import generate, shard_filename, simulate_group
from ams_torch.apps.recipe import RecipeError, load_recipe

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

SMALL = """
name = "small"
sequences = 5
frames = 6
batch = 2
[head]
mesh = "sphere"
radius = 0.1
[groom]
kind = "sphere"
strands = 24
particles = 8
length = { uniform = [0.08, 0.14] }
[params]
drag = { uniform = [1.0, 2.0] }
[stages]
collisions = true
[motion]
type = { choice = ["shake", "nod", "random"] }
[motion.shake]
amplitude = { uniform = [0.3, 0.9] }
[motion.random]
keys = 2
[wind]
probability = 0.5
speed = { uniform = [0.5, 2.0] }
[store]
guides = 4
velocities = true
"""


def write(tmp_path, text, name="small.toml"):
    p = tmp_path / name
    p.write_text(text)
    return str(p)


def positions_by_index(folder):
    out = {}
    for name in sorted(os.listdir(folder)):
        if name.endswith(".h5"):
            with h5py.File(os.path.join(folder, name), "r") as f:
                for k in f:
                    out[int(f[k].attrs["index"])] = (f[k]["positions"][()], f[k].attrs["checksum"])
    return out


def sha(path):
    return hashlib.sha256(open(path, "rb").read()).hexdigest()


def test_recipe_errors_name_the_key(tmp_path):
    cases = [
        ("sequences = 5", "sequences = 0", "sequences must be an integer"),
        ("[store]\n", "[store]\nbogus = 1\n", "unknown key(s) ['bogus'] in [store]"),
        ("guides = 4", "guides = 400", "[store].guides = 400 exceeds"),
        ("velocities = true", "velocities = true\nprecision = \"int8\"", "[store].precision"),
        ("drag = { uniform = [1.0, 2.0] }", "drag = { uniform = [2.0, 1.0] }", "[params].drag: uniform needs low <= high"),
        ("drag = { uniform = [1.0, 2.0] }", "stretch_stiffness = { uniform = [-2.0, -1.0] }",
         "[params].stretch_stiffness must be non-negative"),
        ("drag = { uniform = [1.0, 2.0] }", "drag = { gaussian = [1.0, 2.0] }", "[params].drag"),
        ("[head]", "[head]\nsdf_resolution = { randint = [8, 16] }", "head is fixed for a whole dataset"),
        ("keys = 2", "keys = 2\nspeed = 3", "unknown argument(s) ['speed']"),
        ('name = "small"', 'name = "small"\nframez = 3', "unknown key(s) ['framez']"),
    ]
    for old, new, match in cases:
        assert old in SMALL
        with pytest.raises(RecipeError) as err:
            load_recipe(write(tmp_path, SMALL.replace(old, new, 1)))
        assert match in str(err.value), (new, str(err.value))
        assert "small.toml" in str(err.value)
    with pytest.raises(RecipeError, match="no such recipe file"):
        load_recipe(str(tmp_path / "missing.toml"))


def test_draws_depend_on_recipe_and_index_only(tmp_path):
    r = load_recipe(write(tmp_path, SMALL))
    more = load_recipe(write(tmp_path, SMALL.replace("sequences = 5", "sequences = 9"), "more.toml"))
    renamed = load_recipe(write(tmp_path, SMALL.replace('name = "small"', 'name = "other"'), "other.toml"))
    assert r.hash == more.hash == renamed.hash  # size, name and storage do not change the draws
    for i in range(5):
        assert r.sequence_spec(i) == more.sequence_spec(i) == renamed.sequence_spec(i)
    assert r.group_spec(1) == more.group_spec(1)
    assert len({r.sequence_spec(i)["seed"] for i in range(5)}) == 5  # every sequence has its own stream
    assert len({str(r.sequence_spec(i)["motion"]) for i in range(5)}) >= 3
    changed = load_recipe(write(tmp_path, SMALL.replace("frames = 6", "frames = 7"), "changed.toml"))
    assert changed.hash != r.hash and changed.sequence_spec(0) != r.sequence_spec(0)
    assert r.num_groups == 3 and r.group_sequences(2) == [4]
    assert [r.shard_groups(i, 2) for i in range(2)] == [[0, 2], [1]]


def test_same_shard_is_byte_identical_and_shardings_agree(tmp_path):
    r = load_recipe(write(tmp_path, SMALL))
    a = generate(r, str(tmp_path / "a"), progress=False, log=lambda s: None)
    b = generate(r, str(tmp_path / "b"), progress=False, log=lambda s: None)
    assert sha(a[0]) == sha(b[0])  # same recipe, same shard: the same bytes
    two = generate(r, str(tmp_path / "two"), num_shards=2, progress=False, log=lambda s: None)
    assert [os.path.basename(p) for p in two] == [shard_filename(r, 0, 2), shard_filename(r, 1, 2)]
    one, split = positions_by_index(tmp_path / "a"), positions_by_index(tmp_path / "two")
    assert sorted(one) == sorted(split) == list(range(5))
    for i in one:
        assert np.array_equal(one[i][0], split[i][0]) and one[i][1] == split[i][1]
    problems, notes = validate(str(tmp_path / "two"))
    assert not any(problems.values()) and not [n for n in notes if n.startswith("error")]
    # one shard of four on its own: sound, and the missing shards are noted, not failed
    generate(r, str(tmp_path / "part"), shards=[1], num_shards=4, progress=False, log=lambda s: None)
    problems, notes = validate(str(tmp_path / "part"))
    assert not any(problems.values()) and any("1 of 4 shards present" in n for n in notes)


def test_layout_contents(tmp_path):
    r = load_recipe(write(tmp_path, SMALL))
    path = generate(r, str(tmp_path / "d"), progress=False, log=lambda s: None)[0]
    with h5py.File(path, "r") as f:
        assert f.attrs["format"] == "ams_torch.dataset" and list(f.attrs["sequences"]) == [0, 1, 2, 3, 4]
        g = f["seq_000003"]
        assert g["positions"].shape == (6, 24, 8, 3) and g["positions"].chunks == (1, 24, 8, 3)
        assert g["positions"].compression == "gzip" and g["positions"].shuffle and g["positions"].fletcher32
        assert g["velocities"].shape == (6, 24, 8, 3) and g["guide_positions"].shape == (6, 4, 8, 3)
        gi = g["guide_indices"][()]
        assert np.array_equal(g["guide_positions"][()], g["positions"][()][:, gi])
        assert g["rotations"].shape == (6, 3, 3) and g["angular_velocities"].shape == (6, 3)
        assert np.allclose(np.linalg.det(g["rotations"][()]), 1.0, atol=1e-5)
        assert int(g.attrs["group"]) == 1 and "motion" in g.attrs and "checksum" in g.attrs
        # the two sequences of a group share the groom and differ in motion
        assert np.array_equal(f["seq_000002"]["rest_positions"][()], g["rest_positions"][()])
        assert not np.array_equal(f["seq_000002"]["positions"][()], g["positions"][()])
        assert not np.array_equal(f["seq_000000"]["rest_positions"][()], g["rest_positions"][()])
    half = load_recipe(write(tmp_path, SMALL.replace("velocities = true", "precision = \"float16\"\ncompression = \"lzf\""),
                             "half.toml"))
    path16 = generate(half, str(tmp_path / "h"), progress=False, log=lambda s: None)[0]
    assert validate_file(path16) == []
    with h5py.File(path16, "r") as f16, h5py.File(path, "r") as f32:
        p16, p32 = f16["seq_000001"]["positions"], f32["seq_000001"]["positions"][()]
        assert p16.dtype == np.float16 and p16.compression == "lzf" and "velocities" not in f16["seq_000001"]
        err = np.abs(p16[()].astype(np.float32) - p32).max()
        assert 0 < err < 2.5e-4  # float16 in metres: about 0.1 mm at 0.25 m
        print(f"\n[datasets] float16 storage error: {err * 1e3:.3f} mm max")


def test_dataset_windows_match_the_simulation_and_workers(tmp_path):
    r = load_recipe(write(tmp_path, SMALL))
    out = str(tmp_path / "d")
    generate(r, out, num_shards=2, progress=False, log=lambda s: None)
    xs = []
    res = simulate_group(r, 1, on_frame=lambda k, s: xs.append(s.x.detach().float().numpy()))
    sim_x = np.stack(xs, 1)  # (B, F, S, N, 3)
    ds = HairSequenceDataset(out, window=3, stride=2)
    assert len(ds) == 5 * 2  # 5 sequences x windows starting at 0, 2 of 6 frames
    seen = 0
    for item in ds:
        if item["sequence"] in (2, 3):
            b = item["sequence"] - 2
            s = item["start"]
            assert item["positions"].shape == (3, 24, 8, 3) and item["positions"].dtype == torch.float32
            assert np.array_equal(item["positions"].numpy(), sim_x[b, s:s + 3])
            seen += 1
    assert seen == 4 and [sp["index"] for sp in res["specs"]] == [2, 3]
    arrays = ds.sequence_arrays(3)
    assert arrays["rest_positions"].shape == (24, 8, 3) and arrays["motion"]["type"] in ("shake", "nod", "keyframes")
    loader = lambda w: list(torch.utils.data.DataLoader(ds, batch_size=3, num_workers=w))  # noqa: E731
    serial, parallel = loader(0), loader(2)
    assert len(serial) == len(parallel) == 4
    for a, b in zip(serial, parallel):
        assert a.keys() == b.keys()
        for k in a:
            assert torch.equal(a[k], b[k]), k
    sub = HairSequenceDataset(out, window=6, sequences=[4], fields=["velocities"], static_fields=["rest_positions"])
    assert len(sub) == 1 and set(sub[0]) == {"velocities", "rest_positions", "sequence", "start"}
    with pytest.raises(ValueError, match="longer than every sequence"):
        HairSequenceDataset(out, window=7)
    with pytest.raises(ValueError, match="not stored"):
        HairSequenceDataset(out, fields=["nonsense"])


def flip_byte(path, dataset, offset_in_chunk=200):
    with h5py.File(path, "r") as f:
        d = f[dataset]
        info = d.id.get_chunk_info(2)
        where = info.byte_offset + min(offset_in_chunk, info.size - 1)
    with open(path, "r+b") as fh:
        fh.seek(where)
        b = fh.read(1)
        fh.seek(where)
        fh.write(bytes([b[0] ^ 0x5A]))


@pytest.mark.parametrize("compression", ["gzip", "none"])
def test_validate_reports_corruption(tmp_path, compression, capsys):
    text = SMALL.replace("velocities = true", f'compression = "{compression}"')
    r = load_recipe(write(tmp_path, text))
    path = generate(r, str(tmp_path / "d"), progress=False, log=lambda s: None)[0]
    assert main(["validate", str(tmp_path / "d"), "--quiet"]) == 0
    good = open(path, "rb").read()
    flip_byte(path, "seq_000001/positions")
    problems = validate_file(path)
    assert problems and all("seq_000001/positions" in p for p in problems), problems
    assert main(["validate", str(tmp_path / "d"), "--quiet"]) == 1
    assert "FAIL" in capsys.readouterr().out
    with open(path, "wb") as fh:  # truncated
        fh.write(good[: len(good) // 2])
    assert "cannot be opened as HDF5" in validate_file(path)[0]
    with open(path, "wb") as fh:
        fh.write(good)
    with h5py.File(path, "r+") as f:  # a NaN written in place after generation
        f["seq_000004/positions"][3, 0, 0, 0] = np.nan
    problems = validate_file(path)
    assert any("NaN" in p for p in problems) and any("checksum mismatch" in p for p in problems)
    with h5py.File(path, "r+") as f:  # a sequence gone
        del f["seq_000000"]
    assert any("missing sequence" in p for p in validate_file(path))


def test_killed_generator_resumes_to_identical_files(tmp_path):
    text = SMALL.replace("sequences = 5", "sequences = 8").replace("frames = 6", "frames = 40") \
        .replace("strands = 24", "strands = 160").replace("particles = 8", "particles = 16")
    recipe = write(tmp_path, text)
    r = load_recipe(recipe)
    clean = generate(r, str(tmp_path / "clean"), progress=False, log=lambda s: None)[0]
    out = tmp_path / "killed"
    work = out / ".partial" / os.path.splitext(shard_filename(r, 0, 1))[0]
    cmd = [sys.executable, "-m", "ams_torch.apps.cli", "generate", recipe, "--out", str(out), "--quiet"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    deadline = time.time() + 120
    while time.time() < deadline and proc.poll() is None:
        if work.is_dir() and any(n.endswith(".h5") for n in os.listdir(work)):
            break
        time.sleep(0.01)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert proc.returncode == -signal.SIGKILL, "the generator finished before it could be killed"
    assert not (out / shard_filename(r, 0, 1)).exists()
    res = subprocess.run(cmd, capture_output=True, text=True)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "already done" in res.stdout  # finished groups were not simulated again
    final = out / shard_filename(r, 0, 1)
    assert sha(final) == sha(clean)
    assert not (out / ".partial").exists() and not [n for n in os.listdir(out) if ".tmp" in n]


def test_cli_generate_tiny_recipe_and_validate(tmp_path, capsys):
    out = str(tmp_path / "tiny")
    t0 = time.perf_counter()
    assert main(["generate", os.path.join(ROOT, "datasets", "tiny.toml"), "--out", out, "--quiet"]) == 0
    seconds = time.perf_counter() - t0
    print(f"\n[datasets] tiny.toml generated in {seconds:.1f} s")
    assert main(["validate", out]) == 0
    assert "1 of 1 file(s) sound" in capsys.readouterr().out
    ds = HairSequenceDataset(out, window=10, stride=10)
    item = ds[0]
    assert item["positions"].shape == (10, 128, 12, 3) and item["guide_positions"].shape == (10, 16, 12, 3)
    arrays = ds.sequence_arrays(0)
    assert arrays["root_triangles"].shape == (128,)  # root binding of the grown groom
    assert main(["generate", os.path.join(ROOT, "datasets", "tiny.toml"), "--out", out, "--shard", "3/2"]) == 2


def test_ray_backend_matches_local(tmp_path):
    ray = pytest.importorskip("ray")
    r = load_recipe(write(tmp_path, SMALL))
    local = generate(r, str(tmp_path / "local"), num_shards=2, progress=False, log=lambda s: None)
    from ams_torch.apps.datagen import generate_ray, start_local_ray

    start_local_ray(num_cpus=2)
    try:
        assert ray.util.get_node_ip_address() == "127.0.0.1"
        assert all(n["NodeManagerAddress"] == "127.0.0.1" for n in ray.nodes())
        assert ray.get_runtime_context().gcs_address.startswith("127.0.0.1:")
        remote = generate_ray(r, str(tmp_path / "ray"), num_shards=2, progress=False, log=lambda s: None)
    finally:
        ray.shutdown()
    assert [os.path.basename(p) for p in remote] == [os.path.basename(p) for p in local]
    for a, b in zip(local, remote):
        assert sha(a) == sha(b)
