"""Dataset metadata is checked like the arrays (issue 28, items 6 and 7): attributes edited or
deleted after writing are problems for ``validate`` (exit 1) and a DatasetError for the Dataset,
never a silently different dataset or a raw KeyError; a file given twice is refused."""
import os
import shutil

import h5py
import numpy as np
import pytest

from ams_torch.apps.cli import main
from ams_torch.apps.data import DatasetError, HairSequenceDataset, validate, validate_file
from ams_torch.apps.data.metadata import ATTRS_DIGEST, FILE_ATTRS, SEQUENCE_ATTRS, attrs_digest
from ams_torch.apps.datagen import generate
from ams_torch.apps.recipe import parse_recipe


@pytest.fixture(scope="module")
def shard(tmp_path_factory):
    """4 sequences of 5 frames in 2 batch groups (one train, one test), with guides and velocities."""
    r = parse_recipe({"name": "meta", "sequences": 4, "frames": 5, "batch": 2, "head": {"mesh": "sphere"},
                      "groom": {"kind": "sphere", "strands": 10, "particles": 6}, "motion": {"type": "nod"},
                      "store": {"guides": 2, "velocities": True}, "split": {"train": 0.5, "test": 0.5}})
    return generate(r, str(tmp_path_factory.mktemp("meta") / "d"), progress=False, log=lambda s: None)[0]


def _copy(shard, tmp_path):
    path = str(tmp_path / os.path.basename(shard))
    shutil.copy(shard, path)
    return path


def _tamper(path, edit, reseal=False):
    """Apply ``edit(f)`` to the file; ``reseal``: recompute the attrs digests as a careful forger
    would, so only the relations between attributes and arrays can tell."""
    with h5py.File(path, "r+") as f:
        edit(f)
        if reseal:
            for obj in [f] + [f[k] for k in f if k.startswith("seq_")]:
                if ATTRS_DIGEST in obj.attrs:
                    obj.attrs[ATTRS_DIGEST] = attrs_digest(obj.attrs)


def test_a_sound_file_has_no_metadata_problems(shard):
    assert validate_file(shard) == []
    with h5py.File(shard, "r") as f:
        assert ATTRS_DIGEST in f.attrs and all(ATTRS_DIGEST in f[k].attrs for k in f if k.startswith("seq_"))
        assert set(FILE_ATTRS) <= set(f.attrs) and set(SEQUENCE_ATTRS) <= set(f["seq_000000"].attrs)
    assert len(HairSequenceDataset(shard, window=2)) == 4 * 4


def _set(key, value, seq="seq_000001"):
    return lambda f: f[seq].attrs.__setitem__(key, value)


def _del(key, seq="seq_000001"):
    return lambda f: f[seq].attrs.__delitem__(key)


CASES = {  # name: (edit, reseal, words the problem must hold)
    "frames 1000": (_set("frames", 1000), False, "'frames'"),
    "frames 5 -> 3": (_set("frames", 3), True, "'frames' = 3"),
    "index duplicated": (_set("index", 0), True, "'index' = 0 does not match"),
    "index deleted": (_del("index"), False, "'index' is missing"),
    "group changed": (_set("group", 1), True, "'group' = 1"),
    "split changed": (_set("split", "valid"), True, "the masks put it in"),
    "seed changed": (_set("seed", 7), False, "attrs_sha256 mismatch"),
    "motion changed": (_set("motion", '{"type": "static"}'), False, "attrs_sha256 mismatch"),
    "frame digests deleted": (lambda f: f["seq_000001"].__delitem__("frame_sha256"), False,
                              "frame_sha256/positions is missing"),
    "array checksum deleted": (lambda f: f["seq_000001/rest_positions"].attrs.__delitem__("sha256"), False,
                               "rest_positions: attribute 'sha256'"),
    "recipe_digest deleted": (lambda f: f.attrs.__delitem__("recipe_digest"), False, "'recipe_digest' is missing"),
    "recipe_digest forged": (lambda f: f.attrs.__setitem__("recipe_digest", "0" * 64), True,
                             "not the SHA-256 of the stored recipe"),
    "file frames changed": (lambda f: f.attrs.__setitem__("frames", 4), True, "holds 5 frames"),
    "sequence listed twice": (lambda f: f.attrs.__setitem__("sequences", np.array([0, 0, 1, 2, 3])), True,
                              "lists a sequence twice"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_edited_metadata_is_a_problem_and_the_dataset_refuses_it(shard, tmp_path, case, capsys):
    edit, reseal, words = CASES[case]
    path = _copy(shard, tmp_path)
    _tamper(path, edit, reseal)
    problems = validate_file(path)
    assert any(words in p for p in problems), problems
    assert all(p.startswith(path) for p in problems)
    assert main(["validate", path, "--quiet"]) == 1
    capsys.readouterr()
    with pytest.raises(DatasetError) as err:
        HairSequenceDataset(path, window=2)
    assert str(err.value).startswith(path) and "ams-torch validate" in str(err.value)


def test_a_file_given_twice_is_refused(shard, tmp_path):
    """Item 7: HairSequenceDataset([f, f]) held every sequence twice (8 windows became 16)."""
    link = tmp_path / "same.h5"
    os.symlink(shard, link)
    for files in ([shard, shard], [shard, str(link)]):
        with pytest.raises(DatasetError, match="is given twice"):
            HairSequenceDataset(files, window=2)
        report = validate(files)
        assert not report.ok and any("is given twice" in p for p in report.problems)
    assert len(HairSequenceDataset([shard], window=2)) == 16


def test_validate_could_not_run_on_any_file_that_is_not_a_dataset(shard, tmp_path, capsys):
    """Item 14: a `.data` groom gave exit 1 (problems found), a simulate `sequence.h5` exit 2 (could
    not run); both are not datasets: 2. A truncated dataset file is a problem found: 1."""
    groom = tmp_path / "hair.data"
    groom.write_bytes(np.random.default_rng(0).bytes(3000))
    seq = tmp_path / "sequence.h5"
    with h5py.File(seq, "w") as f:
        f["positions"] = np.zeros((1, 2, 4, 3), np.float32)
    for p in (groom, seq):
        assert main(["validate", str(p), "--quiet"]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"error: {p}: not an ams_torch dataset") and err.count("\n") == 1
    cut = tmp_path / "cut.h5"
    cut.write_bytes(open(shard, "rb").read()[:20000])
    assert main(["validate", str(cut), "--quiet"]) == 1
    assert "cannot be opened as HDF5" in capsys.readouterr().out
