"""The interpolation benchmark end to end: the `mini` suite generated and scored through
`ams-torch bench-interp`, with a plug-in method defined here (module:factory), resumption, and
the errors a newcomer meets."""
import json
import shutil

import pytest
import torch

from ams_torch.apps.cli import main
from baselines.protocol import Interpolator


class CopyNearestGuide(Interpolator):
    """A user's method: every strand takes its nearest guide's shape (no head rotation of the
    offset), to show that any Interpolator plugs in."""

    name = "copy-nearest"

    def predict(self, sample):
        rest, gi = sample["rest_positions"], sample["guide_index"]
        near = torch.cdist(rest[:, 0], rest[gi, 0]).argmin(1)
        shift = (rest[:, :1] - rest[gi][near][:, :1])  # root offsets, head frame (S, 1, 3)
        world = torch.einsum("tij,snj->tsni", sample["rotations"], shift)
        return sample["guide_positions"][:, near] + world


def make_plugin(device=None):
    return CopyNearestGuide()


class WrongShape(Interpolator):
    def predict(self, sample):
        return sample["guide_positions"]  # (T, G, N, 3): not the dense groom


def make_wrong():
    return WrongShape()


@pytest.fixture(scope="module")
def mini_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench") / "mini"
    argv = ["bench-interp", "mini", "--methods", "rigid,skinning,skinning+pushout,test_bench_interp:make_plugin,"
            "agnostic,upsampler", "--guides", "8,16", "--out", str(out), "--cost-sizes", "100", "--cost-frames", "1",
            "--train", "--option", "agnostic.steps=10", "--option", "upsampler.steps=10", "--quiet"]
    assert main(argv) == 0
    return out, argv


def test_mini_suite_end_to_end(mini_run):
    out, _ = mini_run
    res = json.loads((out / "results.json").read_text())
    prov = res["runs"][-1]
    for k in ("commit", "ams_torch", "torch", "device", "date", "command"):
        assert k in prov
    info = res["datasets"]["mini"]
    assert info["guides_alone"] == [8, 16] and len(info["checksum"]) == 64
    rows = [r for r in res["rows"] if r["guide_source"] == "alone"]
    tests = info["splits"]["test"]
    for m in ("rigid", "skinning", "skinning+pushout", "test_bench_interp:make_plugin", "(dense reference)",
              "(guide input vs dense copies)"):
        for g in (8, 16):
            got = [r for r in rows if r["method"] == m and r["guides"] == g]
            assert len(got) == tests, (m, g)
    by = {(r["method"], r["guides"], r["sequence"]): r for r in rows}
    for (m, g, q), r in by.items():
        if "not_applicable" in r:
            continue
        assert r["mean_mm"] >= 0 and r["p95_mm"] <= r["max_mm"] + 1e-9
        if m == "skinning+pushout":  # the push-out never adds penetration, and leaves none deeper than 0.1 mm
            assert r["head_inside_share"] <= by[("skinning", g, q)]["head_inside_share"]
            assert r["head_inside_share"] == 0.0
    # the dense reference is exact against itself; guides alone are not the dense run's copies (hair–hair on)
    assert all(r["mean_mm"] == 0 for r in rows if r["method"] == "(dense reference)")
    assert any(r["mean_mm"] > 0 for r in rows if r["method"] == "(guide input vs dense copies)")
    # more guides: skinning gets closer to the dense run on average
    mean = lambda m, g: sum(r["mean_mm"] for r in rows if r["method"] == m and r["guides"] == g)  # noqa: E731
    assert mean("skinning", 16) < mean("skinning", 8)
    assert {r["holdout"] for r in rows} >= {"groom_seed", "motion"}
    # learned: trained on the train split; the upsampler is bound to its groom: n/a on the held-out groom
    assert all("mean_mm" in r for r in rows if r["method"] == "agnostic")
    up = [r for r in rows if r["method"] == "upsampler"]
    assert {r["holdout"] for r in up if "not_applicable" in r} == {"groom_seed"}
    assert all("mean_mm" in r for r in up if r["holdout"] != "groom_seed")
    assert (out / "models" / "mini" / "agnostic-G8.pt").exists()
    board = (out / "leaderboard.md").read_text()
    assert "test_bench_interp:make_plugin" in board and "held out: groom_seed" in board
    assert (out / "error_vs_guides.png").stat().st_size > 0
    assert res["cost"] and {c["method"] for c in res["cost"]} >= {"skinning", "test_bench_interp:make_plugin"}
    assert res["cost_dataset"] == "mini"


