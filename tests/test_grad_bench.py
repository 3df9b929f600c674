"""scripts/bench_grad.py runs (toy sizes; the full run is by hand on a quiet machine:
docs/benchmarks/grad.md)."""
import json

from helpers import load_script


def test_bench_grad_smoke(tmp_path):
    """In-process, 16 strands: both paths timed (forward without and with grad, backward, per
    stage), the memory rows of a 4-frame rollout without checkpointing, with segments, and with segments and
    frame checkpoints (fresh processes),
    the JSON and the markdown written."""
    bench = load_script("bench_grad")
    out = tmp_path / "grad"
    assert bench.main(["--quick", "--scenes", "dynamics", "--threads", "1", "--reps", "1", "--out", str(out)]) == 0
    saved = json.loads((tmp_path / "grad.json").read_text())
    records, memory = saved["records"], saved["memory"]
    assert {r["path"] for r in records} == {"native", "torch"}
    for r in records:
        assert r["S"] == 16 and r["N"] == 32
        assert all(r[k] > 0 for k in ("forward_nograd_ms", "forward_ms", "backward_ms", "dynamics_ms"))
    assert [(m["checkpoint_every"], m["checkpoint_frames"]) for m in memory] == [(0, False), (2, False), (2, True)]
    assert all(m["peak_rise_MiB"] == m["peak_rise_MiB"] and m["state_MiB"] > 0 for m in memory), memory
    md = (tmp_path / "grad.md").read_text()
    assert "| dynamics | 16 | native |" in md and "## Memory" in md and saved["meta"]["machine"] in md
