"""The benchmark's data: guides simulated alone, motion velocities, benchmark samples from
HairSequenceDataset, split hold-outs, colliders drawn per batch group, single-groom recipes and
the suites of datasets/bench."""
import json
import os

import h5py
import numpy as np
import pytest
import torch

from ams_torch.apps.data import HairSequenceDataset, list_datasets, read_scene_meshes, validate, validate_file
from ams_torch.apps.datagen import generate, generate_suite, suite_recipes
from ams_torch.apps.recipe import MissingRequirement, RecipeError, load_recipe
from ams_torch.sim.model import pinned_counts
from ams_torch.sim.params import Params

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
QUIET = dict(progress=False, log=lambda s: None)

BASE = """
name = "guides"
sequences = 4
frames = 5
batch = 2
[head]
mesh = "sphere"
radius = 0.1
[groom]
kind = "sphere"
strands = 40
particles = 6
length = 0.12
[stages]
collisions = true
[motion]
type = { cycle = ["shake", "nod"] }
[store]
guides = [3, 8]
motion_velocities = true
velocities = true
[split]
train = 0.5
valid = 0.0
test = 0.5
"""


def write(tmp_path, text, name="r.toml"):
    p = tmp_path / name
    p.write_text(text)
    return str(p)


def make(tmp_path, text, name="r.toml", **kw):
    r = load_recipe(write(tmp_path, text, name))
    out = str(tmp_path / (name[:-5] + "_out"))
    return r, generate(r, out, **QUIET, **kw), out


@pytest.fixture(scope="module")
def plain(tmp_path_factory):
    """BASE generated once (no hair-hair): (recipe, shard paths, folder)."""
    return make(tmp_path_factory.mktemp("plain"), BASE)


# -- guides simulated alone -------------------------------------------------------------------
def test_guides_alone_are_stored_validated_and_match_the_dense_run_without_hair_hair(plain, tmp_path):
    r, (path,), out = plain
    assert r.guide_counts == [3, 8] == r.alone_counts
    with h5py.File(path, "r") as f:
        assert f.attrs["format_version"] == 3 and json.loads(f.attrs["store"])["guides"] == [3, 8]
        g = f["seq_000001"]
        gi, dense = g["guide_indices"][()], g["guide_positions"][()]
        assert gi.shape == (8,) and dense.shape == (5, 8, 6, 3)
        a3, a8 = g["guides_alone_3"], g["guides_alone_8"]
        assert a3.shape == (5, 3, 6, 3) and a8.shape == (5, 8, 6, 3) and a8.chunks == (1, 8, 6, 3)
        assert (a8.attrs["units"], a8.attrs["dims"]) == ("m", "frame,guide,particle,xyz")
        assert g["frame_sha256/guides_alone_3"].shape == (5, 32) and list(g.attrs["guides_alone"]) == [3, 8]
        # without hair-hair the strands do not interact: alone = the dense run's copies, to rounding
        assert np.abs(a8[()] - dense).max() < 1e-6 and np.abs(a3[()] - dense[:, :3]).max() < 1e-6
        assert np.abs(dense[-1] - dense[0]).max() > 1e-3  # and they did move
        assert np.array_equal(g["num_pinned"][()], pinned_counts(Params(**{
            k: tuple(v) if k == "gravity" else v for k, v in json.loads(g.attrs["params"]).items()}),
            torch.from_numpy(g["rest_positions"][()])).numpy())
    assert validate(out).ok
    # the per-frame digests and the sequence checksum cover them
    bad = str(tmp_path / "bad.h5")
    with open(path, "rb") as src, open(bad, "wb") as dst:
        dst.write(src.read())
    with h5py.File(bad, "r+") as f:
        f["seq_000001/guides_alone_3"][2, 1, 1, 0] += 1e-3
    assert any("seq_000001/guides_alone_3: frame 2: checksum mismatch" in p for p in validate_file(bad))
    with h5py.File(bad, "r+") as f:
        del f["seq_000002/guides_alone_8"]
    assert any("seq_000002: missing dataset(s) ['guides_alone_8']" in p for p in validate_file(bad))


