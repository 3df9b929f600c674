"""Native banded solver (issue 3): plain vs native CPU vs CUDA, op registration, build machinery.

The native CPU kernel is built once per session (``native`` fixture, cached across runs in
``~/.cache/ams_torch`` or ``$AMS_TORCH_CACHE``); CUDA cases run only where a GPU is visible.
"""
from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import pytest
import torch

from helpers import DEVICES
from native_cases import H, strand_system

from ams_torch.native import build as _native
from ams_torch.solver import op as ops
from ams_torch.solver.reference import banded_matvec, banded_to_dense, solve_banded_dense, solve_banded_plain

REPO = Path(__file__).resolve().parents[1]
CSRC = REPO / "ams_torch" / "native" / "csrc" / "banded"
CSRC_ROOT = CSRC.parent


# ---------------------------------------------------------------------------------------
# input factories (strand_system, shared: tests/native_cases.py)
# ---------------------------------------------------------------------------------------


def stiff_system(strands, n, dtype=torch.float64, device="cpu", seed=0):
    """κ = 1e8 N/m springs on 1e-6 kg particles at dt = 1/60 s: condition number ~1e11."""
    return strand_system(strands, n, mass=1e-6, stiffness=(1e8, 1e8, 1e8), dtype=dtype, device=device, seed=seed)


# ---------------------------------------------------------------------------------------
# fixtures
# ---------------------------------------------------------------------------------------

@pytest.fixture(scope="session")
def native():
    """The native CPU op, built (or loaded from the cache) once per session."""
    if not _native.native_enabled():
        pytest.skip("AMS_TORCH_NATIVE=0: native kernels disabled")
    op = _native.cpu_op()
    status = _native.native_status()["cpu"]
    assert op is not None, f"native CPU solver failed to build: {status['reason']}"
    return op


def _solve(backend: str, blocks, rhs):
    if backend == "plain":
        return solve_banded_plain(blocks, rhs)
    return ops.solve_banded(blocks, rhs)  # native on CPU/CUDA when built


def _require_native(device: str) -> None:
    if device == "cuda":
        _native.cuda_op()
        st = _native.native_status()["cuda"]
        if not st["built"] and st["reason"].startswith("no CUDA toolkit"):
            pytest.skip(st["reason"])  # a GPU but no nvcc: the plain path is all there is
        assert st["built"], f"native CUDA solver failed to build: {st['reason']}"


