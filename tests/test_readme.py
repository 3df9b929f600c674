"""The README's Python examples run as written (in a scratch folder, after the one command the
dataset example names)."""
import re
from pathlib import Path

import torch

README = Path(__file__).resolve().parents[1] / "README.md"


def _blocks():
    return re.findall(r"```python\n(.*?)```", README.read_text(), re.S)


def test_readme_has_the_examples():
    blocks = _blocks()
    assert len(blocks) == 3, "update this test when the README's examples change"
    assert "ams_torch as at" in blocks[0] and "testing" not in blocks[0]  # no test helpers in the first example


def test_first_example_simulates(monkeypatch, tmp_path):
    monkeypatch.chdir(tmp_path)
    ns = {}
    exec(compile(_blocks()[0], "README.md:first example", "exec"), ns)
    x = ns["state"].x
    assert x.shape == (1000, 32, 3) and bool(torch.isfinite(x).all())
    assert int(ns["state"].frame) == 120


def test_plugin_and_dataset_examples(monkeypatch, tmp_path):
    from ams_torch.apps.cli import main
    from baselines import Interpolator
    from baselines.protocol import check_prediction
    from baselines.scene import make_sample

    monkeypatch.chdir(tmp_path)
    root = Path(__file__).resolve().parents[1]
    assert main(["generate", str(root / "datasets/bench/mini.toml"), "--out", "out/bench/mini", "--quiet"]) == 0
    plugin, data = {}, {}
    exec(compile(_blocks()[1], "README.md:plug-in example", "exec"), plugin)
    exec(compile(_blocks()[2], "README.md:dataset example", "exec"), data)
    method = plugin["make"]()
    assert isinstance(method, Interpolator)
    sample = make_sample(data["sample"], data["test"])
    ref = sample.pop("positions")
    out = check_prediction("readme", method.fit(data["train"], sample["guide_index"]).predict(sample), sample)
    assert out.shape == ref.shape
    # every guide strand is its own nearest guide: it is reproduced exactly
    assert torch.allclose(out[:, sample["guide_index"]], sample["guide_positions"], atol=1e-6)