def test_guides_alone_differ_from_the_dense_copies_with_hair_hair(tmp_path):
    text = BASE.replace("collisions = true", "collisions = true\nhair_hair = true\n[hair_hair]\nresolution = 8") \
        .replace("strands = 40", "strands = 60").replace("sequences = 4", "sequences = 2") \
        .replace("frames = 5", "frames = 8")
    _, (path,), _ = make(tmp_path, text)
    with h5py.File(path, "r") as f:
        g = f["seq_000000"]
        gap = np.abs(g["guides_alone_8"][()] - g["guide_positions"][()]).max()
    assert gap > 1e-5, gap  # the dense groom's hair-hair pushes its guides; alone they feel only each other
    print(f"\n[bench data] guides alone vs dense copies with hair-hair: {gap * 1e3:.3f} mm max")


def test_guides_alone_can_be_switched_off_and_a_single_count_still_works(tmp_path):
    r, (path,), _ = make(tmp_path, BASE.replace("guides = [3, 8]", "guides = 8\nguides_alone = false"))
    assert r.guide_counts == [8] and r.alone_counts == []
    with h5py.File(path, "r") as f:
        assert not any(k.startswith("guides_alone_") for k in f["seq_000000"])
    with pytest.raises(ValueError, match=r"guides=8 was not simulated alone in this dataset \(guide counts simulated "
                                         r"alone: none\)"):
        HairSequenceDataset(path, guides=8)
    for bad, match in (("guides = [3, 3]", "lists a guide count twice"), ("guides = [0, 4]", r"guides\[0\] must be"),
                       ("guides = [3, 80]", "exceeds the groom's 40 strands")):
        with pytest.raises(RecipeError, match=match):
            load_recipe(write(tmp_path, BASE.replace("guides = [3, 8]", bad), "bad.toml"))


# -- motion velocities --------------------------------------------------------------------------
def test_motion_velocities_of_a_rigidly_moving_groom_are_its_velocity(tmp_path):
    """No gravity, no drag, a translation at constant velocity u (keyframes whose Catmull-Rom
    tangents equal the slope on [0, 1] s): the groom moves rigidly, and the stored motion velocity
    (x_k − x_{k−1}) / dt is u at every particle, to float32 rounding."""
    u = np.array([0.3, -0.1, 0.05])
    keys = [(t * u).tolist() for t in (-1.0, 0.0, 1.0, 2.0)]
    text = BASE.replace('type = { cycle = ["shake", "nod"] }',
                        f'type = "keyframes"\ntimes = [-1.0, 0.0, 1.0, 2.0]\ntranslations = {keys}') \
        .replace("[stages]", "[params]\ngravity = [0.0, 0.0, 0.0]\ndrag = 0.0\n[stages]")
    _, (path,), _ = make(tmp_path, text)
    with h5py.File(path, "r") as f:
        g = f["seq_000000"]
        mv, v, x = g["motion_velocities"][()], g["velocities"][()], g["positions"][()].astype(np.float64)
        rest, trans = g["rest_positions"][()].astype(np.float64), g["translations"][()]
        assert (g["motion_velocities"].attrs["units"], g["motion_velocities"].attrs["dims"]) == \
            ("m/s", "frame,strand,particle,xyz")
    assert np.abs(trans - np.arange(1, 6)[:, None] / 60.0 * u).max() < 1e-6  # the head moved at u
    assert np.abs(x - rest[None] - trans[:, None, None].astype(np.float64)).max() < 1e-6  # rigidly
    assert np.abs(mv - u).max() < 1e-4, np.abs(mv - u).max()  # 1 mm/s of 0.3 m/s ... rounding of x / dt
    assert np.abs(v - u).max() < 1e-4


