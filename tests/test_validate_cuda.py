"""The first-GPU-run script, dry: ``scripts/validate_cuda.sh OUT --dry-run`` runs every step's Python on
the CPU at toy sizes (the emulated CUDA backends, the eager stand-in of the graph capture, bench_frame
on 40 strands), so that the run on a GPU does not fail on the script itself."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_validate_cuda_dry_run(tmp_path):
    out = tmp_path / "validate"
    env = dict(os.environ, PYTHON=sys.executable)
    proc = subprocess.run([str(REPO / "scripts" / "validate_cuda.sh"), str(out), "--dry-run"], env=env,
                          capture_output=True, text=True, timeout=900)
    summary = json.loads((out / "summary.json").read_text())
    steps = summary["steps"]
    assert proc.returncode == 0, (proc.stdout[-3000:], {k: v.get("detail") for k, v in steps.items()})
    assert summary["meta"]["dry"] is True
    want = ["preflight", "build", "tests", "compile", "parity", "sizes", "graph", "ptxas", "bench", "sanitizer"]
    assert list(steps) == want
    for name in want[:-1]:
        assert steps[name]["status"] in ("pass", "skip"), (name, steps[name])
    assert steps["sanitizer"]["status"] == "skip"
    assert steps["build"]["backends"]["cuda_emu"]["built"]  # the emulated CUDA backends stand in
    assert steps["graph"]["results"]["20"]["captures"] == 1
    assert (out / "benchmarks" / "cuda_dry.md").exists() and (out / "benchmarks" / "cuda_dry.json").exists()
    md = (out / "summary.md").read_text()
    assert "| parity | **pass** |" in md and "dry run" in md


def test_validate_cuda_reports_a_failing_step_and_goes_on(tmp_path):
    """A step that fails (here: preflight without the --dry-run's allowance for no GPU) is reported,
    and the other steps still run; the exit status says it failed."""
    out = tmp_path / "validate"
    proc = subprocess.run([sys.executable, str(REPO / "scripts" / "validate_cuda.py"), str(out), "--only",
                           "preflight", "ptxas", "--budget-s", "120"], capture_output=True, text=True, timeout=600,
                          env=dict(os.environ, AMS_TORCH_CACHE=str(tmp_path / "cache")))
    steps = json.loads((out / "summary.json").read_text())["steps"]
    import torch

    if torch.cuda.is_available():
        assert steps["preflight"]["status"] == "pass"
    else:
        assert proc.returncode == 1 and steps["preflight"]["status"] == "fail"
        assert "no CUDA device visible" in steps["preflight"]["detail"]
        assert steps["ptxas"]["status"] == "skip" and "no CUDA device" in steps["ptxas"]["detail"]
    assert (out / "steps" / "preflight.log").exists()
