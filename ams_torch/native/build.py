"""Lazy build and loading of the native kernels (CPU and CUDA, and the CUDA emulation of the tests).

Nothing is compiled at import time. The first use of a backend (:func:`native_ops`, :func:`cpu_op`,
:func:`cuda_op`; the simulator asks for every backend its configuration needs when it is
constructed: :func:`ensure`) compiles it once with ``torch.utils.cpp_extension.load`` into a cache
directory, loads it, runs its smoke test (:mod:`ams_torch.native.probes`: one tiny call compared
with the torch definition) and reuses it in every later call and process. When a backend cannot
be had (native code disabled, no C++ compiler, no ninja, no CUDA toolkit, a compile error, a
failed smoke test) the caller gets ``None`` and falls back to the torch definition, and one
:class:`NativeBuildWarning` is issued per backend kind and process, naming the kind and why.

Backends (``_BACKENDS``): one library per device, ``cpu`` (every op group's CPU kernels:
the banded solve, ``frame``, ``frame_adjoint``, ``collide``, ``grid``; :data:`GROUPS`) and ``cuda``
(their CUDA kernels), each registering its functions under one ``torch.ops`` namespace
(``ams_torch_cpu``, ``ams_torch_cuda``); ``cuda_emu``, the CUDA library's sources built as host
code (:mod:`ams_torch.native.emulation`); and the emulator's test-only self-test library
(``selftest_cuda``, ``selftest_cuda_emu``). Every C++ source is compiled with the same flags, one
floating-point contraction setting (``-ffp-contract=off``) included.

Environment:
    AMS_TORCH_NATIVE=0           use the torch definitions only (never build).
    AMS_TORCH_CACHE=<dir>        cache root (default ``~/.cache/ams_torch``). Each build goes to
                                 ``<root>/<backend>-torch<ver>-cuda<ver>-<hash>``, the hash
                                 covering torch/CUDA/Python versions, compiler, CPU capability,
                                 flags, architectures and the sources, so a changed source or machine rebuilds.
    AMS_TORCH_BUILD_LOCK_STALE_S seconds after which a build lock is considered abandoned
                                 (default 1200).
    MAX_JOBS is honoured when set (otherwise min(cpu_count, 4)). TORCH_CUDA_ARCH_LIST: see
    :mod:`ams_torch.native.cuda_arch` (unset: the visible devices' architectures, clamped to what
    torch and nvcc support, the newest also as PTX; set: checked against ``nvcc --list-gpu-arch``
    and completed with the devices' architectures).

Cache integrity: ``build.json`` records the library's size and SHA-256; a library that does not
match (truncated, emptied, replaced) is never loaded: it is deleted and rebuilt (relinked from the
cached objects when those are intact).

Concurrency: builders of one cache directory serialise on ``ams_build.lock`` in it (pid,
host, time). A lock whose owner is a dead process on this host, or that is older than the
stale limit, is removed, as is torch's own FileBaton ``lock`` file (which a killed build leaves
behind and which would otherwise make every later build wait forever).

:func:`native_status` reports, for every backend kind, whether it is built, why not, and its flags.
"""
from __future__ import annotations

import contextlib
import copy
import hashlib
import json
import os
import platform
import re
import shutil
import subprocess
import sys
import threading
import time
import warnings
from pathlib import Path
from typing import Callable, Iterator, Optional

import torch

from ams_torch.native import emulation, probes
from ams_torch.native.cache import (  # noqa: F401  (re-exported: the lock and the cache's file names)
    DEFAULT_LOCK_STALE_S,
    ENV_LOCK_STALE,
    LOCK_NAME,
    MARKER_NAME,
    TORCH_LOCK_NAME,
    build_lock,
    cached_library as _cached_library,
    discard_library as _discard_library,
    lock_is_stale,
    write_marker as _write_marker,
)
from ams_torch.native.cuda_arch import nvcc_arches, resolve_arch_list

