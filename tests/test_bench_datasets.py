"""scripts/bench_datasets.py at toy sizes (the full runs are by hand: docs/benchmarks/datasets.md)."""
import json

import pytest
from helpers import built_native, load_script


def test_bench_datasets_simulation_section(tmp_path):
    """The batched-simulation section: one record per B with the throughput fields, the batching
    ratio against B = 1, and the table with the target column."""
    built_native("cpu")
    bench = load_script("bench_datasets")
    bench.main(["--sections", "sim", "--sim-strands", "24", "--sim-batches", "1", "4", "--sim-frames", "2",
                "--particles", "8", "--resolution", "16", "--threads", "1", "--out", str(tmp_path)])
    rec = json.loads((tmp_path / "datasets.json").read_text())
    sims = rec["simulation"]
    assert [r["batch"] for r in sims] == [1, 4] and rec["generation"] == [] and rec["ray"] == []
    for r in sims:
        assert r["ms_per_frame"] > 0 and r["sequence_frames_per_s"] > 0 and r["grid_capacity"] >= 1
        assert r["sequence_frames_per_s"] == pytest.approx(1e3 * r["batch"] / r["ms_per_frame"])
    assert sims[0]["batch_ratio"] == 1.0
    assert sims[1]["batch_ratio"] == pytest.approx(sims[1]["ms_per_frame"] / (4 * sims[0]["ms_per_frame"]))
    md = (tmp_path / "datasets.md").read_text()
    assert "## Batched simulation" in md and "| 24 | 4 |" in md and "Generation" not in md


@pytest.mark.slow
def test_bench_datasets_ray_section(tmp_path):
    """The Ray section: a loopback cluster of 1, then 2 worker CPUs generates the same recipe."""
    pytest.importorskip("ray")
    bench = load_script("bench_datasets")
    bench.main(["--sections", "ray", "--strands", "24", "--particles", "8", "--frames", "2", "--ray-sequences", "4",
                "--ray-batch", "2", "--resolution", "16", "--threads", "1", "--out", str(tmp_path)])
    rays = json.loads((tmp_path / "datasets.json").read_text())["ray"]
    assert [r["workers"] for r in rays] == [1, 2] and rays[0]["speedup"] == 1.0 and all(r["seconds"] > 0 for r in rays)
    assert "## The Ray backend" in (tmp_path / "datasets.md").read_text()


def test_storage_copies_read_and_verify(tmp_path):
    """The read section's float16 / lzf / uncompressed copies of a generated file read and verify
    (checksums and the attributes' digest recomputed), and float16 rounds within 2⁻¹¹ relative."""
    import numpy as np
    import torch
    from learned_data import toy_dataset

    from ams_torch.apps.data import HairSequenceDataset, validate

    bench = load_script("bench_datasets")
    src = toy_dataset(tmp_path / "src", sequences=2, frames=4, batch=2, strands=12, particles=6, guides=4,
                      split=(1.0, 0.0, 0.0))
    base = HairSequenceDataset(src, window=None, verify="always")
    for prec, comp in (("float16", "gzip"), ("float32", "lzf"), ("float32", "none")):
        out = tmp_path / f"{prec}-{comp}"
        out.mkdir()
        for f in sorted((tmp_path / "src").glob("*.h5")):
            bench.copy_with_storage(str(f), str(out / f.name), prec, comp)
        assert validate(str(out)).ok, validate(str(out))
        ds = HairSequenceDataset(str(out), window=None, verify="always")
        a, b = ds[0]["positions"], base[0]["positions"]
        tol = 2.0 ** -11 * float(b.abs().max()) if prec == "float16" else 0.0
        assert torch.allclose(a.float(), b.float(), atol=tol, rtol=0) and np.isfinite(a.numpy()).all()
