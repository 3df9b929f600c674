"""Dataset recipes, sharded resumable generation, validation, the torch Dataset, the Ray backend."""
import hashlib
import os
import shutil
import time

import h5py
import numpy as np
import pytest
import torch
from helpers import sha

from ams_torch.apps.cli import main
from ams_torch.apps.data import DatasetError, HairSequenceDataset, read_scene_meshes, validate, validate_file
from ams_torch.apps.datagen import OutputError, generate, shard_filename, simulate_group
from ams_torch.apps.recipe import RecipeError, load_recipe

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
QUIET = dict(progress=False, log=lambda s: None)

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
[[colliders]]
type = "capsule"
a = [0.0, -0.3, 0.15]
b = [0.0, -0.1, 0.15]
radius = 0.02
[colliders.motion]
type = "keyframes"
times = [0.0, 0.1]
translations = [[0.0, 0.0, 0.0], [0.0, 0.0, -0.02]]
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
[split]
train = 0.34
valid = 0.33
test = 0.33
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
                for k in (k for k in f if k.startswith("seq_")):
                    out[int(f[k].attrs["index"])] = (f[k]["positions"][()], f[k].attrs["checksum"])
    return out


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    """SMALL generated once as one shard and as three shards: (recipe, one-shard dir, three-shard dir)."""
    tmp = tmp_path_factory.mktemp("small")
    r = load_recipe(write(tmp, SMALL))
    return r, generate(r, str(tmp / "one"), **QUIET)[0], generate(r, str(tmp / "three"), num_shards=3, **QUIET)


def test_recipe_errors_name_the_key(tmp_path):
    cases = [
        ("sequences = 5", "sequences = 0", "sequences must be an integer >= 1"),
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
        ("test = 0.33\n", "test = 0.43\n", "[split] shares must sum to 1; got train 0.34 + valid 0.33 + test 0.43"),
        ("test = 0.33\n", "test = -0.33\n", "[split].test must be a finite number >= 0"),
        ("test = 0.33\n", "tset = 0.33\n", "unknown key(s) ['tset'] in [split]"),
        ('type = { choice = ["shake", "nod", "random"] }', 'type = { choice = ["shake", { uniform = [0, 1] }] }',
         "[motion].type: choice option 2 holds a sampler"),
    ]
    for old, new, match in cases:
        assert old in SMALL
        with pytest.raises(RecipeError) as err:
            load_recipe(write(tmp_path, SMALL.replace(old, new, 1)))
        assert match in str(err.value), (new, str(err.value))
        assert "small.toml" in str(err.value)
    with pytest.raises(RecipeError, match="no such recipe file"):
        load_recipe(str(tmp_path / "missing.toml"))


def test_every_sampler_value_is_validated_when_read(tmp_path):
    """Item 9: a typo in the last choice option, a range end out of bounds, a float range for an
    integer, a bad value in one motion type's table: all fail at parse time, naming key and value."""
    tiny = open(os.path.join(ROOT, "datasets", "tiny.toml")).read()
    cases = [
        ('preset = { choice = ["straight", "wavy", "bob"] }', 'preset = { choice = ["straight", "wavy", "bobb"] }',
         "[groom].preset = 'bobb' (choice option 3 of 3): ", "[groom].preset must be one of"),
        ("drag = { uniform = [1.0, 2.5] }", "drag = { uniform = [-1.0, 2.5] }",
         "[params].drag = -1.0 (uniform low end): ", "[params].drag must be non-negative"),
        ("strands = 128", "strands = { uniform = [100, 200] }",
         "[groom].strands = 100.0 (uniform low end): ", "[groom].strands must be an integer >= 1"),
        ("amplitude = { uniform = [0.2, 0.5] }", 'amplitude = { choice = [0.2, "big"] }',
         "[motion.nod].amplitude = 'big' (choice option 2 of 2, motion nod): ", "must be a finite number"),
        ("turbulence = { uniform = [0.0, 1.0] }", "turbulence = { uniform = [-1.0, 1.0] }",
         "[wind].turbulence = -1.0 (uniform low end): ", "[wind].turbulence must be a finite number >= 0"),
        ('type = { choice = ["shake", "nod", "random"] }', 'type = { choice = ["shake", "nodd", "random"] }',
         "[motion].type = 'nodd' (choice option 2 of 3): must be one of", ""),
        ("length_jitter = { uniform = [0.0, 0.3] }", "length_jitter = { uniform = [0.0, 0.3] }\nstep = { uniform = [-1.0, 0.1] }",
         "[groom].growth.step = -1.0 (uniform low end): ", "growth step"),
    ]
    for old, new, label, problem in cases:
        assert old in tiny, old
        with pytest.raises(RecipeError) as err:
            load_recipe(write(tmp_path, tiny.replace(old, new, 1), "tiny.toml"))
        assert label in str(err.value) and problem in str(err.value), str(err.value)
    r = load_recipe(os.path.join(ROOT, "datasets", "tiny.toml"))  # the shipped recipe is valid as a whole
    assert r.num_groups == 3