__all__ = ["native_status", "native_enabled", "native_ops", "ensure", "kinds", "cpu_op", "cuda_op",
           "NativeBuildWarning"]

CSRC_ROOT = Path(__file__).resolve().parent / "csrc"
CSRC = CSRC_ROOT / "banded"
ENV_ENABLE = "AMS_TORCH_NATIVE"
ENV_CACHE = "AMS_TORCH_CACHE"

#: op group -> (its CPU sources, its CUDA sources: the .cu files and their torch binding), relative
#: to csrc/. Groups are the folders of csrc/ and a Python-side notion only (which functions exist;
#: :mod:`ams_torch.native.dispatch`): every group's CPU sources go into the one CPU library, its
#: CUDA sources into the one CUDA library.
GROUPS = {
    "banded": (("banded/banded_cpu.cpp",), ("banded/banded_cuda_binding.cpp", "banded/banded_cuda.cu")),
    "frame": (("frame/frame_cpu.cpp",), ("frame/frame_cuda_binding.cpp", "frame/frame_cuda.cu")),
    "frame_adjoint": (("frame/frame_adjoint_cpu.cpp",),
                      ("frame/frame_adjoint_cuda_binding.cpp", "frame/frame_adjoint_cuda.cu")),
    "collide": (("collide/collide_cpu.cpp",), ("collide/collide_cuda_binding.cpp", "collide/collide_cuda.cu")),
    "collide_adjoint": (("collide/collide_adjoint_cpu.cpp",),
                        ("collide/collide_adjoint_cuda_binding.cpp", "collide/collide_adjoint_cuda.cu")),
    "grid": (("grid/grid_cpu.cpp", "grid/sweeps_cpu.cpp"),
             ("grid/grid_cuda_binding.cpp", "grid/grid_cuda.cu", "grid/sweeps_cuda_binding.cpp", "grid/sweeps_cuda.cu")),
    "finish_adjoint": (("frame/finish_adjoint_cpu.cpp",),
                       ("frame/finish_adjoint_cuda_binding.cpp", "frame/finish_adjoint_cuda.cu")),
    "grid_adjoint": (("grid/grid_adjoint_cpu.cpp",),
                     ("grid/grid_adjoint_cuda_binding.cpp", "grid/grid_adjoint_cuda.cu")),
}

# backend -> (extension name, sources compiled, headers they read (relative to csrc/; left empty here),
#             torch.ops namespace, device type). csrc/ is the include path: includes are path-qualified
#             ("common/launch_cuda.cuh"); the headers are completed with the include closure below.
# One library per device: every source registers its functions under the library's namespace
# (TORCH_LIBRARY_FRAGMENT(ams_torch_cpu, m) / TORCH_LIBRARY_IMPL(ams_torch_cpu, CPU, m); the same
# with ams_torch_cuda), and every source of a library is compiled with the same flags (one
# floating-point contraction setting: inline and template functions of shared headers, of which
# the linker keeps one copy per library, are then the same code in every source).
_BACKENDS = {
    "cpu": ("ams_torch_cpu", tuple(s for cpu, _ in GROUPS.values() for s in cpu), (), "ams_torch_cpu", "cpu"),
    "cuda": ("ams_torch_cuda", tuple(s for _, cuda in GROUPS.values() for s in cuda), (), "ams_torch_cuda", "cuda"),
}


# The emulator's self-test kernels (csrc/emulation/selftest_cuda.*), a separate test-only library:
# built on request only, for the emulation (tests) and on a GPU (scripts/validate_cuda.py: the
# emulator's answers against the device's); no op of ams_torch calls it.
_SELFTEST = {
    "selftest_cuda": ("ams_torch_selftest_cuda", ("emulation/selftest_cuda_binding.cpp", "emulation/selftest_cuda.cu"),
                      (), "ams_torch_selftest_cuda", "cuda"),
}
_INCLUDE = re.compile(r'^\s*#\s*include\s*"([^"]+)"', re.M)