# ---------------------------------------------------------------------------------------
# accuracy: plain vs native CPU vs CUDA against the dense solve
# ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 1e-4)])
@pytest.mark.parametrize("n", [1, 2, 3, 4, 5, 8, 33, 256])
def test_backends_match_dense(native, device, dtype, tol, n):
    _require_native(device)
    strands = 3 if n == 256 else 19  # 19: not a multiple of the SIMD width
    blocks, rhs = strand_system(strands, n, dtype=dtype, device=device, seed=n)
    ref = solve_banded_dense(blocks.double(), rhs.double())
    results = {b: _solve(b, blocks, rhs) for b in ("plain", "native")}
    for backend, x in results.items():
        assert x.dtype == dtype and x.shape == rhs.shape and x.device == rhs.device
        rel = ((x.double() - ref).norm() / ref.norm()).item()
        assert rel <= tol, f"{backend} {device} N={n} {dtype}: relative error {rel:.3g} > {tol}"
    agree = ((results["native"] - results["plain"]).double().norm() / ref.norm()).item()
    assert agree <= tol


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("n", [16, 64])
def test_backward_stable_on_stiff_strands(native, device, n):
    """SPEC §4: ‖Ax − b‖ / (‖A‖₂ ‖x‖) ≤ 1e-14 in float64 at condition numbers near 1e11."""
    _require_native(device)
    blocks, rhs = stiff_system(8, n, device=device, seed=100 + n)
    dense = banded_to_dense(blocks.cpu())
    cond = torch.linalg.cond(dense[0]).item()
    assert cond > 1e10, f"test system not stiff enough: cond = {cond:.3g}"
    a_norm = torch.linalg.matrix_norm(dense, ord=2)  # (strands,)
    for backend in ("plain", "native"):
        x = _solve(backend, blocks, rhs).cpu()
        resid = (banded_matvec(blocks.cpu(), x) - rhs.cpu()).flatten(1).norm(dim=1)
        berr = resid / (a_norm * x.flatten(1).norm(dim=1))
        assert berr.max().item() <= 1e-14, f"{backend} {device}: backward error {berr.max().item():.3g}"


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_unread_entries_are_ignored(native, device, dtype):
    """NaN in the never-read entries (upper triangle of A[i,i], blocks[i,k] for k > i) changes nothing."""
    _require_native(device)
    clean, rhs = strand_system(11, 7, dtype=dtype, device=device, seed=3)
    junk, _ = strand_system(11, 7, dtype=dtype, device=device, seed=3, junk=True)
    assert junk.isnan().any()
    for backend in ("plain", "native"):
        x_clean = _solve(backend, clean, rhs)
        x_junk = _solve(backend, junk, rhs)
        assert torch.isfinite(x_clean).all()
        assert torch.equal(x_clean, x_junk), backend


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("strands", [1, 3, 8, 9, 13, 40])
def test_batched_equals_one_at_a_time(native, device, strands):
    """Every SIMD lane / thread / CUDA thread computes the same bits as a lone strand."""
    _require_native(device)
    blocks, rhs = strand_system(strands, 6, dtype=torch.float32, device=device, seed=strands)
    x = ops.solve_banded(blocks, rhs)
    for s in range(strands):
        assert torch.equal(x[s], ops.solve_banded(blocks[s], rhs[s])), f"strand {s}"


def test_leading_dims_broadcast_and_promote(native):
    blocks, rhs = strand_system(6, 5, seed=4)
    b = blocks.reshape(2, 3, 5, 4, 3, 3)
    r = rhs.reshape(2, 3, 5, 3)
    x = ops.solve_banded(b, r)
    assert x.shape == (2, 3, 5, 3)
    torch.testing.assert_close(x.reshape(6, 5, 3), solve_banded_plain(blocks, rhs), rtol=1e-12, atol=0)
    shared = ops.solve_banded(blocks[0], rhs)  # one matrix, six right-hand sides
    torch.testing.assert_close(shared, solve_banded_plain(blocks[0].expand(6, -1, -1, -1, -1), rhs),
                               rtol=1e-12, atol=0)
    mixed = ops.solve_banded(blocks.float(), rhs)  # float32 blocks, float64 rhs → float64
    assert mixed.dtype == torch.float64
    with pytest.raises(ValueError):
        ops.solve_banded(blocks, rhs[:, :4])
    empty = ops.solve_banded(blocks[:0], rhs[:0])
    assert empty.shape == (0, 5, 3)


def test_native_cpu_is_used(native):
    status = _native.native_status()
    assert status["cpu"]["built"] and Path(status["cpu"]["library"]).exists()
    assert status["cpu"]["reason"] is None
    if not torch.cuda.is_available():
        assert not status["cuda"]["built"] and status["cuda"]["reason"]
    blocks, rhs = strand_system(4, 9, seed=5)
    x = torch.ops.ams_torch_cpu.solve_banded(blocks, rhs)
    assert torch.equal(x, ops.solve_banded(blocks, rhs))


# ---------------------------------------------------------------------------------------
# op registration: opcheck, gradients, torch.compile
# ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("device", DEVICES)
def test_opcheck(native, device):
    _require_native(device)
    b64, r64 = strand_system(3, 6, device=device, seed=6)
    b32, r32 = strand_system(9, 4, dtype=torch.float32, device=device, seed=7)
    samples = [
        (b64.requires_grad_(), r64.requires_grad_()),
        (b64.detach(), r64.detach().requires_grad_()),
        (b32, r32),
    ]
    for args in samples:
        torch.library.opcheck(torch.ops.ams_torch.solve_banded.default, args)


