"""May these tensors run a native kernel? The one rule every registered op of ams_torch applies
before it calls its native kernel (and otherwise its torch definition):

* the kernels take float32 and float64 tensors on CPU or CUDA (:data:`NATIVE_DTYPES`,
  :data:`NATIVE_DEVICES`);
* a tensor that keeps a gradient goes to the torch definition (the gradient is exact on the
  definition), except for the ops with their own adjoint (``frame_adjoint``);
* the device's native library must be built (built lazily on the first question, one
  :class:`~ams_torch.native.build.NativeBuildWarning` when it cannot be).

Op groups (``group``) are the folders of ``csrc/``: ``banded`` (the solve), ``frame``,
``frame_adjoint``, ``collide``, ``grid`` (``build.GROUPS``): which functions exist, not separate
libraries. Every group's kernels are in the one library of their device (build backends ``cpu``
and ``cuda``); :func:`native_kind` names it. The Python checks (:func:`native_inputs`) are
traceable: no build, no host sync.
"""
from __future__ import annotations

from typing import Iterable, Optional

import torch

from ams_torch.native import build as _build

__all__ = ["NATIVE_DTYPES", "NATIVE_DEVICES", "GROUPS", "native_kind", "keeps_gradient", "native_inputs",
           "native_available", "native_namespace"]

#: the dtypes of the native kernels (others take the torch definition)
NATIVE_DTYPES = (torch.float32, torch.float64)
#: the device types of the native kernels
NATIVE_DEVICES = ("cpu", "cuda")
#: the op groups (``build.GROUPS``: their sources)
GROUPS = tuple(_build.GROUPS)


def native_kind(group: str, device) -> Optional[str]:
    """The build backend holding op ``group``'s kernels on ``device`` (the device's one library:
    "frame", cuda -> "cuda"), or None for a device without native kernels."""
    if group not in GROUPS:
        raise ValueError(f"unknown native op group {group!r}; one of {sorted(GROUPS)}")
    dev = torch.device(device).type
    return dev if dev in NATIVE_DEVICES else None


def keeps_gradient(tensors: Iterable[Optional[torch.Tensor]], grad_mode: bool = True) -> bool:
    """Whether any of ``tensors`` requires grad (None entries skipped); with ``grad_mode`` only while
    grad mode is on (an entry point), without it always (inside an op's kernel)."""
    if grad_mode and not torch.is_grad_enabled():
        return False
    return any(t is not None and t.requires_grad for t in tensors)


def native_inputs(x: torch.Tensor, tensors: Iterable[Optional[torch.Tensor]] = (), grad_mode: bool = True) -> bool:
    """Whether a native kernel may take ``x`` (float32/float64 on CPU/CUDA) and ``tensors`` (none
    keeping a gradient: :func:`keeps_gradient`). Traceable; builds nothing."""
    return x.dtype in NATIVE_DTYPES and x.device.type in NATIVE_DEVICES and not keeps_gradient(tensors, grad_mode)


def native_available(group: str, device, dtype) -> bool:
    """Whether op ``group``'s native kernels run for tensors of ``device`` and ``dtype`` (builds them
    on first call; False when they cannot be built, when ``AMS_TORCH_NATIVE=0``, or for another
    dtype or device). Not traceable: decide it when the simulator is built."""
    kind = native_kind(group, device)
    return kind is not None and dtype in NATIVE_DTYPES and _build.native_ops(kind) is not None


def native_namespace(group: str, x: torch.Tensor, tensors: Iterable[Optional[torch.Tensor]] = (),
                     grad_mode: bool = False):
    """The ``torch.ops`` namespace of op ``group``'s native kernels for ``x``'s device, or None (the
    torch definition): the inputs fail :func:`native_inputs` (inside a kernel: any tensor requiring
    grad, whatever the grad mode) or the library cannot be had."""
    if not native_inputs(x, tensors, grad_mode):
        return None
    return _build.native_ops(native_kind(group, x.device))
