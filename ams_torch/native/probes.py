"""Smoke tests of a freshly loaded native library: one tiny call of each op group, compared with the
torch definition (float64, a few values). :mod:`ams_torch.native.build` runs the probes of a library
(every registered group's: the CPU, CUDA and emulated CUDA libraries hold every group) right after
loading it and marks the backend unavailable, with the error, when it fails: a library
built for the wrong GPU architecture, a broken toolkit or driver, or a kernel that crashes, is then
reported at build time (and the torch path is used) instead of failing, or returning garbage,
inside the first step.

The banded solve's probe is here; the op groups of the upper layers register theirs
(:func:`register`: ``frame``, ``collide`` and ``grid`` in :mod:`ams_torch.sim.backends`, imported
with ``ams_torch``). A library without probes (the emulator's self-test) is only loaded.
"""
from __future__ import annotations

from typing import Callable, Dict

import torch

__all__ = ["probe", "register", "close"]

F64 = torch.float64
TOL = 1e-8
#: op group -> probe(ns, device): raises when the backend's op is wrong
PROBES: Dict[str, Callable] = {}


def register(group: str, fn: Callable) -> None:
    """Make ``fn(ns, device)`` the probe of op group ``group`` (a key of ``build.GROUPS``)."""
    PROBES[group] = fn


def close(got: torch.Tensor, want: torch.Tensor, what: str) -> None:
    """Raise AssertionError unless ``got`` is within 1e-8 (relative, 2-norm) of ``want``."""
    got, want = got.detach().double().cpu(), want.detach().double().cpu()
    err = (got - want).norm().item()
    scale = max(want.norm().item(), 1e-30)
    if not (err <= TOL * scale):
        raise AssertionError(f"{what}: relative difference {err / scale:.3g} from the torch definition")


#: the build backends holding every op group (the emulated CUDA library as ``cuda_emu``)
LIBRARIES = ("cpu", "cuda")


def groups(kind: str) -> list:
    """The op groups whose probes backend ``kind`` runs: every registered one for the CPU and CUDA
    libraries and the emulated CUDA library (``cuda_emu``), none for another (the self-test)."""
    base = kind[:-4] if kind.endswith("_emu") else kind
    return list(PROBES) if base in LIBRARIES else []


def probe(kind: str, ns, device: str) -> None:
    """Run the probes of backend ``kind`` (a key of the build table) on ``ns`` (its ``torch.ops``
    namespace) with ``device`` tensors ("cpu" for the CPU and emulated backends, "cuda")."""
    for name in groups(kind):
        with torch.no_grad():
            PROBES[name](ns, torch.device(device))
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


def _banded(ns, device) -> None:
    blocks = torch.zeros(2, 5, 4, 3, 3, dtype=F64, device=device)
    blocks[:, :, 0] = 2.0 * torch.eye(3, dtype=F64, device=device)
    rhs = torch.arange(30, dtype=F64, device=device).reshape(2, 5, 3)
    close(ns.solve_banded(blocks, rhs), rhs / 2.0, "solve_banded")


register("banded", _banded)