@pytest.mark.parametrize("device", DEVICES)
def test_gradcheck(native, device):
    _require_native(device)
    blocks, rhs = strand_system(2, 5, stiffness=(30.0, 10.0, 3.0), dt=0.1, device=device, seed=8)
    blocks.requires_grad_()
    rhs.requires_grad_()
    assert torch.autograd.gradcheck(ops.solve_banded, (blocks, rhs), eps=1e-6, atol=1e-8, rtol=1e-6)
    small_b, small_r = blocks.detach()[:1, :4].clone().requires_grad_(), rhs.detach()[:1, :4].clone().requires_grad_()
    assert torch.autograd.gradgradcheck(ops.solve_banded, (small_b, small_r), eps=1e-6, atol=1e-7, rtol=1e-5)


def test_gradient_matches_autograd_of_plain_solver(native):
    """The registered backward (adjoint solve + band projection) equals autograd through the
    plain solver's own arithmetic, including zero gradient on never-read entries."""
    blocks, rhs = strand_system(5, 9, seed=9)
    weight = torch.randn(5, 9, 3, dtype=torch.float64)
    grads = []
    for fn in (ops.solve_banded, solve_banded_plain):
        b = blocks.clone().requires_grad_()
        r = rhs.clone().requires_grad_()
        (fn(b, r) * weight).sum().backward()
        grads.append((b.grad, r.grad))
    torch.testing.assert_close(grads[0][0], grads[1][0], rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(grads[0][1], grads[1][1], rtol=1e-9, atol=1e-12)
    gb = grads[0][0]
    assert torch.count_nonzero(gb[:, :, 0].triu(1)) == 0
    assert all(torch.count_nonzero(gb[:, :k, k]) == 0 for k in range(1, 4))


def test_torch_compile_fullgraph(native):
    blocks, rhs = strand_system(4, 6, dtype=torch.float32, seed=10)

    def step(b, r):
        return 2.0 * ops.solve_banded(b, r) + r

    torch._dynamo.reset()
    compiled = torch.compile(step, fullgraph=True, dynamic=False)
    torch.testing.assert_close(compiled(blocks, rhs), step(blocks, rhs), rtol=1e-6, atol=1e-7)


# ---------------------------------------------------------------------------------------
# fallback, CUDA compile, build lock
# ---------------------------------------------------------------------------------------

_FALLBACK_SCRIPT = textwrap.dedent(
    """
    import json, os, sys, warnings
    sys.path.insert(0, {tests!r})
    import torch
    from native_cases import strand_system
    from ams_torch.native import build as _native
    from ams_torch.solver import op as ops
    from ams_torch.solver.reference import solve_banded_plain

    def scenario(env):
        os.environ.update(env)
        _native._state = {{k: _native._fresh_state() for k in _native._BACKENDS}}
        _native._ops.clear()
        _native._warned = False
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            same = True
            for dtype in (torch.float64, torch.float32):
                blocks, rhs = strand_system(7, 10, dtype=dtype, seed=11)
                same &= torch.equal(ops.solve_banded(blocks, rhs), solve_banded_plain(blocks, rhs))
        ours = [w for w in caught if issubclass(w.category, _native.NativeBuildWarning)]
        return dict(same=bool(same), warnings=len(ours), reason=_native.native_status()["cpu"]["reason"],
                    built=_native.native_status()["cpu"]["built"])

    out = dict(disabled=scenario({{"AMS_TORCH_NATIVE": "0"}}),
               no_compiler=scenario({{"AMS_TORCH_NATIVE": "1", "CXX": "/nonexistent/c++"}}))
    print(json.dumps(out))
    """
)


def test_fallback_without_native(tmp_path):
    """AMS_TORCH_NATIVE=0, and no compiler: plain results bit for bit, exactly one warning each."""
    env = dict(os.environ, AMS_TORCH_CACHE=str(tmp_path / "cache"), PYTHONPATH=str(REPO))
    script = _FALLBACK_SCRIPT.format(tests=str(REPO / "tests"))
    proc = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    for name, hint in (("disabled", "AMS_TORCH_NATIVE"), ("no_compiler", "compiler")):
        res = out[name]
        assert res["same"], name
        assert res["warnings"] == 1, (name, res)
        assert not res["built"] and hint in res["reason"], (name, res)
    assert not (tmp_path / "cache").exists() or not any((tmp_path / "cache").iterdir())


CUDA_SOURCES = sorted(CSRC_ROOT.glob("*/*.cu"))
CUDA_BINDINGS = sorted(CSRC_ROOT.glob("*/*_cuda_binding.cpp"))
INCLUDE_DIRS = [f"-I{CSRC_ROOT}"]


def _local_includes(path: Path, seen=None) -> list:
    """#include lines of a source and, recursively, of the csrc/ headers it includes."""
    seen = set() if seen is None else seen
    out = []
    for line in path.read_text().splitlines():
        if not line.startswith("#include"):
            continue
        out.append(line)
        h = CSRC_ROOT / line.split()[1].strip('"<>')
        if h.is_file() and h not in seen:
            seen.add(h)
            out += _local_includes(h, seen)
    return out


@pytest.mark.parametrize("src", CUDA_SOURCES, ids=lambda p: p.name)
def test_nvcc_compiles_cuda_kernel(tmp_path, src):
    """Every CUDA kernel file is plain CUDA C++ (no torch headers): CI compiles each with nvcc."""
    nvcc = shutil.which("nvcc")
    if nvcc is None:
        pytest.skip("nvcc not found")
    includes = _local_includes(src)
    assert not [i for i in includes if "torch" in i or "ATen" in i or "c10" in i], includes
    obj = tmp_path / (src.stem + ".o")
    cmd = [nvcc, "-std=c++17", "-O3", "-c", str(src), "-o", str(obj)] + INCLUDE_DIRS + [
        "-gencode", "arch=compute_80,code=sm_80", "-gencode", "arch=compute_90,code=sm_90"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    assert obj.stat().st_size > 0


def _cuda_include_dir():
    from torch.utils import cpp_extension

    nvcc = shutil.which("nvcc")
    roots = [os.environ.get("CUDA_HOME"), os.environ.get("CUDA_PATH"), cpp_extension.CUDA_HOME, "/usr/local/cuda"]
    if nvcc:
        roots.append(str(Path(os.path.realpath(nvcc)).parents[1]))
    for root in roots:
        if root and (Path(root) / "include" / "cuda_runtime_api.h").exists():
            return Path(root) / "include"
    return None


@pytest.mark.parametrize("binding", CUDA_BINDINGS, ids=lambda p: p.name)
def test_cuda_binding_compiles_against_torch_headers(tmp_path, binding):
    """The torch binding of the CUDA kernel is only built with a CUDA torch; CI checks that it
    compiles (syntax and types) against this torch's headers and the CUDA toolkit's."""
    cxx = shutil.which(os.environ.get("CXX", "c++"))
    cuda_inc = _cuda_include_dir()
    if cxx is None or cuda_inc is None:
        pytest.skip("needs a C++ compiler and the CUDA toolkit headers")
    from torch.utils import cpp_extension

    includes = cpp_extension.include_paths()
    if not any((Path(p) / "c10" / "cuda" / "impl" / "cuda_cmake_macros.h").exists() for p in includes):
        # CPU wheels ship c10/cuda headers but not this generated one (it only sets build macros).
        fake = tmp_path / "c10" / "cuda" / "impl"
        fake.mkdir(parents=True)
        (fake / "cuda_cmake_macros.h").write_text("#pragma once\n")
        includes = [str(tmp_path)] + includes
    cmd = [cxx, "-std=c++20", "-fsyntax-only", str(binding)] + INCLUDE_DIRS + [f"-I{cuda_inc}"] + [
        f"-I{p}" for p in includes]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-4000:]


def _write_lock(path: Path, pid: int, age_s: float = 0.0) -> None:
    path.write_text(json.dumps({"pid": pid, "host": socket.gethostname(), "time": time.time()}))
    if age_s:
        t = time.time() - age_s
        os.utime(path, (t, t))


def test_lock_of_killed_builder_is_broken(tmp_path):
    """A builder killed while holding the lock (ours and torch's FileBaton) does not block the next."""
    holder = textwrap.dedent(
        f"""
        import sys, time
        from pathlib import Path
        from ams_torch.native.build import build_lock
        d = Path({str(tmp_path)!r})
        with build_lock(d):
            (d / "lock").write_text("")  # torch's FileBaton, as cpp_extension.load leaves it
            print("held", flush=True)
            time.sleep(120)
        """
    )
    proc = subprocess.Popen([sys.executable, "-c", holder], stdout=subprocess.PIPE, text=True,
                            env=dict(os.environ, PYTHONPATH=str(REPO)))
    try:
        assert proc.stdout.readline().strip() == "held"
        assert (tmp_path / _native.LOCK_NAME).exists() and (tmp_path / "lock").exists()
        assert not _native.lock_is_stale(tmp_path / _native.LOCK_NAME, 600.0)  # live holder
    finally:
        proc.kill()
        proc.wait()
    assert _native.lock_is_stale(tmp_path / _native.LOCK_NAME, 600.0)
    t0 = time.monotonic()
    with _native.build_lock(tmp_path, stale_after_s=600.0):
        assert not (tmp_path / "lock").exists()
        owner = json.loads((tmp_path / _native.LOCK_NAME).read_text())
        assert owner["pid"] == os.getpid()
    assert time.monotonic() - t0 < 5.0
    assert not (tmp_path / _native.LOCK_NAME).exists()


def test_old_lock_is_broken_and_live_lock_is_waited_for(tmp_path):
    lock = tmp_path / _native.LOCK_NAME
    _write_lock(lock, os.getpid(), age_s=3600.0)  # live owner, but an hour old
    t0 = time.monotonic()
    with _native.build_lock(tmp_path, stale_after_s=60.0):
        pass
    assert time.monotonic() - t0 < 2.0
    _write_lock(lock, os.getpid())  # live and fresh: wait until it is older than the limit
    t0 = time.monotonic()
    with _native.build_lock(tmp_path, stale_after_s=1.0, poll_s=0.05):
        waited = time.monotonic() - t0
    assert 0.8 <= waited < 10.0


def test_stale_torch_filebaton_does_not_hang_load(tmp_path):
    """torch's own FileBaton `lock`, left by a killed cpp_extension.load, is cleared under our lock:
    the next load completes instead of waiting forever."""
    from torch.utils import cpp_extension

    if not cpp_extension.is_ninja_available() or shutil.which(os.environ.get("CXX", "c++")) is None:
        pytest.skip("needs ninja and a C++ compiler")
    src = tmp_path / "probe.cpp"
    src.write_text("extern \"C\" int ams_lock_probe() { return 42; }\n")
    build = tmp_path / "build"
    build.mkdir()
    (build / "lock").write_text("")  # what a killed build leaves behind
    result = {}

    def run():
        with _native.build_lock(build):
            result["path"] = cpp_extension.load(
                name="ams_lock_probe", sources=[str(src)], build_directory=str(build),
                is_python_module=False, verbose=False)

    th = threading.Thread(target=run, daemon=True)
    th.start()
    th.join(timeout=90)
    assert not th.is_alive(), "cpp_extension.load hung on a stale lock file"
    assert Path(result["path"]).exists()
