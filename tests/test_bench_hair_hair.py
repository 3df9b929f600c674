"""scripts/bench_hair_hair.py at toy sizes (the full run is by hand: docs/benchmarks/hair_hair.md)."""
import json

from helpers import built_native, load_script


def test_bench_hair_hair_smoke(tmp_path):
    """Both backends and the dense definition timed per case, the blocks the hair occupies
    recorded, the R-scaling table relative to R = 64 and the target rows written."""
    built_native("cpu")
    bench = load_script("bench_hair_hair")
    out = tmp_path / "hh"
    bench.main(["--cases", "40x8", "--resolutions", "16", "64", "--reps", "1", "--collision-cases", "--dense",
                "--dense-max-resolution", "16", "--threads", "1", "--out", str(out)])
    result = json.loads(out.with_suffix(".json").read_text())
    rows = {r["resolution"]: r for r in result["rows"]}
    assert set(rows) == {16, 64}
    for r in rows.values():
        assert 0 < r["blocks_used"] <= r["capacity_blocks"] and r["native_median_ms"] > 0
        assert r["native_vs_torch_dv_rel"] < 1e-3  # float32 parity of the whole stage
    assert "dense_median_ms" in rows[16] and "dense_median_ms" not in rows[64]
    scale = {(s["backend"], s["resolution"]): s["over_r64"] for s in result["scaling"]}
    assert scale[("native", 64)] == 1.0 and ("torch", 16) in scale
    md = out.with_suffix(".md").read_text()
    assert "| 40 × 8 | 64³ | off |" in md and "relative to R = 64" in md