def include_closure(files) -> tuple:
    """Every csrc/ file that ``files`` (paths relative to csrc/) include, directly or through other
    headers, sorted: what a build of those files reads, so the cache key covers it. Includes are
    path-qualified from csrc/ (``#include "common/launch_cuda.cuh"``), the only include directory
    of a build; a quoted include that names a csrc/ file any other way (a bare name that the
    compiler would find beside the includer) is an error, so nothing a build reads escapes the key."""
    seen, todo = set(), list(files)
    while todo:
        rel = todo.pop()
        for inc in _INCLUDE.findall((CSRC_ROOT / rel).read_text()):
            if (CSRC_ROOT / inc).is_file():
                if inc not in seen:
                    seen.add(inc)
                    todo.append(inc)
            elif (CSRC_ROOT / rel).parent.joinpath(inc).is_file():
                raise ValueError(f'{rel}: #include "{inc}" names a csrc/ file relative to its folder; '
                                 f"write it from csrc/ (\"{(Path(rel).parent / inc).as_posix()}\")")
            # else not ours: a system or torch header given with quotes
    return tuple(sorted(seen - set(files)))


def _complete(table: dict) -> dict:
    """The table with each backend's headers made the include closure of its sources: nobody lists
    headers by hand, so a header added to a kernel can never be left out of its cache key."""
    return {k: (n, src, tuple(sorted(set(hdr) | set(include_closure(src)))), ns, dev)
            for k, (n, src, hdr, ns, dev) in table.items()}


_BACKENDS, _SELFTEST = _complete(_BACKENDS), _complete(_SELFTEST)
_ALL = {**_BACKENDS, **_SELFTEST, **emulation.emulated_specs({**_BACKENDS, **_SELFTEST})}

#: How each stage of a frame whose inputs require grad runs on a native simulator (forward and
#: adjoint): reported by native_status()["gradients"].
GRADIENT_STAGES = {
    "dynamics": "native forward and adjoint (frame_posed / frame_adjoint of the cpu / cuda library); with "
                "Params(contact='substep') and colliders substep by substep, the contact after each by the native "
                "collision forward and adjoint (as 'collisions'), follow-the-leader at the frame's end by the "
                "collision kernels without colliders and their adjoint; the one-particle angular form "
                "(angular_reaction=False), a callable external force or a rest shape requiring grad: the torch "
                "definition",
    "hair_hair": "native forward and adjoint (p2g / pressure / g2p and p2g_adjoint / pressure_adjoint / "
                 "g2p_adjoint of the cpu / cuda library: P2G, the pressure's face field, sweeps and cell terms, G2P with "
                 "the FLIP/PIC blend; the backward pass recomputes the grid from the stage's inputs, nothing of it "
                 "kept between the passes; the change of frame by autograd on its torch definition); on CUDA under "
                 "torch's deterministic mode: the torch definition's vector-Jacobian product recomputed, its "
                 "pressure sweeps by native kernels (sweeps / sweeps_adjoint)",
    "collisions": "native forward and adjoint (collide / collide_adjoint of the cpu / cuda library) for "
                  "spheres, capsules, planes and meshes with at most 16 push-out passes; gradients reach x, v, "
                  "the colliders' world poses and velocities (the head's pose through colliders that follow it), "
                  "friction and the head rotation; a hollow sphere, a collider class without kernels, or "
                  "collider geometry or a rest shape requiring grad: the torch definition",
    "finish": "native forward and adjoint (finish / finish_adjoint of the cpu / cuda library) when the head pose "
              "has velocities; otherwise the torch definition",
    "plastic_yield": "native adjoint (yield_adjoint of the cpu / cuda library; the forward is the torch definition "
                     "in every path: a few elementwise operations), with the head pose's change of frame by autograd",
}


class NativeBuildWarning(RuntimeWarning):
    """A native backend could not be built or loaded; the torch definition is used for its ops."""


_lock = threading.RLock()
_warned = set()  # backend kinds warned about in this process (anything falsy resets it)