def test_motion_velocities_integrate_to_the_stored_positions(plain):
    """positions[k] = positions[k−1] + dt · motion_velocities[k] (x_{−1}: the groom carried by the
    pose at t = 0), while the simulator's state velocity is another quantity."""
    _, (path,), _ = plain
    with h5py.File(path, "r") as f:
        g = f["seq_000002"]
        x, mv, v = g["positions"][()].astype(np.float64), g["motion_velocities"][()], g["velocities"][()]
        dt = float(g.attrs["dt"])
    assert np.abs(x[1:] - x[:-1] - dt * mv[1:]).max() < 1e-6
    assert np.abs(mv - v).max() > 1e-3  # follow-the-leader and damping: the state velocity is not the motion's


# -- benchmark samples --------------------------------------------------------------------------
def test_dataset_makes_benchmark_samples(plain):
    r, (path,), out = plain
    ds = HairSequenceDataset(out, window=None, guides=3)
    assert len(ds) == 4 and ds.alone_counts == [3, 8] and ds.dense_guides == 8  # one item per whole sequence
    item = ds[1]
    shapes = {k: tuple(v.shape) for k, v in item.items() if isinstance(v, torch.Tensor)}
    assert shapes == {"guide_positions": (5, 3, 6, 3), "guide_index": (3,), "rest_positions": (40, 6, 3),
                      "num_pinned": (40,), "rotations": (5, 3, 3), "translations": (5, 3), "positions": (5, 40, 6, 3),
                      "collider_rotations": (5, 0, 3, 3), "collider_translations": (5, 0, 3)}
    assert item["guide_index"].dtype == torch.long and item["num_pinned"].dtype == torch.long
    assert item["guide_positions"].dtype == torch.float32 and (item["sequence"], item["start"]) == (1, 0)
    with h5py.File(path, "r") as f:
        g = f["seq_000001"]
        assert np.array_equal(item["guide_positions"].numpy(), g["guides_alone_3"][()])
        assert np.array_equal(item["guide_index"].numpy(), g["guide_indices"][:3])
        assert np.array_equal(item["num_pinned"].numpy(), g["num_pinned"][()])
    d = HairSequenceDataset(out, window=2, stride=3, guides=5, guide_source="dense", fields=["motion_velocities"],
                            split="test")
    test = [i for i in range(4) if r.sequence_split(i) == "test"]
    assert [(it["sequence"], it["start"]) for it in d] == [(i, s) for i in test for s in (0, 3)]
    one = d[1]  # the first test sequence, frames 3-4
    with h5py.File(path, "r") as f:
        g = f[f"seq_{test[0]:06d}"]
        assert np.array_equal(one["guide_positions"].numpy(), g["guide_positions"][3:5, :5])
        assert np.array_equal(one["motion_velocities"].numpy(), g["motion_velocities"][3:5])
    batches = list(torch.utils.data.DataLoader(ds, batch_size=2, num_workers=2))
    assert len(batches) == 2 and batches[0]["guide_positions"].shape == (2, 5, 3, 6, 3)
    with pytest.raises(ValueError, match=r"guides=4 was not simulated alone in this dataset \(guide counts simulated "
                                         r"alone: \[3, 8\]\)"):
        HairSequenceDataset(out, guides=4)
    with pytest.raises(ValueError, match=r"stores the dense run's copies of 8 guide\(s\)"):
        HairSequenceDataset(out, guides=9, guide_source="dense")
    with pytest.raises(ValueError, match="guide_source must be one of"):
        HairSequenceDataset(out, guides=3, guide_source="alon")


def test_format_2_files_are_still_read(plain, tmp_path):
    """A version-2 file (no guides alone, no num_pinned): read, num_pinned from the stored params."""
    _, (path,), _ = plain
    old = str(tmp_path / "old.h5")
    with open(path, "rb") as src, open(old, "wb") as dst:
        dst.write(src.read())
    with h5py.File(old, "r+") as f:
        f.attrs["format_version"] = 2
        del f.attrs["attrs_sha256"]  # version 2 files had no attribute digests
        for name in [k for k in f if k.startswith("seq_")]:
            del f[name].attrs["attrs_sha256"]
            for k in ("guides_alone_3", "guides_alone_8", "num_pinned", "frame_sha256/guides_alone_3",
                      "frame_sha256/guides_alone_8"):
                del f[name][k]
    ds = HairSequenceDataset(old, window=None, guides=8, guide_source="dense")
    with h5py.File(path, "r") as f:
        assert np.array_equal(ds[0]["num_pinned"].numpy(), f["seq_000000/num_pinned"][()])
    with pytest.raises(ValueError, match="alone: none"):
        HairSequenceDataset(old, guides=8)


