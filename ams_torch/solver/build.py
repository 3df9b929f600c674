"""Lazy build and loading of the native banded-solver kernels (CPU and CUDA).

Nothing is compiled at import time. The first solve on a device asks for that device's
backend (:func:`cpu_op`, :func:`cuda_op`); it is compiled once with
``torch.utils.cpp_extension.load`` into a cache directory, loaded, and reused by every later
call and process. When a backend cannot be had (native code disabled, no C++ compiler, no
ninja, no CUDA toolkit, a compile error) the caller gets ``None``, falls back to the plain
torch solver, and one :class:`NativeBuildWarning` is issued per process.

Environment:
    AMS_TORCH_NATIVE=0           use the plain-torch solver only (never build).
    AMS_TORCH_CACHE=<dir>        cache root (default ``~/.cache/ams_torch``). Each build goes to
                                 ``<root>/<backend>-torch<ver>-cuda<ver>-<hash>``, the hash
                                 covering torch/CUDA/Python versions, compiler, CPU capability,
                                 flags and the sources, so a changed source or machine rebuilds.
    AMS_TORCH_BUILD_LOCK_STALE_S seconds after which a build lock is considered abandoned
                                 (default 1200).
    MAX_JOBS, TORCH_CUDA_ARCH_LIST are honoured when set; otherwise MAX_JOBS is capped at
    min(cpu_count, 4) and the architecture list is taken from the visible GPUs.

Concurrency: builders of one cache directory serialise on ``ams_build.lock`` in it (pid,
host, time). A lock whose owner is a dead process on this host, or that is older than the
stale limit, is removed, as is torch's own FileBaton ``lock`` file (which a killed build leaves
behind and which would otherwise make every later build wait forever).

:func:`native_status` reports which backends were built and why not.
"""
from __future__ import annotations

import contextlib
import copy
import hashlib
import json
import os
import platform
import shutil
import socket
import subprocess
import sys
import threading
import time
import warnings
from pathlib import Path
from typing import Callable, Iterator, Optional

import torch

__all__ = ["native_status", "native_enabled", "cpu_op", "cuda_op", "NativeBuildWarning"]

CSRC_ROOT = Path(__file__).resolve().parent / "csrc"
CSRC = CSRC_ROOT / "banded"
ENV_ENABLE = "AMS_TORCH_NATIVE"
ENV_CACHE = "AMS_TORCH_CACHE"
ENV_LOCK_STALE = "AMS_TORCH_BUILD_LOCK_STALE_S"
DEFAULT_LOCK_STALE_S = 1200.0
LOCK_NAME = "ams_build.lock"   # ours: JSON {"pid", "host", "time"}
TORCH_LOCK_NAME = "lock"       # torch.utils.file_baton.FileBaton inside the build directory
MARKER_NAME = "build.json"     # written after a successful build: its inputs and the library

# backend -> (extension name, sources compiled, headers they include (paths relative to csrc/),
#             torch.ops namespace, device type). Every csrc/ folder is on the include path.
# One backend per op group and device, so that a group that fails to build leaves the others.
_BACKENDS = {
    "cpu": ("ams_torch_banded_cpu", ("banded/banded_cpu.cpp",),
            ("banded/banded_cholesky.h", "banded/banded_simd.h", "banded/interleave.h", "banded/thread_scratch.h"),
            "ams_torch_cpu", "cpu"),
    "cuda": (
        "ams_torch_banded_cuda",
        ("banded/banded_cuda_binding.cpp", "banded/banded_cuda.cu"),
        ("banded/banded_cholesky.h", "banded/banded_cuda.h"),
        "ams_torch_cuda",
        "cuda",
    ),
    "grid_cpu": ("ams_torch_grid_cpu", ("grid/grid_cpu.cpp",), ("grid/grid.h", "grid/grid_simd.h"),
                 "ams_torch_grid_cpu", "cpu"),
    "grid_cuda": (
        "ams_torch_grid_cuda",
        ("grid/grid_cuda_binding.cpp", "grid/grid_cuda.cu"),
        ("grid/grid.h", "grid/grid_cuda.h"),
        "ams_torch_grid_cuda",
        "cuda",
    ),
    "frame_cpu": (
        "ams_torch_frame_cpu",
        ("frame/frame_cpu.cpp",),
        ("banded/banded_cholesky.h", "banded/banded_simd.h", "banded/interleave.h", "banded/thread_scratch.h",
         "frame/lanes.h", "frame/ftl.h", "frame/finish.h", "frame/frame.h", "frame/frame_binding.h"),
        "ams_torch_frame_cpu",
        "cpu",
    ),
    "frame_cuda": (
        "ams_torch_frame_cuda",
        ("frame/frame_cuda_binding.cpp", "frame/frame_cuda.cu"),
        ("banded/banded_cholesky.h", "frame/lanes.h", "frame/ftl.h", "frame/finish.h", "frame/frame.h",
         "frame/frame_binding.h", "frame/frame_cuda.h", "frame/transpose_cuda.cuh"),
        "ams_torch_frame_cuda",
        "cuda",
    ),
    "collide_cpu": (
        "ams_torch_collide_cpu",
        ("collide/collide_cpu.cpp",),
        ("banded/banded_cholesky.h", "banded/banded_simd.h", "banded/interleave.h", "banded/thread_scratch.h",
         "frame/lanes.h", "frame/ftl.h", "collide/collide.h", "collide/collide_binding.h"),
        "ams_torch_collide_cpu",
        "cpu",
    ),
    "collide_cuda": (
        "ams_torch_collide_cuda",
        ("collide/collide_cuda_binding.cpp", "collide/collide_cuda.cu"),
        ("banded/banded_cholesky.h", "frame/lanes.h", "frame/ftl.h", "frame/transpose_cuda.cuh", "collide/collide.h",
         "collide/collide_binding.h", "collide/collide_cuda.h"),
        "ams_torch_collide_cuda",
        "cuda",
    ),
}