def _fresh_state() -> dict:
    return {"attempted": False, "built": False, "reason": None, "library": None, "build_dir": None,
            "build_seconds": None, "flags": None, "notes": []}


_state = {kind: _fresh_state() for kind in _ALL}
_ops: dict = {}
_loading: set = set()  # kinds being built, loaded and smoke-tested now (by this process)


def _st(kind: str) -> dict:
    """The state of ``kind`` (a fresh one when ``_state`` was reset to fewer kinds)."""
    return _state.setdefault(kind, _fresh_state())


def native_enabled() -> bool:
    """False when the environment variable ``AMS_TORCH_NATIVE`` is 0/false/no/off."""
    return os.environ.get(ENV_ENABLE, "1").strip().lower() not in ("0", "false", "no", "off")


def cache_root() -> Path:
    """Root of the build cache: ``$AMS_TORCH_CACHE`` or ``~/.cache/ams_torch``."""
    env = os.environ.get(ENV_CACHE)
    return Path(env).expanduser() if env else Path.home() / ".cache" / "ams_torch"


def kinds(device: Optional[str] = None) -> list:
    """Every backend kind (the keys of the build table and their emulations), or those whose ops
    take ``device`` tensors' device type ("cpu", "cuda", or "emulation")."""
    return [k for k, spec in _ALL.items() if device is None or spec[4] == device]


def native_ops(kind: str):
    """The ``torch.ops`` namespace of backend ``kind`` (see :func:`kinds`), building, loading and
    smoke-testing its library on first call; None when it cannot be had (one warning per kind)."""
    if kind not in _ALL:
        raise ValueError(f"unknown native backend {kind!r}; one of {sorted(_ALL)}")
    return _get(kind)


def ensure(kind_list) -> dict:
    """Build (or load) every backend of ``kind_list`` now. Returns ``{kind: reason}`` for those that
    are unavailable (empty when all are built)."""
    missing = {}
    for kind in kind_list:
        if native_ops(kind) is None:
            missing[kind] = _st(kind)["reason"]
    return missing


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
        build: first try to build every backend this process could use (the CPU ones always; the
            CUDA ones when a GPU is visible; never the emulated ones, which are for the tests),
            instead of only reporting what was used so far.
    Returns:
        ``{"enabled": bool, "cache_dir": str, <kind>: {...} for every kind}``; each backend dict
        has ``built`` (bool), ``reason`` (why not, or None), ``attempted`` (a build or load was
        tried in this process), ``library`` (path of the loaded .so), ``build_dir``,
        ``build_seconds`` (compile + load + smoke test, ~0 when cached), ``flags`` (compiler
        flags; for CUDA the architectures in ``TORCH_CUDA_ARCH_LIST=...``), ``notes`` (what the
        build changed, e.g. architectures added or left out) and ``device`` ("cpu", "cuda" or
        "emulation"); ``gradients`` says, per stage, what a frame whose inputs require grad runs
        (native kernels and adjoint, or the torch definition).
    """
    if build:
        for kind, spec in _BACKENDS.items():
            if spec[4] == "cpu" or torch.cuda.is_available():
                _get(kind)
    with _lock:
        out = {"enabled": native_enabled(), "cache_dir": str(cache_root())}
        for kind in _ALL:
            st = copy.deepcopy(_st(kind))
            if not st["attempted"]:
                st["reason"] = _static_reason(kind) or "not built yet: built on first use"
            st["device"] = _ALL[kind][4]
            out[kind] = st
        grad = dict(GRADIENT_STAGES)
        if not any(_st(k)["built"] for k in ("cpu", "cuda")):
            adjoint = out["cpu"]["reason"]
            grad["dynamics"] = grad["dynamics"] if adjoint.startswith("not built yet") else \
                f"torch definition (the adjoint kernels did not build: {adjoint})"
        out["gradients"] = grad
        return out


# ---------------------------------------------------------------------------------------
# build and load
# ---------------------------------------------------------------------------------------

def _get(kind: str) -> Optional[Callable]:
    op = _ops.get(kind)
    if op is not None:
        return op
    with _lock:
        st = _st(kind)
        if kind in _loading:
            # asked again from inside its own smoke test: the probes' reference is the torch
            # definition, which must not call the library being tested (one library holds the
            # banded solve that the definition of the frame calls)
            return None
        if not st["attempted"]:
            t0 = time.perf_counter()
            _loading.add(kind)
            try:
                _ops[kind] = _build_and_load(kind, st)
                st["built"] = True
            except _Unavailable as e:
                st["reason"] = str(e)
            except Exception as e:  # a compile or load error: report it, never crash the solve
                st["reason"] = f"build failed: {type(e).__name__}: {_tail(str(e))}"
            finally:
                _loading.discard(kind)
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
    """One warning per backend kind and process; when native code is disabled by the user, one in all."""
    global _warned
    if not _warned:
        _warned = set()
    key = "disabled" if not native_enabled() else kind
    if key in _warned:
        return
    _warned.add(key)
    warnings.warn(
        f"ams_torch: native kernels of backend {kind!r} unavailable ({reason}); its ops use the torch "
        "definition, which is much slower. ams_torch.native_status() has the details; set "
        f"{ENV_ENABLE}=0 to choose the torch path explicitly.",
        NativeBuildWarning,
        stacklevel=4,
    )


def _static_reason(kind: str) -> Optional[str]:
    """Why ``kind`` cannot be built, from facts known without compiling, or None."""
    if not native_enabled():
        return f"disabled by {ENV_ENABLE}={os.environ.get(ENV_ENABLE)}"
    if _ALL[kind][4] == "cuda":
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


def build_tag(kind: str, key_parts: dict) -> str:
    """The cache folder name of backend ``kind``: a hash of the build configuration ``key_parts``
    and of every file the build reads (its sources, the include closure of their csrc/ headers,
    the emulator's files for an emulated build), read now: any edit rebuilds."""
    name, sources, headers, namespace, device = _ALL[kind]
    digest = hashlib.sha256()
    digest.update(json.dumps(key_parts, sort_keys=True).encode())
    files = sorted(set(sources) | set(headers) | set(include_closure(sources)))
    inputs = [CSRC_ROOT / f for f in files]
    if device == emulation.DEVICE:
        inputs += emulation.shim_files()
    for path in inputs:
        digest.update(str(path.relative_to(CSRC_ROOT)).encode())
        digest.update(path.read_bytes())
    return f"{kind}-torch{torch.__version__}-cuda{torch.version.cuda or 'none'}-{digest.hexdigest()[:16]}"


def _build_and_load(kind: str, st: dict) -> Callable:
    reason = _static_reason(kind)
    if reason:
        raise _Unavailable(reason)
    name, sources, headers, namespace, device = _ALL[kind]
    cflags, cuda_flags, ldflags, key_parts = _build_config(device)
    st["notes"] = list(key_parts.pop("notes", []))
    tag = build_tag(kind, key_parts)
    build_dir = cache_root() / tag.replace("+", "_")
    st["build_dir"] = str(build_dir)
    st["flags"] = cflags + cuda_flags + ([f"TORCH_CUDA_ARCH_LIST={key_parts['arch']}"] if "arch" in key_parts else [])
    build_dir.mkdir(parents=True, exist_ok=True)

    library = _cached_library(build_dir)
    if library is None:
        with build_lock(build_dir):
            library = _cached_library(build_dir)  # another process may have finished meanwhile
            if library is None:
                from torch.utils import cpp_extension

                if not cpp_extension.is_ninja_available():
                    raise _Unavailable("ninja is not installed (pip install ninja)")
                _discard_library(build_dir, name)
                if device == emulation.DEVICE:
                    paths, includes = emulation.prepare(sources, headers, build_dir / "src")
                else:
                    paths = [str(CSRC_ROOT / s) for s in sources]
                    includes = [str(CSRC_ROOT)]
                with _build_env(device, key_parts.get("arch")):
                    path = cpp_extension.load(
                        name=name,
                        sources=paths,
                        extra_cflags=cflags,
                        extra_cuda_cflags=cuda_flags,
                        extra_ldflags=ldflags,
                        extra_include_paths=includes,
                        build_directory=str(build_dir),
                        is_python_module=False,
                        verbose=False,
                    )
                library = Path(path)
                _write_marker(build_dir, library, key_parts)
    torch.ops.load_library(str(library))
    st["library"] = str(library)
    ns = getattr(torch.ops, namespace)
    _smoke_test(kind, ns, device, st)
    return ns


def _smoke_test(kind: str, ns, device: str, st: dict) -> None:
    """Run the backend's probe (:mod:`ams_torch.native.probes`); a failure makes it unavailable."""
    if device == "cuda" and torch.cuda.is_current_stream_capturing():
        st["notes"].append("smoke test skipped: first used inside a CUDA graph capture")
        return
    try:
        probes.probe(kind, ns, "cuda" if device == "cuda" else "cpu")
    except Exception as e:  # noqa: BLE001 - any failure of the probe means the backend is unusable
        raise _Unavailable(f"built and loaded, but its smoke test failed: {type(e).__name__}: {_tail(str(e), 4)}")


def _build_config(device: str):
    """(C++ flags, nvcc flags, linker flags, cache-key facts) for a backend of ``device``."""
    # -ffp-contract=off for every C++ source (GCC's default for C++ is "fast": a*b + c fused into
    # one FMA where the compiler likes): the kernels round like the torch definition, and the
    # sources of one library share header functions that must be the same code in all of them.
    cflags = ["-O3", "-fno-math-errno", "-ffp-contract=off", "-Wno-psabi"]
    ldflags: list = []
    capability = torch.backends.cpu.get_cpu_capability()
    if device == emulation.DEVICE:
        cflags = emulation.compile_flags()
    if device == "cpu":
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
    if device == emulation.DEVICE:
        key["emulation"] = emulation.REWRITE_VERSION
    if device == "cuda":
        cuda_flags = ["-O3"]  # torch adds the C++ standard and the -gencode list
        from torch.utils import cpp_extension

        nvcc = str(Path(cpp_extension.CUDA_HOME, "bin", "nvcc"))
        key["nvcc"] = _tool_version([nvcc, "--version"])
        try:
            key["arch"], key["notes"] = _cuda_arch_list(nvcc)
        except ValueError as e:
            raise _Unavailable(str(e))
        key["cuda_flags"] = cuda_flags
    return cflags, cuda_flags, ldflags, key


def _tool_version(cmd: list) -> str:
    try:
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=30).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    lines = out.splitlines()
    return (lines[0] + " | " + lines[-1]) if lines else "unknown"


def _cuda_arch_list(nvcc: str) -> tuple:
    """(TORCH_CUDA_ARCH_LIST to build with, notes): :func:`ams_torch.native.cuda_arch.resolve_arch_list`."""
    caps = [torch.cuda.get_device_capability(i) for i in range(torch.cuda.device_count())]
    return resolve_arch_list(os.environ.get("TORCH_CUDA_ARCH_LIST"), caps, torch.cuda.get_arch_list(),
                             nvcc_arches(nvcc))


@contextlib.contextmanager
def _build_env(device: str, arch: Optional[str]) -> Iterator[None]:
    saved = {k: os.environ.get(k) for k in ("MAX_JOBS", "TORCH_CUDA_ARCH_LIST")}
    try:
        if not saved["MAX_JOBS"]:
            os.environ["MAX_JOBS"] = str(max(1, min(os.cpu_count() or 1, 4)))
        if device == "cuda" and arch:
            os.environ["TORCH_CUDA_ARCH_LIST"] = arch
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _tail(text: str, lines: int = 12) -> str:
    return "\n".join(text.strip().splitlines()[-lines:])