def test_draws_depend_on_recipe_and_index_only(tmp_path):
    r = load_recipe(write(tmp_path, SMALL))
    more = load_recipe(write(tmp_path, SMALL.replace("sequences = 5", "sequences = 9"), "more.toml"))
    renamed = load_recipe(write(tmp_path, SMALL.replace('name = "small"', 'name = "other"'), "other.toml"))
    assert r.hash == more.hash == renamed.hash  # size, name and storage do not change the draws
    assert len({r.digest, more.digest, renamed.digest}) == 3  # ... but they are different datasets
    for i in range(5):
        assert r.sequence_spec(i) == more.sequence_spec(i) == renamed.sequence_spec(i)
    assert r.group_spec(1) == more.group_spec(1)
    assert len({r.sequence_spec(i)["seed"] for i in range(5)}) == 5  # every sequence has its own stream
    assert len({str(r.sequence_spec(i)["motion"]) for i in range(5)}) >= 3
    changed = load_recipe(write(tmp_path, SMALL.replace("frames = 6", "frames = 7"), "changed.toml"))
    assert changed.hash != r.hash and changed.sequence_spec(0) != r.sequence_spec(0)
    assert r.num_groups == 3 and r.group_sequences(2) == [4]
    assert [r.shard_groups(i, 2) for i in range(2)] == [[0, 2], [1]]
    # splits: whole batch groups, counts from the ratios (largest remainder), from the seed only
    assert sorted(r.group_splits()) == ["test", "train", "valid"]
    assert [r.sequence_split(i) for i in range(5)] == [r.group_splits()[i // 2] for i in range(5)]
    assert load_recipe(write(tmp_path, SMALL, "again.toml")).group_splits() == r.group_splits()
    big = load_recipe(write(tmp_path, SMALL.replace("sequences = 5", "sequences = 200")
                            .replace("train = 0.34\nvalid = 0.33\ntest = 0.33", "train = 0.8\nvalid = 0.1\ntest = 0.1"),
                            "big.toml"))
    counts = {k: big.group_splits().count(k) for k in ("train", "valid", "test")}
    assert counts == {"train": 80, "valid": 10, "test": 10}
    assert big.group_splits()[:10] != ["train"] * 10  # a permutation, not a prefix


def test_same_shard_is_byte_identical_and_shardings_agree(small, tmp_path):
    r, one, three = small
    again = generate(r, str(tmp_path / "again"), **QUIET)[0]
    assert sha(one) == sha(again)  # same recipe, same shard: the same bytes
    assert [os.path.basename(p) for p in three] == [shard_filename(r, i, 3) for i in range(3)]
    a, b = positions_by_index(os.path.dirname(one)), positions_by_index(os.path.dirname(three[0]))
    assert sorted(a) == sorted(b) == list(range(5))
    for i in a:
        assert np.array_equal(a[i][0], b[i][0]) and a[i][1] == b[i][1]
    report = validate(os.path.dirname(three[0]))
    assert report.ok and not any(report.files.values()) and not report.problems


def test_layout_is_self_describing(small):
    r, path, _ = small
    with h5py.File(path, "r") as f:
        a = f.attrs
        assert a["format"] == "ams_torch.dataset" and a["format_version"] == 3 and list(a["sequences"]) == [0, 1, 2, 3, 4]
        assert a["recipe_digest"] == r.digest and a["num_shards"] == 1
        g = f["seq_000003"]
        assert g["positions"].shape == (6, 24, 8, 3) and g["positions"].chunks == (1, 24, 8, 3)
        assert g["positions"].compression == "gzip" and g["positions"].shuffle and g["positions"].fletcher32
        assert g["velocities"].shape == (6, 24, 8, 3) and g["guide_positions"].shape == (6, 4, 8, 3)
        gi = g["guide_indices"][()]
        assert np.array_equal(g["guide_positions"][()], g["positions"][()][:, gi])
        assert g["rotations"].shape == (6, 3, 3) and g["angular_velocities"].shape == (6, 3)
        assert np.allclose(np.linalg.det(g["rotations"][()]), 1.0, atol=1e-5)
        assert int(g.attrs["group"]) == 1 and "motion" in g.attrs and "checksum" in g.attrs
        # units and dimension labels on every array; per-frame digests of the large arrays
        assert (g["positions"].attrs["units"], g["positions"].attrs["dims"]) == ("m", "frame,strand,particle,xyz")
        assert (g["velocities"].attrs["units"], g["angular_velocities"].attrs["units"]) == ("m/s", "rad/s")
        assert g["guide_positions"].attrs["dims"] == "frame,guide,particle,xyz"
        assert all("units" in g[k].attrs and "dims" in g[k].attrs and "sha256" in g[k].attrs
                   for k in g if k != "frame_sha256")
        digests = g["frame_sha256/positions"][()]
        assert digests.shape == (6, 32) and digests[2].tobytes() == hashlib.sha256(g["positions"][2].tobytes()).digest()
        # moving collider: its world pose per frame (the keyframed translation)
        assert g["collider_translations"].shape == (6, 1, 3)
        assert np.allclose(g["collider_translations"][-1, 0], [0.0, 0.0, -0.02], atol=1e-6)
        # the split masks: one split per sequence, whole batch groups, as the recipe says
        masks = np.stack([f[f"mask/{k}"][()] for k in ("train", "valid", "test")])
        assert masks.dtype == bool and (masks.sum(0) == 1).all()
        names = np.array(["train", "valid", "test"])[masks.argmax(0)].tolist()
        assert names == [r.sequence_split(i) for i in range(5)] == [f[f"seq_{i:06d}"].attrs["split"] for i in range(5)]
        # the two sequences of a group share the groom and differ in motion
        assert np.array_equal(f["seq_000002"]["rest_positions"][()], g["rest_positions"][()])
        assert not np.array_equal(f["seq_000002"]["positions"][()], g["positions"][()])
        assert not np.array_equal(f["seq_000000"]["rest_positions"][()], g["rest_positions"][()])
    meshes = read_scene_meshes(path)
    head, cap = meshes["head"], meshes["colliders"][0]
    assert head["type"] == "sphere" and head["radius"] == pytest.approx(0.1)
    assert np.allclose(np.linalg.norm(head["vertices"], axis=1), 0.1, atol=1e-6) and head["faces"].shape[1] == 3
    assert cap["type"] == "capsule" and np.allclose(cap["a"], [0.0, -0.3, 0.15]) and cap["radius"] == 0.02
    v = cap["vertices"].astype(np.float64)
    seg = np.array([0.0, 0.2, 0.0])
    t = np.clip((v - cap["a"]) @ seg / seg.dot(seg), 0, 1)
    assert np.allclose(np.linalg.norm(v - (cap["a"] + t[:, None] * seg), axis=1), 0.02, atol=1e-6)


def test_float16_and_lzf_storage(tmp_path, small):
    _, path, _ = small
    half = load_recipe(write(tmp_path, SMALL.replace("velocities = true", "precision = \"float16\"\ncompression = \"lzf\""),
                             "half.toml"))
    path16 = generate(half, str(tmp_path / "h"), **QUIET)[0]
    assert validate_file(path16) == []
    with h5py.File(path16, "r") as f16, h5py.File(path, "r") as f32:
        p16, p32 = f16["seq_000001"]["positions"], f32["seq_000001"]["positions"][()]
        assert p16.dtype == np.float16 and p16.compression == "lzf" and "velocities" not in f16["seq_000001"]
        err = np.abs(p16[()].astype(np.float32) - p32).max()
        assert 0 < err < 2.5e-4  # float16 in metres: about 0.1 mm at 0.25 m
        print(f"\n[datasets] float16 storage error: {err * 1e3:.3f} mm max")
    ds = HairSequenceDataset(str(tmp_path / "h"), window=6)  # float16 digests verify as stored
    assert ds[0]["positions"].dtype == torch.float32


def test_grown_groom_roots_index_the_stored_head_mesh(tmp_path):
    text = open(os.path.join(ROOT, "datasets", "tiny.toml")).read().replace("sequences = 6", "sequences = 1") \
        .replace("frames = 30", "frames = 2").replace("strands = 128", "strands = 40").replace("subdivisions = 3",
                                                                                            "subdivisions = 2")
    path = generate(load_recipe(write(tmp_path, text, "tiny.toml")), str(tmp_path / "t"), **QUIET)[0]
    head = read_scene_meshes(path)["head"]
    assert head["type"] == "mesh" and head["source"] == "default"
    with h5py.File(path, "r") as f:
        g = f["seq_000000"]
        tri, bary, rest = g["root_triangles"][()], g["root_barycentrics"][()], g["rest_positions"][()]
    corners = head["vertices"][head["faces"][tri]]  # (S, 3, 3)
    roots = np.einsum("sc,scx->sx", bary, corners)
    assert np.abs(roots - rest[:, 0]).max() < 1e-5


def test_dataset_windows_match_the_simulation_splits_and_workers(small):
    r, _, three = small
    out = os.path.dirname(three[0])
    xs = []
    res = simulate_group(r, 1, on_frame=lambda k, s: xs.append(s.x.detach().float().numpy()))
    sim_x = np.stack(xs, 1)  # (B, F, S, N, 3)
    ds = HairSequenceDataset(out, window=3, stride=2)
    assert len(ds) == 5 * 2  # 5 sequences x windows starting at 0, 2 of 6 frames
    seen = 0
    for item in ds:
        if item["sequence"] in (2, 3):
            b, s = item["sequence"] - 2, item["start"]
            assert item["positions"].shape == (3, 24, 8, 3) and item["positions"].dtype == torch.float32
            assert np.array_equal(item["positions"].numpy(), sim_x[b, s:s + 3])
            seen += 1
    assert seen == 4 and [sp["index"] for sp in res["specs"]] == [2, 3]
    arrays = ds.sequence_arrays(3)
    assert arrays["rest_positions"].shape == (24, 8, 3) and arrays["motion"]["type"] in ("shake", "nod", "keyframes")
    assert arrays["split"] == r.sequence_split(3)
    loader = lambda w: list(torch.utils.data.DataLoader(ds, batch_size=3, num_workers=w))  # noqa: E731
    serial, parallel = loader(0), loader(2)
    assert len(serial) == len(parallel) == 4
    for a, b in zip(serial, parallel):
        assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    for split in ("train", "valid", "test"):
        part = HairSequenceDataset(out, window=6, split=split)
        assert sorted({s[2] for s in part.sequences}) == [i for i in range(5) if r.sequence_split(i) == split]
    both = HairSequenceDataset(out, window=6, split=["train", "test"])
    assert len(both) == sum(r.sequence_split(i) != "valid" for i in range(5))
    sub = HairSequenceDataset(out, window=6, sequences=[4], fields=["velocities"], static_fields=["rest_positions"])
    assert len(sub) == 1 and set(sub[0]) == {"velocities", "rest_positions", "sequence", "start"}
    with pytest.raises(ValueError, match="longer than every sequence"):
        HairSequenceDataset(out, window=7)
    with pytest.raises(ValueError, match="not stored"):
        HairSequenceDataset(out, fields=["nonsense"])
    with pytest.raises(ValueError, match=r"split must be one of \['train', 'valid', 'test'\]; got 'training'"):
        HairSequenceDataset(out, split="training")
    with pytest.raises(ValueError, match="verify must be one of"):
        HairSequenceDataset(out, verify="sometimes")


def test_mixed_shardings_and_recipes_are_refused(small, tmp_path):
    """Item 6: one-shard and three-shard outputs in one folder (the README followed literally, or
    files copied together) are refused by generate, reported by validate, refused by the Dataset."""
    r, one, three = small
    out = tmp_path / "mixed"
    shutil.copytree(os.path.dirname(one), out)
    with pytest.raises(OutputError) as err:
        generate(r, str(out), shards=[1], num_shards=3, **QUIET)
    msg = str(err.value)
    assert "already holds a 1-shard dataset (small-shard-00000-of-00001.h5)" in msg and "--shards 1" in msg
    assert not (out / shard_filename(r, 1, 3)).exists() and not (out / ".partial").exists()
    for p in three:  # copied in by hand: 1 + 3 files, 10 sequences, 5 unique
        shutil.copy(p, out)
    report = validate(str(out))
    assert not report.ok and not any(report.files.values())  # each file is sound, the dataset is not
    assert any("different shardings" in p for p in report.problems)
    dup = [p for p in report.problems if "appear in more than one file" in p]
    assert dup and "5 sequence(s)" in dup[0] and "small-shard-00000-of-00001.h5" in dup[0]
    with pytest.raises(DatasetError, match="not one dataset") as err:
        HairSequenceDataset(str(out), window=2)
    assert "small-shard-00000-of-00001.h5" in str(err.value)
    other = load_recipe(write(tmp_path, SMALL.replace("drag = { uniform = [1.0, 2.0] }", "drag = 1.5"), "other.toml"))
    with pytest.raises(OutputError, match="another recipe"):
        generate(other, os.path.dirname(one), **QUIET)
    files = [one, generate(other, str(tmp_path / "other"), **QUIET)[0]]
    with pytest.raises(DatasetError, match="2 different recipes"):
        HairSequenceDataset(files, window=2)
    with pytest.raises(ValueError, match=r"4 shards for 3 batch group\(s\): a shard would be empty"):
        generate(r, str(tmp_path / "four"), num_shards=4, **QUIET)


def test_validate_is_complete_and_sound_or_says_why(small, tmp_path):
    """Item 7: 1 of 3 shards, an unfinished shard, an empty folder are problems (notes with
    allow_partial); exit 0 complete and sound, 1 problems, 2 could not run."""
    r, _, three = small
    part = tmp_path / "part"
    part.mkdir()
    shutil.copy(three[1], part)
    report = validate(str(part))
    assert not report.ok and any("1 of 3 shards present (missing shard(s) [0, 2]" in p for p in report.problems)
    partial = validate(str(part), allow_partial=True)
    assert partial.ok and any("1 of 3 shards present" in n for n in partial.notes)
    assert main(["validate", str(part), "--quiet"]) == 1 and main(["validate", str(part), "--allow-partial", "--quiet"]) == 0
    work = part / ".partial" / os.path.splitext(shard_filename(r, 0, 3))[0]  # shard 0 cut short after one group
    work.mkdir(parents=True)
    (work / "group-000000.h5").write_bytes(b"")
    (work / "shard.json").write_text('{"groups": [0, 3]}')
    report = validate(str(part))
    assert any("unfinished (1 of 2 batch groups done" in p for p in report.problems)
    assert validate(str(part), allow_partial=True).ok
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["validate", str(empty)]) == 1
    assert main(["validate", str(tmp_path / "nowhere")]) == 2
    with h5py.File(empty / "other.h5", "w") as f:
        f["x"] = np.zeros(3)
    assert main(["validate", str(empty)]) == 2
    with pytest.raises(DatasetError, match="not an ams_torch dataset"):
        validate(str(empty))
    assert main(["validate", os.path.dirname(three[0]), "--quiet"]) == 0


def flip_byte(path, dataset, chunk=2, offset_in_chunk=200):
    with h5py.File(path, "r") as f:
        info = f[dataset].id.get_chunk_info(chunk)
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
    path = generate(r, str(tmp_path / "d"), **QUIET)[0]
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
    assert any("NaN" in p for p in problems) and any("frame 3: checksum mismatch" in p for p in problems)
    with h5py.File(path, "r+") as f:  # a sequence gone
        del f["seq_000000"]
    assert any("missing sequence" in p for p in validate_file(path))
    with h5py.File(path, "r+") as f:  # a version-1 file: refused with what to do
        f.attrs["format_version"] = 1
    expected = f"{path}: format_version 1 is not read by this library (it reads versions 2, 3); regenerate it with " \
               f"`ams-torch generate` (its recipe is in the file's 'recipe' attribute)"
    assert validate_file(path) == [expected]
    with pytest.raises(DatasetError) as err:
        HairSequenceDataset(path)
    assert str(err.value) == expected


def test_dataset_verifies_checksums(small, tmp_path):
    """Item 8: an overwritten float is caught on its first read (or on every read with
    "always"), silently returned with "never"; flipped bytes give a DatasetError naming the file,
    the sequence and the array, not a bare OSError."""
    _, one, _ = small
    path = str(tmp_path / os.path.basename(one))
    shutil.copy(one, path)
    with h5py.File(path, "r+") as f:  # h5py rewrites the chunk with a valid Fletcher-32: only SHA-256 sees it
        f["seq_000002/positions"][4, 0, 0, 0] += 1e-3
    items = {v: HairSequenceDataset(path, window=2, stride=2, verify=v) for v in ("first_read", "always", "never")}
    for v, ds in items.items():
        assert ds[0]["sequence"] == 0  # untouched sequences read fine
    bad = [i for i, (q, s) in enumerate(items["never"].items) if items["never"].sequences[q][2] == 2 and s == 4][0]
    with pytest.raises(DatasetError) as err:
        items["first_read"][bad]
    assert str(err.value).startswith(f"{path}: seq_000002/positions frame 4: checksum mismatch")
    with pytest.raises(DatasetError):
        items["always"][bad]
    with pytest.raises(DatasetError):
        items["always"][bad]  # every time
    assert items["never"][bad]["positions"].shape == (2, 24, 8, 3)
    shutil.copy(one, path)
    flip_byte(path, "seq_000001/positions", chunk=2)
    ds = HairSequenceDataset(path, window=1, verify="never")
    k = [i for i, (q, s) in enumerate(ds.items) if ds.sequences[q][2] == 1 and s == 2][0]
    with pytest.raises(DatasetError) as err:
        ds[k]
    assert isinstance(err.value, ValueError) and f"{path}: seq_000001/positions frames 2-2: unreadable (corrupt data" \
        in str(err.value)
    # the cost of verification: a worker hashes each frame it reads once
    clean = HairSequenceDataset(os.path.dirname(one), window=3)
    t = {}
    for v in ("never", "first_read"):
        d = HairSequenceDataset(os.path.dirname(one), window=3, verify=v)
        t0 = time.perf_counter()
        for _ in range(3):
            for i in range(len(d)):
                d[i]
        t[v] = (time.perf_counter() - t0) / (3 * len(d)) * 1e3
    print(f"\n[datasets] window read: {t['never']:.3f} ms unverified, {t['first_read']:.3f} ms first_read "
          f"(3 passes over {len(clean)} windows)")


class FakeRay:
    """Just enough of Ray to run generate_ray's driver in this process: tasks run when waited on."""

    def __init__(self):
        self.initialized, self.calls = False, []
        self.util = type("util", (), {"get_node_ip_address": staticmethod(lambda: "127.0.0.1")})

    def is_initialized(self):
        return self.initialized

    def init(self, **kwargs):
        self.initialized = True
        self.calls.append(("init", kwargs.get("_node_ip_address")))

    def shutdown(self):
        self.initialized = False
        self.calls.append(("shutdown",))

    def cluster_resources(self):
        return {"CPU": 2.0}

    def remote(self, **options):
        return lambda fn: type("task", (), {"remote": staticmethod(lambda *a: ("ref", fn, a))})

    def wait(self, pending, num_returns=1):
        ref = pending[0]
        return [("done", ref[1](*ref[2]))], pending[1:]

    def get(self, ref):
        return ref[1]

    def cancel(self, ref, force=False):
        self.calls.append(("cancel", ref[2][2], force))


def test_ray_driver_interrupted_cancels_shuts_down_and_resumes(small, tmp_path, monkeypatch):
    """Item 12 (the driver's logic, with a stand-in for Ray): progress counts batch groups; a
    KeyboardInterrupt cancels the pending tasks and shuts the cluster it started down; the rerun
    says what it resumes and writes what the local backend writes."""
    from ams_torch.apps.datagen import generate_ray, ray_backend

    r, _, local = small
    fake = FakeRay()
    monkeypatch.setattr(ray_backend, "_import_ray", lambda: fake)
    out, seen = str(tmp_path / "ray"), []

    def interrupt(done, total):
        seen.append((done, total))
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        generate_ray(r, out, num_shards=3, progress=False, log=lambda s: None, on_group=interrupt)
    assert seen == [(1, 3)] and not fake.initialized
    assert fake.calls == [("init", "127.0.0.1"), ("cancel", 1, True), ("cancel", 2, True), ("shutdown",)]
    assert not [n for n in os.listdir(out) if n.endswith(".h5")]  # no shard file from a cut-short run
    logs, counts = [], []
    remote = generate_ray(r, out, num_shards=3, progress=False, log=logs.append, on_group=lambda d, t: counts.append((d, t)))
    assert logs[0] == "resuming: 1 of 3 batch groups already done" and counts == [(2, 3), (3, 3)]
    assert [sha(p) for p in remote] == [sha(p) for p in local]


def test_ray_backend_matches_local_on_loopback(small, tmp_path):
    ray = pytest.importorskip("ray")
    from ams_torch.apps.datagen import generate_ray, start_local_ray

    r, _, local = small
    counts = []

    def check(done, total):
        counts.append((done, total))
        assert ray.util.get_node_ip_address() == "127.0.0.1"
        assert all(n["NodeManagerAddress"] == "127.0.0.1" for n in ray.nodes())
        assert ray.get_runtime_context().gcs_address.startswith("127.0.0.1:")

    start_local_ray(num_cpus=2)
    try:
        remote = generate_ray(r, str(tmp_path / "ray"), num_shards=3, progress=False, log=lambda s: None, on_group=check)
    finally:
        ray.shutdown()
    assert counts == [(1, 3), (2, 3), (3, 3)]
    assert [os.path.basename(p) for p in remote] == [os.path.basename(p) for p in local]
    for a, b in zip(local, remote):
        assert sha(a) == sha(b)