class NativeBuildWarning(RuntimeWarning):
    """The native solver could not be built or loaded; the plain-torch solver is used."""


_lock = threading.RLock()
_warned = False


def _fresh_state() -> dict:
    return {"attempted": False, "built": False, "reason": None, "library": None, "build_dir": None,
            "build_seconds": None, "flags": None}


_state = {kind: _fresh_state() for kind in _BACKENDS}
_ops: dict = {}


def native_enabled() -> bool:
    """False when the environment variable ``AMS_TORCH_NATIVE`` is 0/false/no/off."""
    return os.environ.get(ENV_ENABLE, "1").strip().lower() not in ("0", "false", "no", "off")


def cache_root() -> Path:
    """Root of the build cache: ``$AMS_TORCH_CACHE`` or ``~/.cache/ams_torch``."""
    env = os.environ.get(ENV_CACHE)
    return Path(env).expanduser() if env else Path.home() / ".cache" / "ams_torch"


def native_ops(kind: str):
    """The ``torch.ops`` namespace of backend ``kind`` (a key of ``_BACKENDS``), building and
    loading its library on first call; None when it cannot be had (one warning per process)."""
    return _get(kind)


def cpu_op() -> Optional[Callable]:
    """``torch.ops.ams_torch_cpu.solve_banded`` (building it on first call), or None."""
    ns = _get("cpu")
    return None if ns is None else ns.solve_banded


def cuda_op() -> Optional[Callable]:
    """``torch.ops.ams_torch_cuda.solve_banded`` (building it on first call), or None."""
    ns = _get("cuda")
    return None if ns is None else ns.solve_banded


def native_status(build: bool = False) -> dict:
    """Which native backends are built, and why not.

    Args:
        build: first try to build every backend this process could use (CPU always; CUDA when
            a GPU is visible), instead of only reporting what earlier solves did.
    Returns:
        ``{"enabled": bool, "cache_dir": str, "cpu": {...}, "cuda": {...}}``; each backend
        dict has ``built`` (bool), ``reason`` (why not, or None), ``attempted`` (a build or
        load was tried in this process), ``library`` (path of the loaded .so), ``build_dir``,
        ``build_seconds`` (compile + load time, ~0 when cached) and ``flags``.
    """
    if build:
        for kind, spec in _BACKENDS.items():
            if spec[4] == "cpu" or torch.cuda.is_available():
                _get(kind)
    with _lock:
        out = {"enabled": native_enabled(), "cache_dir": str(cache_root())}
        for kind in _BACKENDS:
            st = copy.deepcopy(_state[kind])
            if not st["attempted"]:
                st["reason"] = _static_reason(kind) or "not built yet: built on first use"
            out[kind] = st
        return out


# ---------------------------------------------------------------------------------------
# build and load
# ---------------------------------------------------------------------------------------

def _get(kind: str) -> Optional[Callable]:
    op = _ops.get(kind)
    if op is not None:
        return op
    with _lock:
        st = _state[kind]
        if not st["attempted"]:
            t0 = time.perf_counter()
            try:
                _ops[kind] = _build_and_load(kind, st)
                st["built"] = True
            except _Unavailable as e:
                st["reason"] = str(e)
            except Exception as e:  # a compile or load error: report it, never crash the solve
                st["reason"] = f"build failed: {type(e).__name__}: {_tail(str(e))}"
            # (an interrupt, e.g. Ctrl-C during the build, leaves the backend untried: the next
            # call builds again)
            st["attempted"] = True
            st["build_seconds"] = round(time.perf_counter() - t0, 3)
            if not st["built"]:
                _warn_once(kind, st["reason"])
        return _ops.get(kind)


