"""Which GPU architectures the CUDA backends are compiled for (``TORCH_CUDA_ARCH_LIST``).

Unset: as torch chooses for its own extensions (``torch.utils.cpp_extension``): the visible
devices' compute capabilities, each clamped to the newest architecture this torch was built for,
the newest one also as PTX (``+PTX``, so a newer GPU JIT-compiles it); additionally clamped to the
newest architecture nvcc can compile (a GPU newer than the toolkit still gets PTX it can run).

Set by the user: named architectures are expanded as torch does (``"Hopper"`` -> ``9.0+PTX``),
entries nvcc cannot compile (``nvcc --list-gpu-arch``; CUDA 13 dropped everything below 7.5) are
left out with a note, and the architecture of every visible device is added when the list does
not cover it (a library without code for the device would build and then fail at every launch).
"""
from __future__ import annotations

import re
import subprocess
from typing import Iterable, List, Optional, Sequence, Set, Tuple

__all__ = ["parse_arch_list", "nvcc_arches", "resolve_arch_list"]

# torch's named architectures (torch/utils/cpp_extension.py, _get_cuda_arch_flags), combined names first
NAMED_ARCHES = (
    ("Kepler+Tesla", "3.7"), ("Kepler", "3.5+PTX"), ("Maxwell+Tegra", "5.3"), ("Maxwell", "5.0;5.2+PTX"),
    ("Pascal", "6.0;6.1+PTX"), ("Volta+Tegra", "7.2"), ("Volta", "7.0+PTX"), ("Turing", "7.5+PTX"),
    ("Ampere+Tegra", "8.7"), ("Ampere", "8.0;8.6+PTX"), ("Ada", "8.9+PTX"), ("Hopper", "9.0+PTX"),
    ("Blackwell+Tegra", "11.0"), ("Blackwell", "10.0;10.3;12.0;12.1+PTX"),
)
_ENTRY = re.compile(r"^(\d+)\.(\d+)(a|f)?(\+PTX)?$")


def _key(arch: str) -> Tuple[int, int]:
    m = _ENTRY.match(arch)
    return (int(m.group(1)), int(m.group(2))) if m else (0, 0)


def _base(entry: str) -> str:
    """"9.0a+PTX" -> "9.0"."""
    m = _ENTRY.match(entry)
    return f"{m.group(1)}.{m.group(2)}" if m else entry


def parse_arch_list(text: str) -> List[str]:
    """Entries of a ``TORCH_CUDA_ARCH_LIST`` value (named architectures expanded; ``;`` or space
    separated). Raises ValueError naming an entry that is not an architecture."""
    text = text.replace(" ", ";")
    for name, value in NAMED_ARCHES:
        text = text.replace(name, value)
    out = []
    for entry in filter(None, (e.strip() for e in text.split(";"))):
        if not _ENTRY.match(entry):
            raise ValueError(f"TORCH_CUDA_ARCH_LIST: {entry!r} is not an architecture (e.g. 8.0, 9.0+PTX, Hopper)")
        if entry not in out:
            out.append(entry)
    return out


def nvcc_arches(nvcc: str) -> Optional[Set[str]]:
    """The architectures ``nvcc --list-gpu-arch`` names (``compute_90`` -> ``"9.0"``), or None when it
    cannot be asked."""
    try:
        proc = subprocess.run([nvcc, "--list-gpu-arch"], capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.SubprocessError):
        return None
    found = set()
    for m in re.finditer(r"compute_(\d+)(\d)\b", proc.stdout):
        found.add(f"{int(m.group(1))}.{m.group(2)}")
    return found or None


def _clamp(cap: Tuple[int, int], ceiling: Optional[Tuple[int, int]]) -> Tuple[int, int]:
    return cap if ceiling is None else min(cap, ceiling)


def resolve_arch_list(env: Optional[str], device_caps: Sequence[Tuple[int, int]], torch_arches: Iterable[str],
                      nvcc: Optional[Set[str]]) -> Tuple[str, List[str]]:
    """The ``TORCH_CUDA_ARCH_LIST`` to build with, and notes on what was changed.

    Args:
        env: the user's ``TORCH_CUDA_ARCH_LIST`` (None or "" or "native": choose as torch does).
        device_caps: compute capabilities of the visible devices, e.g. ``[(9, 0)]``.
        torch_arches: ``torch.cuda.get_arch_list()`` (``"sm_90"``, ``"compute_90"``, ...).
        nvcc: the architectures nvcc compiles (:func:`nvcc_arches`), None when unknown.
    Raises:
        ValueError: a malformed list, or no architecture left that nvcc can compile.
    """
    sms = [int(a.split("_")[1].rstrip("af")) for a in torch_arches if a.startswith("sm_")]
    torch_max = max(((s // 10, s % 10) for s in sms), default=None)
    nvcc_max = max((_key(a) for a in nvcc), default=None) if nvcc else None
    ceiling = min(c for c in (torch_max, nvcc_max) if c is not None) if (torch_max or nvcc_max) else None
    devices = sorted({_clamp(tuple(c), ceiling) for c in device_caps})
    device_archs = [f"{a}.{b}" for a, b in devices]
    notes: List[str] = []
    if not env or env == "native":
        if not device_archs:
            raise ValueError("no CUDA device to choose architectures for: set TORCH_CUDA_ARCH_LIST")
        archs = list(device_archs)
        archs[-1] += "+PTX"
        clamped = [f"{a}.{b}" for a, b in sorted(set(map(tuple, device_caps))) if _clamp((a, b), ceiling) != (a, b)]
        if clamped:
            notes.append(f"device architecture {', '.join(clamped)} is newer than torch/nvcc support: built for "
                         f"{device_archs[-1]}+PTX (JIT-compiled for the device)")
        return ";".join(archs), notes
    archs = []
    for entry in parse_arch_list(env):
        if nvcc is not None and _base(entry) not in nvcc:
            notes.append(f"TORCH_CUDA_ARCH_LIST entry {entry} left out: this nvcc cannot compile it "
                         f"(nvcc --list-gpu-arch: {min(nvcc, key=_key)} .. {max(nvcc, key=_key)})")
            continue
        archs.append(entry)
    covered = {_base(a) for a in archs}
    for arch in device_archs:
        if arch not in covered:
            archs.append(arch)
            notes.append(f"added {arch}, the architecture of a visible device, to TORCH_CUDA_ARCH_LIST")
    if not archs:
        raise ValueError(f"TORCH_CUDA_ARCH_LIST={env!r}: no architecture left that this nvcc can compile")
    archs.sort(key=_key)
    return ";".join(archs), notes
