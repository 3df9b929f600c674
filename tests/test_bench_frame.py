"""scripts/bench_frame.py and scripts/parity_frames.py run (the full runs are by hand:
docs/benchmarks/frame.md, docs/benchmarks/parity.md)."""
import json

from helpers import built_native, load_script


def test_bench_frame_smoke(tmp_path, capsys):
    """scripts/bench_frame.py, in-process and tiny: both paths timed, the JSON records carry the
    fields the issue names, the native path dispatches fewer ops than the torch path, and the
    markdown table and ratio are written."""
    built_native("cpu")
    bench = load_script("bench_frame")
    out = tmp_path / "frame"
    assert bench.main(["--scenes", "dynamics", "--strands", "64", "--reps", "2", "--no-memory", "--threads", "1",
                       "--profile", "2", "--out", str(out)]) == 0
    assert "ams_torch_cpu::frame_finish" in capsys.readouterr().out  # the profile names the fused kernel
    records = json.loads((tmp_path / "frame.json").read_text())["records"]
    keys = {"scene", "S", "N", "device", "path", "stage", "median_ms", "min_ms", "ops_per_frame",
            "peak_bytes_per_particle"}
    assert all(keys <= set(r) for r in records)
    total = {r["path"]: r for r in records if r["stage"] == "total"}
    assert set(total) == {"native", "torch"} and total["native"]["S"] == 64 and total["native"]["N"] == 32
    assert total["native"]["ops_per_frame"] < total["torch"]["ops_per_frame"] / 10
    assert all(r["min_ms"] > 0 and r["min_ms"] <= r["median_ms"] for r in records if r["stage"] == "total")
    md = (tmp_path / "frame.md").read_text()
    assert "| dynamics | 64 | native |" in md and "torch / native" in md
    # the markdown can be re-rendered from the JSON alone, with the targets table
    (tmp_path / "frame.md").unlink()
    assert bench.main(["--render", str(tmp_path / "frame.json"), "--note", "a note"]) == 0
    md = (tmp_path / "frame.md").read_text()
    assert "| dynamics | 64 | native |" in md and "ops per frame, native" in md and md.rstrip().endswith("a note")


def test_parity_script_whole_runs_agree(tmp_path):
    """scripts/parity_frames.py on a small version of the demo scene (head collisions, hair–hair,
    its own motion; 40 strands, 8 frames, float64): native and torch runs, each fed its own
    output, stay within 1e-10 m of each other for both materials."""
    built_native("cpu")
    parity = load_script("parity_frames")
    scene = str(parity.ROOT / "datasets" / "scenes" / "default.toml")
    for material in parity.MATERIALS:
        r = parity.compare(scene, strands=40, frames=8, material=material)
        assert r["S"] == 40 and r["frames"] == 8 and len(r["per_frame_dx_m"]) == 8
        assert r["max_dx_m"] <= 1e-10 and r["max_dv_mps"] <= 1e-8, (material, r["max_dx_m"], r["max_dv_mps"])