def test_rerun_resumes_without_recomputing(mini_run, tmp_path):
    out, argv = mini_run
    copy = tmp_path / "again"
    shutil.copytree(out, copy)
    res = json.loads((copy / "results.json").read_text())
    kept = len(res["rows"])
    res["rows"] = [r for r in res["rows"] if not (r["method"] == "skinning" and r["guides"] == 16)]  # "killed" there
    (copy / "results.json").write_text(json.dumps(res))
    args = [a if a != str(out) else str(copy) for a in argv]
    args[args.index("--cost-sizes") + 1] = "none"
    assert main(args) == 0
    again = json.loads((copy / "results.json").read_text())
    assert len(again["rows"]) == kept  # only the missing rows were scored again
    assert len(again["runs"]) == 2


def test_training_resumed_under_a_larger_cap_rescores_its_rows(mini_run, tmp_path):
    """A rerun with a larger step cap resumes the learned model's training; the rows the old
    model scored are scored again (each row names its model), every other row is kept."""
    out, argv = mini_run
    copy = tmp_path / "longer"
    shutil.copytree(out, copy)
    before = json.loads((copy / "results.json").read_text())["rows"]
    old = {r.get("model") for r in before if r["method"] == "upsampler" and r["guides"] == 8}
    assert len(old) == 1 and None not in old and old.pop().endswith("/10")
    args = [a if a != str(out) else str(copy) for a in argv]
    args[args.index("--cost-sizes") + 1] = "none"
    args[args.index("upsampler.steps=10")] = "upsampler.steps=14"
    args[args.index("--methods") + 1] = "upsampler,skinning"
    args[args.index("--guides") + 1] = "8"
    assert main(args) == 0
    after = json.loads((copy / "results.json").read_text())["rows"]
    assert len(after) == len(before)
    new = {r["model"] for r in after if r["method"] == "upsampler" and r["guides"] == 8}
    assert len(new) == 1 and new.pop().endswith("/14")
    # untouched: the other guide count's model and every method that learns nothing
    assert [r for r in after if r["method"] == "upsampler" and r["guides"] == 16] == \
        [r for r in before if r["method"] == "upsampler" and r["guides"] == 16]
    assert [r for r in after if r["method"] == "skinning"] == [r for r in before if r["method"] == "skinning"]


def test_errors_a_newcomer_meets(mini_run, tmp_path, capsys):
    out, _ = mini_run
    data = str(out / "data" / "mini")
    assert main(["bench-interp", data, "--methods", "test_bench_interp:make_wrong", "--guides", "8",
                 "--out", str(tmp_path / "w"), "--cost-sizes", "none", "--quiet"]) == 2
    assert "returned shape" in capsys.readouterr().err
    assert main(["bench-interp", data, "--methods", "skinning", "--guides", "12", "--out", str(tmp_path / "g"),
                 "--cost-sizes", "none", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "G in [8, 16]" in err and "--guide-source dense" in err
    assert main(["bench-interp", "no_such_suite", "--methods", "skinning", "--guides", "8",
                 "--out", str(tmp_path / "s"), "--quiet"]) == 2
    assert "neither a dataset" in capsys.readouterr().err
    assert main(["bench-interp", data, "--methods", "nope:factory", "--guides", "8", "--out", str(tmp_path / "m"),
                 "--cost-sizes", "none", "--quiet"]) == 2
    assert "cannot import module" in capsys.readouterr().err
    assert main(["bench-interp", data, "--methods", "skinning", "--guides", "8", "--out", str(tmp_path / "c"),
                 "--cost-sizes", "100", "--cost-dataset", "hairhair", "--quiet"]) == 2
    assert "--cost-dataset 'hairhair' is not a dataset of this run" in capsys.readouterr().err


def test_dataset_without_guides_is_refused_naming_the_recipe_key():
    from baselines.bench import BenchError, _check_guides

    none = {"guides_max": 0, "guides_alone": []}
    with pytest.raises(BenchError, match=r"stores no guide strands.*\[store\] guides"):
        _check_guides("d", none, [8], ["alone"])
    few = {"guides_max": 16, "guides_alone": [8, 16]}
    with pytest.raises(BenchError, match="stores 16 guides; --guides 32"):
        _check_guides("d", few, [32], ["dense"])
    _check_guides("d", few, [8, 16], ["alone", "dense"])  # fine
