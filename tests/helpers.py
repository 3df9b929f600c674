"""Plain helpers the test modules share (functions and constants, not fixtures: those are in
conftest.py). A module, not a test module, so that no test module imports another or conftest."""
import os
from pathlib import Path

import pytest
import torch

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


def built_native(kind: str):
    """The torch.ops namespace of native backend ``kind`` ("cpu", "cuda_emu", "selftest_cuda_emu", ...),
    built or loaded from the cache: skips when AMS_TORCH_NATIVE=0, fails naming the build error
    when it did not build (a CPU build is required wherever the tests run)."""
    from ams_torch.native import build

    if not build.native_enabled():
        pytest.skip("AMS_TORCH_NATIVE=0: native kernels disabled")
    ns = build.native_ops(kind)
    assert ns is not None, f"native {kind} kernels failed to build: {build.native_status()[kind]['reason']}"
    return ns


def rel(a: torch.Tensor, b: torch.Tensor) -> float:
    """‖a − b‖ / ‖b‖ in float64 on the CPU (‖a − b‖ when b is 0): the parity tests' error."""
    a, b = a.double().cpu(), b.double().cpu()
    den = b.norm().item()
    return (a - b).norm().item() / den if den > 0 else (a - b).norm().item()


def sha(path) -> str:
    """The SHA-256 of a file's bytes (hex)."""
    import hashlib

    with open(path, "rb") as f:
        return hashlib.sha256(f.read()).hexdigest()


#: the repository's root folder
REPO = Path(__file__).resolve().parents[1]


def run_cli(args, fsize=None, timeout=180, script=None):
    """``python -m ams_torch ARGS`` (or ``python -c SCRIPT``) in a child process, with a file size
    limit of ``fsize`` bytes (``ulimit -f``; Python ignores SIGXFSZ, so writes fail with EFBIG)."""
    import resource
    import subprocess
    import sys

    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))

    def limit():
        resource.setrlimit(resource.RLIMIT_FSIZE, (fsize, fsize))

    cmd = [sys.executable, "-c", script] if script else [sys.executable, "-m", "ams_torch", *map(str, args)]
    return subprocess.run(cmd, preexec_fn=limit if fsize else None, capture_output=True, text=True, env=env,
                          timeout=timeout, cwd=str(REPO))


def one_error(p) -> str:
    """The child failed cleanly: exit 2, no signal, no traceback, one ``error:`` line on stderr."""
    lines = [line for line in p.stderr.splitlines() if line.strip()]
    assert p.returncode == 2, (p.returncode, p.stderr[-3000:])
    assert "Traceback" not in p.stderr and "Exception ignored" not in p.stderr, p.stderr[-3000:]
    errors = [line for line in lines if line.startswith("error:")]
    assert len(errors) == 1, lines[-10:]
    return errors[0]


def load_script(name: str):
    """Import ``scripts/<name>.py`` as a module (the scripts are not a package)."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "scripts" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod
