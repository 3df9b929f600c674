"""The CUDA emulation: every CUDA backend of :mod:`ams_torch.native.build` (the CUDA library: every
``.cu`` file and torch binding; and the emulator's self-test) compiled as host C++ against the CPU
torch, so the CUDA kernels run in the tests on a machine without a GPU.

For each CUDA backend ``<kind>`` of the build table there is an emulated backend
``<kind>_emu`` (``cuda_emu``: one emulated library with every CUDA kernel, namespace
``ams_torch_cuda_emu``) with the same sources and headers (a kernel or header added to the table is
emulated with no change here), built like the others (lazily, cached, ``native_ops``):

* the sources and headers are copied into the build directory with two rewrites: the launch
  syntax ``k<<<grid, block, shmem, stream>>>(args)`` becomes
  ``k | ::ams_emu::LaunchConfig("file:line k", grid, block, shmem, stream)(args)`` (a call of
  the emulator, ``csrc/emulation/cuda_emulation.h``), and in the bindings the op library
  ``TORCH_LIBRARY(ns, …)`` (or ``TORCH_LIBRARY_FRAGMENT``) becomes ``ns_emu`` with its ``CUDA`` kernels registered for ``CPU``
  (``.is_cuda()`` checks read ``.is_cpu()``);
* ``.cu`` files are compiled by the C++ compiler with ``__CUDACC__`` and ``__CUDA_ARCH__``
  defined and the emulator included first; the bindings find stand-ins for the toolkit's and
  c10's CUDA headers in ``csrc/emulation/include`` (first on the include path);
* a local header that a copied file includes but the build table does not list is an error
  (the table is also the real build's cache key: an unlisted header would leave a stale cache).

The emulated ops take CPU tensors: ``build.native_ops("cuda_emu").frame(...)`` runs the CUDA
kernels of ``frame_cuda.cu`` through the binding of ``frame_cuda_binding.cpp``. What the
emulation can and cannot show is in the header comment of ``cuda_emulation.h`` and in
``docs/cuda.md``.
"""
from __future__ import annotations

import re
from pathlib import Path
from typing import Dict, Iterable, List, Tuple

CSRC_ROOT = Path(__file__).resolve().parent / "csrc"
SHIM_DIR = CSRC_ROOT / "emulation"
SUFFIX = "_emu"
DEVICE = "emulation"
# bump when the rewrites below change (part of the cache key)
REWRITE_VERSION = 1

_FLAGS = ["-std=c++20", "-O2", "-fno-math-errno", "-ffp-contract=off", "-fvisibility=hidden",
          "-fvisibility-inlines-hidden", "-Wno-unknown-pragmas"]


def emulated_specs(backends: Dict[str, tuple]) -> Dict[str, tuple]:
    """``{<kind>_emu: spec}`` for every CUDA backend of ``backends`` (the build table: kind ->
    (extension name, sources, headers, namespace, device))."""
    out = {}
    for kind, (name, sources, headers, namespace, device) in backends.items():
        if device == "cuda":
            out[kind + SUFFIX] = (name + SUFFIX, sources, headers, namespace + SUFFIX, DEVICE)
    return out


def shim_files() -> List[Path]:
    """Every file of the emulator (hashed into the cache key)."""
    return sorted(p for p in SHIM_DIR.rglob("*") if p.is_file())


def compile_flags() -> List[str]:
    """C++ flags of an emulated build: C++20 (std::atomic_ref), no floating-point contraction
    (the CPU kernels' arithmetic, not nvcc's fused multiply-adds), hidden symbols (the emulated
    and the real library of a backend can be loaded in one process)."""
    return list(_FLAGS)


# -- rewrites ----------------------------------------------------------------------------------
_CALLEE = re.compile(r"([A-Za-z_]\w*)\s*(?:<[^;{}]*>)?\s*$")


def rewrite_launches(text: str, label: str) -> str:
    """``k<<<cfg>>>(args)`` -> ``k | ::ams_emu::LaunchConfig("label:line k", cfg)(args)`` for every
    launch in ``text`` (newlines kept, so line numbers do not move)."""
    out, pos = [], 0
    while True:
        start = text.find("<<<", pos)
        if start < 0:
            out.append(text[pos:])
            return "".join(out)
        depth, i = 0, start + 3
        while i < len(text):
            c = text[i]
            if c in "([{":
                depth += 1
            elif c in ")]}":
                depth -= 1
            elif depth == 0 and text.startswith(">>>", i):
                break
            i += 1
        else:
            raise ValueError(f"{label}: unterminated kernel launch '<<<' at offset {start}")
        line = text.count("\n", 0, start) + 1
        m = _CALLEE.search(text[max(0, start - 200):start])
        where = f"{label}:{line}" + (f" {m.group(1)}" if m else "")
        out.append(text[pos:start])
        out.append(f' | ::ams_emu::LaunchConfig("{where}", ')
        out.append(text[start + 3:i])
        out.append(")")
        pos = i + 3


_LIBRARY = re.compile(r"\b(TORCH_LIBRARY|TORCH_LIBRARY_FRAGMENT)\s*\(\s*(\w+)\s*,")
_IMPL = re.compile(r"\bTORCH_LIBRARY_IMPL\s*\(\s*(\w+)\s*,\s*(\w+)\s*,")


def rewrite_binding(text: str) -> str:
    """The op library renamed ``<ns>_emu``, its CUDA kernels registered for CPU, CUDA-tensor
    checks made CPU-tensor checks."""
    text = _LIBRARY.sub(lambda m: f"{m.group(1)}({m.group(2)}{SUFFIX},", text)
    text = _IMPL.sub(lambda m: f"TORCH_LIBRARY_IMPL({m.group(1)}{SUFFIX}, "
                               f"{'CPU' if m.group(2) == 'CUDA' else m.group(2)},", text)
    text = re.sub(r"\.is_cuda\(\)", ".is_cpu()", text)
    text = re.sub(r"\bDeviceType::CUDA\b", "DeviceType::CPU", text)
    return re.sub(r"\bkCUDA\b", "kCPU", text)


_DEVICE_PRELUDE = ("// CUDA emulation: this .cu file compiled as host C++ (ams_torch/native/emulation.py)\n"
                   "#define __CUDACC__ 1\n#define __CUDA_ARCH__ {arch}\n#include \"cuda_emulation.h\"\n#line 1\n")
_INCLUDE = re.compile(r'^\s*#\s*include\s*"([^"]+)"', re.M)


def emulated_source_name(rel: str) -> str:
    """Where source ``rel`` (relative to csrc/) is written: ``.cu`` files become ``.cu.cpp`` (the
    C++ compiler, not nvcc, builds them)."""
    return rel + ".cpp" if rel.endswith(".cu") else rel


def prepare(sources: Iterable[str], headers: Iterable[str], dest: Path, arch: int = 900) -> Tuple[List[str], List[str]]:
    """Write the rewritten copies of ``sources`` and ``headers`` (paths relative to csrc/) under
    ``dest``. Returns (source paths to compile, include directories: the emulator's stand-in
    headers first, then the emulator, then ``dest``: the copied csrc/, whose includes are path-qualified)."""
    sources, headers = list(sources), list(headers)
    listed = set(sources) | set(headers)
    compiled = []
    for rel in sources + headers:
        text = (CSRC_ROOT / rel).read_text()
        for inc in _INCLUDE.findall(text):
            if (CSRC_ROOT / inc).is_file() and inc not in listed:
                raise ValueError(f"{rel} includes \"{inc}\", a csrc/ header that the build table does not list: "
                                 f"add it to the backend's headers in ams_torch/native/build.py")
        text = rewrite_launches(text, rel)
        if rel in sources:
            text = rewrite_binding(text)
        if rel.endswith(".cu"):
            text = _DEVICE_PRELUDE.format(arch=arch) + text
        out = dest / emulated_source_name(rel)
        out.parent.mkdir(parents=True, exist_ok=True)
        if not out.exists() or out.read_text() != text:  # unchanged copies keep their mtime (ninja)
            out.write_text(text)
        if rel in sources:
            compiled.append(str(out))
    return compiled, [str(SHIM_DIR / "include"), str(SHIM_DIR), str(dest)]