# -- splits and colliders -----------------------------------------------------------------------
HOLD = """
name = "hold"
sequences = 24
frames = 3
batch = 2
colliders = { cycle = [[{ type = "sphere", center = [0.0, -0.2, 0.15], radius = 0.03 }], [], [{ type = "capsule", a = [0.0, -0.3, 0.15], b = [0.0, -0.1, 0.15], radius = 0.02 }]] }
[head]
mesh = "sphere"
radius = 0.1
[groom]
kind = "sphere"
strands = 12
particles = 5
length = 0.1
seed = { cycle = [0, 1, 2, 3] }
[stages]
collisions = true
[motion]
type = { choice = ["shake", "nod", "spin"] }
[store]
guides = 2
[split]
train = 0.75
valid = 0.0
test = 0.25
by = "groom"
[split.hold_out]
motion = ["spin"]
collider = ["capsule"]
groom_seed = [3]
"""


def test_split_hold_outs(tmp_path):
    r = load_recipe(write(tmp_path, HOLD, "hold.toml"))
    assert r.colliders_vary and r.groom_varies
    seeds = [r.group_spec(g)["groom"]["seed"] for g in range(r.num_groups)]
    kinds = [[c["type"] for c in r.group_spec(g)["colliders"]] for g in range(r.num_groups)]
    assert seeds == [g % 4 for g in range(12)] and kinds == [[["sphere"], [], ["capsule"]][g % 3] for g in range(12)]
    split = {i: r.sequence_split(i) for i in range(24)}
    tags = {i: r.sequence_holdout(i) for i in range(24)}
    for i in range(24):
        g = i // 2
        motion = r.sequence_spec(i)["motion_type"]
        assert ("groom_seed" in tags[i]) == (seeds[g] == 3)
        assert ("collider" in tags[i]) == (kinds[g] == ["capsule"])
        assert ("motion" in tags[i]) == (motion == "spin")
        if tags[i]:
            assert split[i] == "test"
    # by groom: the sequences that are not held out for their scene put every groom in one split
    by_groom = {}
    for i in range(24):
        if not {"motion", "collider"} & set(tags[i]):
            by_groom.setdefault(seeds[i // 2], set()).add(split[i])
    assert all(len(s) == 1 for s in by_groom.values()) and by_groom[3] == {"test"}
    assert {"train"} in by_groom.values() and {"test"} in [by_groom[k] for k in (0, 1, 2)]
    # the same recipe without a [split] table splits as version 2 did: by batch group
    plain = load_recipe(write(tmp_path, HOLD.split("[split]")[0], "plain.toml"))
    assert all(plain.sequence_holdout(i) == [] for i in range(24))
    cases = [('motion = ["spin"]', 'motion = ["spinn"]', "[split.hold_out].motion: 'spinn' is not a motion type"),
             ('motion = ["spin"]', 'motion = ["roller_coaster"]', "the recipe never draws 'roller_coaster'"),
             ('collider = ["capsule"]', 'collider = ["plane"]', "[split.hold_out].collider: the recipe never draws"),
             ('groom_seed = [3]', 'groom_seed = [7]', "[split.hold_out].groom_seed: the recipe never draws 7"),
             ('by = "groom"', 'by = "group"', 'holds out grooms: set [split].by = "groom"'),
             ('seed = { cycle = [0, 1, 2, 3] }', '', "the groom seed is drawn at random per batch group"),
             ('train = 0.75\nvalid = 0.0\ntest = 0.25', 'train = 0.85\nvalid = 0.1\ntest = 0.05',
              "no sequence goes to the valid split"),
             ('groom_seed = [3]', 'bogus = [3]', "unknown key(s) ['bogus'] in [split.hold_out]")]
    for old, new, match in cases:
        assert old in HOLD, old
        with pytest.raises(RecipeError) as err:
            load_recipe(write(tmp_path, HOLD.replace(old, new, 1), "bad.toml"))
        assert match in str(err.value) and "bad.toml" in str(err.value), str(err.value)


def test_colliders_drawn_per_group_are_stored_per_group(tmp_path):
    text = HOLD.replace("sequences = 24", "sequences = 6").replace('motion = ["spin"]\n', "") \
        .replace("groom_seed = [3]\n", "").replace('by = "groom"\n', "").replace("train = 0.75", "train = 0.5") \
        .replace("test = 0.25", "test = 0.5")
    r, paths, out = make(tmp_path, text, "cols.toml", num_shards=2)
    assert validate(out).ok
    ds = HairSequenceDataset(out, window=None, guides=2)
    for item in ds:
        i = item["sequence"]
        f = next(p for p in paths if f"seq_{i:06d}" in h5py.File(p, "r"))
        cols = read_scene_meshes(f, i)["colliders"]
        assert [c["type"] for c in cols] == [["sphere"], [], ["capsule"]][i // 2 % 3]
        assert item["collider_rotations"].shape == (3, len(cols), 3, 3)
        scene = json.loads(h5py.File(f, "r")[f"seq_{i:06d}"].attrs["scene"])
        assert [c["type"] for c in scene["colliders"]] == [c["type"] for c in cols]
    assert read_scene_meshes(paths[0])["colliders"] is None  # they vary: ask per sequence


# -- grooms ---------------------------------------------------------------------------------------
def test_single_groom_recipes_are_checked_and_generate_says_how_many_grooms(tmp_path):
    text = open(os.path.join(ROOT, "datasets", "tiny.toml")).read()
    one = text.replace('preset = { choice = ["straight", "wavy", "bob"] }', 'preset = "straight"') \
        .replace("length_jitter = { uniform = [0.0, 0.3] }", "length_jitter = 0.1")
    with pytest.raises(RecipeError, match=r"single_groom = true, but \[groom\].seed is not set, so each batch group "
                                          r"draws its own seed: this recipe would grow up to 3 different grooms"):
        load_recipe(write(tmp_path, "single_groom = true\n" + one, "tiny.toml"))
    r = load_recipe(write(tmp_path, "single_groom = true\n" + one.replace("particles = 12", "particles = 12\nseed = 5"),
                          "tiny.toml"))
    assert r.groom_note() == "grooms: one groom for all 3 batch group(s)"
    many = load_recipe(write(tmp_path, one, "tiny.toml"))
    assert many.groom_note() == ("grooms: 3 different groom(s) in 3 batch group(s) ([groom].seed is not set, so each "
                                 "batch group draws its own seed)")
    with pytest.raises(RecipeError, match=r"single_groom = true, but \[groom\] holds samplers"):
        load_recipe(write(tmp_path, "single_groom = true\n" + text, "tiny.toml"))


def test_dataset_lists_its_grooms(plain):
    _, _, out = plain
    grooms = HairSequenceDataset(out).grooms()
    assert sorted(i for seqs in grooms.values() for i in seqs) == [0, 1, 2, 3] and len(grooms) == 1


# -- suites ---------------------------------------------------------------------------------------
def test_bench_suites_parse_and_say_what_they_hold():
    """Every preset with >= 3 seeds, >= 10 test sequences per groom family and track, held-out
    motions, colliders and groom seeds, guides simulated alone; Ratboy when the assets are there."""
    from ams_torch.grooms.presets import PRESETS

    for suite in ("standard", "full"):
        recipes, skipped = suite_recipes(os.path.join(ROOT, "datasets", "bench", suite))
        names = {r.name for r in recipes}
        assert {"free", "hairhair", "contact"} <= names
        have_assets = os.path.isdir(os.path.join(ROOT, "..", "shared", "assets"))
        assert ("ratboy" in names) == have_assets and bool(skipped) == (not have_assets)
        held, families = set(), set()
        for r in recipes:
            assert r.alone_counts == r.guide_counts and len(r.guide_counts) >= 2
            test = [i for i in range(r.num_sequences) if r.sequence_split(i) == "test"]
            held |= {t for i in test for t in r.sequence_holdout(i)}
            grooms = [r.group_spec(g)["groom"] for g in range(r.num_groups)]
            presets = {g.get("preset") for g in grooms} - {None}
            families |= presets
            for p in presets:  # >= 10 test sequences per groom family (full's dense100k: a cost track), >= 3 seeds
                assert r.name == "dense100k" or sum(grooms[i // r.batch].get("preset") == p for i in test) >= 10, \
                    (suite, r.name, p)
                assert len({g["seed"] for g in grooms if g.get("preset") == p}) >= 3, (suite, r.name, p)
            if r.name == "free":
                assert presets == set(PRESETS)
        assert held >= {"motion", "collider", "groom_seed"} and families == set(PRESETS)


def test_mini_suite_generates_into_a_benchmark_dataset(tmp_path):
    """datasets/bench/mini.toml as a one-recipe suite folder: generated, complete and sound, with
    train and test sequences, a held-out groom and samples for both guide counts."""
    suite = tmp_path / "suite"
    suite.mkdir()
    (suite / "mini.toml").write_text(open(os.path.join(ROOT, "datasets", "bench", "mini.toml")).read())
    (suite / "assets.toml").write_text('requires = ["no/such/folder"]\n' + BASE)
    logs = []
    done = generate_suite(str(suite), str(tmp_path / "out"), progress=False, log=logs.append)
    assert list(done) == ["mini"] and any("skipping assets.toml" in m for m in logs)
    assert list_datasets(str(tmp_path / "out")) == [str(tmp_path / "out" / "mini")]
    assert validate(str(tmp_path / "out" / "mini")).ok
    train = HairSequenceDataset(str(tmp_path / "out" / "mini"), window=None, guides=16, split="train")
    test = HairSequenceDataset(str(tmp_path / "out" / "mini"), window=None, guides=8, split="test")
    assert len(train) >= 2 and len(test) >= 2 and len(train.grooms()) == 1 and len(test.grooms()) == 2
    item = test[0]
    assert item["guide_positions"].shape == (10, 8, 8, 3) and item["positions"].shape == (10, 64, 8, 3)
    assert item["collider_rotations"].shape == (10, 1, 3, 3)
    with pytest.raises(MissingRequirement, match="requires 'no/such/folder'"):
        load_recipe(str(suite / "assets.toml"))


def test_cli_generates_a_suite_folder(tmp_path, capsys):
    from ams_torch.apps.cli import main

    suite = tmp_path / "suite"
    suite.mkdir()
    (suite / "a.toml").write_text(BASE.replace('name = "guides"', 'name = "first"')
                                  .replace("sequences = 4", "sequences = 2"))
    (suite / "b.toml").write_text('requires = ["../no_assets"]\n' + BASE.replace('name = "guides"', 'name = "second"'))
    assert main(["generate", str(suite), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    text = capsys.readouterr().out
    assert "skipping b.toml" in text and "requires '../no_assets'" in text and "first: grooms: one groom" in text
    assert list_datasets(str(tmp_path / "out")) == [str(tmp_path / "out" / "first")]
    assert main(["validate", str(tmp_path / "out" / "first"), "--quiet"]) == 0
    (suite / "c.toml").write_text(BASE.replace('name = "guides"', 'name = "first"'))
    assert main(["generate", str(suite), "--out", str(tmp_path / "out2"), "--quiet"]) != 0
    assert "c.toml have the same name 'first' (one output folder each); rename one" in capsys.readouterr().err