class _Unavailable(Exception):
    """The backend cannot be built here (the message says why)."""


def _warn_once(kind: str, reason: str) -> None:
    global _warned
    if _warned:
        return
    _warned = True
    warnings.warn(
        f"ams_torch: native kernels ({kind}) unavailable ({reason}); using the plain-torch "
        "path, which is much slower. ams_torch.native_status() has the details; set "
        f"{ENV_ENABLE}=0 to choose the plain solver explicitly.",
        NativeBuildWarning,
        stacklevel=4,
    )


def _static_reason(kind: str) -> Optional[str]:
    """Why ``kind`` cannot be built, from facts known without compiling, or None."""
    if not native_enabled():
        return f"disabled by {ENV_ENABLE}={os.environ.get(ENV_ENABLE)}"
    if _BACKENDS[kind][4] == "cuda":
        if torch.version.cuda is None:
            return "this torch was built without CUDA"
        if not torch.cuda.is_available():
            return "no CUDA device is available"
        from torch.utils import cpp_extension

        if cpp_extension.CUDA_HOME is None or not Path(cpp_extension.CUDA_HOME, "bin", "nvcc").exists():
            return "no CUDA toolkit (nvcc) found; set CUDA_HOME"
    cxx = os.environ.get("CXX", "c++")
    if shutil.which(cxx) is None:
        return f"no C++ compiler ({cxx!r}) on PATH"
    return None


def _build_and_load(kind: str, st: dict) -> Callable:
    reason = _static_reason(kind)
    if reason:
        raise _Unavailable(reason)
    name, sources, headers, namespace, device = _BACKENDS[kind]
    cflags, cuda_flags, ldflags, key_parts = _build_config(device)
    digest = hashlib.sha256()
    digest.update(json.dumps(key_parts, sort_keys=True).encode())
    for fname in sources + headers:
        digest.update(fname.encode())
        digest.update((CSRC_ROOT / fname).read_bytes())
    tag = f"{kind}-torch{torch.__version__}-cuda{torch.version.cuda or 'none'}-{digest.hexdigest()[:16]}"
    build_dir = cache_root() / tag.replace("+", "_")
    st["build_dir"] = str(build_dir)
    st["flags"] = cflags + cuda_flags
    build_dir.mkdir(parents=True, exist_ok=True)

    library = _cached_library(build_dir)
    if library is None:
        with build_lock(build_dir):
            library = _cached_library(build_dir)  # another process may have finished meanwhile
            if library is None:
                from torch.utils import cpp_extension

                if not cpp_extension.is_ninja_available():
                    raise _Unavailable("ninja is not installed (pip install ninja)")
                with _build_env(device):
                    path = cpp_extension.load(
                        name=name,
                        sources=[str(CSRC_ROOT / s) for s in sources],
                        extra_cflags=cflags,
                        extra_cuda_cflags=cuda_flags,
                        extra_ldflags=ldflags,
                        extra_include_paths=[str(d) for d in sorted(CSRC_ROOT.iterdir()) if d.is_dir()],
                        build_directory=str(build_dir),
                        is_python_module=False,
                        verbose=False,
                    )
                library = Path(path)
                (build_dir / MARKER_NAME).write_text(json.dumps({"library": library.name, "key": key_parts}))
    torch.ops.load_library(str(library))
    st["library"] = str(library)
    return getattr(torch.ops, namespace)


def _cached_library(build_dir: Path) -> Optional[Path]:
    marker = build_dir / MARKER_NAME
    try:
        library = build_dir / json.loads(marker.read_text())["library"]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return library if library.exists() else None


def _build_config(kind: str):
    """(C++ flags, nvcc flags, linker flags, cache-key facts) for ``kind``."""
    cflags = ["-O3", "-fno-math-errno", "-Wno-psabi"]
    ldflags: list = []
    capability = torch.backends.cpu.get_cpu_capability()
    if kind == "cpu":
        # at::parallel_for is inline OpenMP code when torch uses the OpenMP backend: without
        # -fopenmp it would run serially. The soname libgomp.so.1 resolves to torch's copy.
        if "OpenMP" in torch.__config__.parallel_info() and sys.platform.startswith("linux"):
            cflags.append("-fopenmp")
            ldflags.append("-fopenmp")
        # SIMD across strands: AVX2+FMA where this CPU has them (the capability is in the key,
        # so a cache shared with an older CPU builds its own copy rather than crash).
        if platform.machine().lower() in ("x86_64", "amd64") and capability in ("AVX2", "AVX512"):
            cflags += ["-mavx2", "-mfma"]
    cuda_flags: list = []
    key = {
        "torch": torch.__version__,
        "torch_cuda": torch.version.cuda,
        "python": sys.implementation.cache_tag,
        "machine": platform.machine(),
        "cpu_capability": capability,
        "cxx": _tool_version([os.environ.get("CXX", "c++"), "--version"]),
        "cflags": cflags,
        "ldflags": ldflags,
    }
    if kind == "cuda":
        cuda_flags = ["-O3"]  # torch adds the C++ standard and the -gencode list
        from torch.utils import cpp_extension

        key["nvcc"] = _tool_version([str(Path(cpp_extension.CUDA_HOME, "bin", "nvcc")), "--version"])
        key["arch"] = _cuda_arch_list()
        key["cuda_flags"] = cuda_flags
    return cflags, cuda_flags, ldflags, key


def _tool_version(cmd: list) -> str:
    try:
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=30).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    lines = out.splitlines()
    return (lines[0] + " | " + lines[-1]) if lines else "unknown"


def _cuda_arch_list() -> str:
    env = os.environ.get("TORCH_CUDA_ARCH_LIST")
    if env:
        return env
    caps = sorted({torch.cuda.get_device_capability(i) for i in range(torch.cuda.device_count())})
    return ";".join(f"{major}.{minor}" for major, minor in caps)


@contextlib.contextmanager
def _build_env(kind: str) -> Iterator[None]:
    saved = {k: os.environ.get(k) for k in ("MAX_JOBS", "TORCH_CUDA_ARCH_LIST")}
    try:
        if not saved["MAX_JOBS"]:
            os.environ["MAX_JOBS"] = str(max(1, min(os.cpu_count() or 1, 4)))
        if kind == "cuda" and not saved["TORCH_CUDA_ARCH_LIST"]:
            os.environ["TORCH_CUDA_ARCH_LIST"] = _cuda_arch_list()
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _tail(text: str, lines: int = 12) -> str:
    return "\n".join(text.strip().splitlines()[-lines:])


# ---------------------------------------------------------------------------------------
# build lock
# ---------------------------------------------------------------------------------------

def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    except OSError:
        return False
    try:  # a zombie (killed, not yet reaped) is dead for our purpose
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return True


def lock_is_stale(path: Path, stale_after_s: float) -> bool:
    """True when the build lock ``path`` is abandoned: its owner is a dead process on this host,
    or it is older than ``stale_after_s`` seconds, or it is unreadable and older than 5 s."""
    try:
        age = time.time() - path.stat().st_mtime
    except FileNotFoundError:
        return False
    if age > stale_after_s:
        return True
    try:
        owner = json.loads(path.read_text())
        pid, host = int(owner["pid"]), str(owner["host"])
    except (OSError, ValueError, KeyError, TypeError):
        return age > 5.0  # being written right now, or garbage
    return host == socket.gethostname() and not _pid_alive(pid)


@contextlib.contextmanager
def build_lock(build_dir: Path, stale_after_s: Optional[float] = None, poll_s: float = 0.2) -> Iterator[None]:
    """Hold the build lock of ``build_dir`` (waits for a live holder; breaks a stale one).

    While held, any torch FileBaton ``lock`` in ``build_dir`` is a leftover of a killed build
    (every builder of this directory takes this lock first) and is removed, so that
    ``cpp_extension.load`` does not wait on it forever. Waiting is bounded: a lock older than
    ``stale_after_s`` (default ``$AMS_TORCH_BUILD_LOCK_STALE_S`` or 1200 s) is broken.
    """
    if stale_after_s is None:
        stale_after_s = float(os.environ.get(ENV_LOCK_STALE, DEFAULT_LOCK_STALE_S))
    build_dir = Path(build_dir)
    build_dir.mkdir(parents=True, exist_ok=True)
    path = build_dir / LOCK_NAME
    while True:
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            if lock_is_stale(path, stale_after_s):
                with contextlib.suppress(FileNotFoundError):
                    path.unlink()
            else:
                time.sleep(poll_s)
            continue
        with os.fdopen(fd, "w") as f:
            json.dump({"pid": os.getpid(), "host": socket.gethostname(), "time": time.time()}, f)
        break
    try:
        with contextlib.suppress(FileNotFoundError):
            (build_dir / TORCH_LOCK_NAME).unlink()
        yield
    finally:
        with contextlib.suppress(FileNotFoundError):
            path.unlink()
