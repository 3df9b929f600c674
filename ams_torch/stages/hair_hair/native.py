"""The grid part of the hair–hair stage as three registered ops with native kernels.

``torch.ops.ams_torch.hair_hair_p2g``, ``hair_hair_pressure`` and ``hair_hair_g2p`` work on the
block-sparse grid of :mod:`.sparse` (a pool of K blocks of 4³ cells per scene; layouts there):

* default implementation (any device): the torch definition (``sparse.py``: the dense grid of
  ``transfer.py`` and ``pressure.py`` on the occupied blocks);
* CPU and CUDA: the native kernels of ``ams_torch/native/csrc/grid`` (in the libraries ``cpu`` and
  ``cuda`` of :mod:`ams_torch.native.build`), built lazily on first use, for float32 and
  float64; otherwise (not built, ``AMS_TORCH_NATIVE=0``, another dtype) the torch definition,
  unless ``require_native`` asks for an error instead;
* ``register_fake``: shapes for ``torch.compile`` / meta tensors. No autograd formula: the
  stage calls these ops when nothing requires grad, or in a gradient frame of a native simulator
  inside ``stage.grid_op`` (the differentiable grid op: its backward recomputes the grid
  and runs the native adjoints ``p2g_adjoint`` / ``pressure_adjoint`` / ``g2p_adjoint``,
  ``csrc/grid/grid_adjoint.h``).

What the kernels do differently from the torch definition (same arithmetic per value; slots
at or beyond ``min(count, K)`` are left unwritten):

* **P2G**: the blocks the particles touch get slots (CPU: in block order, as torch; CUDA: by
  atomicAdd, in any order), then one trilinear stencil per particle and face grid, reused for
  mass and momentum. On CPU, particles are bucketed by x-slab of the grid (stable counting sort)
  and slabs of 4 cells are scattered in parallel in two colours (even slabs, then odd), so no
  two threads write the same face and every face sums its contributions in one fixed order:
  results do not depend on the thread count. On CUDA: one thread per particle, atomicAdd
  (summation order, hence the last bits, vary between runs).
* **Pressure**: per used slot, the entries of its 64 cells (zero for cells that cannot carry φ);
  the active cells are counted per scene (the torch path sweeps a list of them with a static
  capacity, ``HairHairGrid.active_capacity``; the kernels need no list, but flag the same
  overflow: the op's third output, per scene, is blocks > K or active cells > that capacity).
  Scenes where no cell has b > 0 skip the sweeps (φ stays exactly 0, as on the torch path):
  decided on the device, no host sync. CPU: the sweeps visit only the slots φ can have reached
  (those with a pushing cell, then the neighbours of slots where φ became non-zero), with the
  values of sweeping every cell. CUDA: all sweeps in one launch, one thread block per scene over
  its used slots, ``__syncthreads()`` between sweeps.
* **G2P**: fused with the FLIP/PIC blend and both frame changes; writes x', v'.
"""
from __future__ import annotations

import torch

from ams_torch.native import build as _native
from ams_torch.native.dispatch import NATIVE_DTYPES, native_available as _available, native_kind, native_namespace
from ams_torch.stages.hair_hair.sparse import BLOCK_CELLS, blocks_per_axis, g2p_sparse, p2g_sparse, pressure_sparse

__all__ = ["NATIVE_DTYPES", "native_available", "p2g_op", "pressure_op", "g2p_op", "p2g", "pressure", "g2p"]



def native_available(device, dtype) -> bool:
    """Whether the native grid kernels run for tensors of ``device`` and ``dtype`` (builds on
    first call; False when they cannot be built, when disabled, or for other dtypes)."""
    return _available("grid", device, dtype)


def _namespace(t: torch.Tensor, require_native: bool, what: str):
    """The native namespace for ``t``'s device, or None (torch definition), or an error."""
    kind = native_kind("grid", t.device)
    ns = native_namespace("grid", t)  # the stage sends inputs that keep a gradient to the torch definition
    if ns is None and require_native:
        if t.dtype not in NATIVE_DTYPES:
            why = f"dtype {t.dtype} (native kernels take float32 and float64)"
        else:
            why = _native.native_status()[kind]["reason"]
        raise RuntimeError(f"hair_hair backend='native': no native {what} kernel for {t.device.type}: {why}")
    return ns


# -- P2G ---------------------------------------------------------------------------------------
@torch.library.custom_op("ams_torch::hair_hair_p2g", mutates_args=())
def p2g_op(x: torch.Tensor, v: torch.Tensor, m: torch.Tensor, frame: torch.Tensor, origin: torch.Tensor,
           cell_size: float, resolution: int, capacity: int,
           require_native: bool) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """x, v: (B, P, 3); m: (B, P); frame: (B, 6, 3); origin: (3,); capacity K. Returns faces
    (B, K, 3, 64, 2), table (B, nb³) int32, blocks (B, K) int32, count (B,) int32."""
    return p2g_sparse(x, v, m, frame, origin, cell_size, resolution, capacity)


def _p2g_kernel(x, v, m, frame, origin, cell_size, resolution, capacity, require_native):
    if x.is_cuda and torch.are_deterministic_algorithms_enabled():
        # the CUDA kernel's float atomics sum in a varying order (its binding alerts): the torch
        # definition (index_add, deterministic in that mode) instead
        return p2g_sparse(x, v, m, frame, origin, cell_size, resolution, capacity)
    ns = _namespace(x, require_native, "P2G")
    if ns is None:
        return p2g_sparse(x, v, m, frame, origin, cell_size, resolution, capacity)
    return tuple(ns.p2g(x, v, m, frame, origin, cell_size, resolution, capacity))


p2g_op.register_kernel("cpu")(_p2g_kernel)
p2g_op.register_kernel("cuda")(_p2g_kernel)


@p2g_op.register_fake
def _p2g_fake(x, v, m, frame, origin, cell_size, resolution, capacity, require_native):
    b = x.shape[0]
    ints = dict(dtype=torch.int32, device=x.device)
    return (x.new_empty(b, capacity, 3, BLOCK_CELLS, 2), torch.empty(b, blocks_per_axis(resolution) ** 3, **ints),
            torch.empty(b, capacity, **ints), torch.empty(b, **ints))


# -- pressure ----------------------------------------------------------------------------------
@torch.library.custom_op("ams_torch::hair_hair_pressure", mutates_args=())
def pressure_op(faces: torch.Tensor, table: torch.Tensor, blocks: torch.Tensor, count: torch.Tensor,
                target_density: torch.Tensor, dt: torch.Tensor, cell_size: float, resolution: int, iterations: int,
                omega: float, stiffness: float, pic: float, active_capacity: int,
                require_native: bool) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """faces: (B, K, 3, 64, 2); table, blocks, count from P2G; target_density, dt: () tensors;
    active_capacity: active cells per scene the torch sweeps hold. Returns phi (B, K, 64), field
    (B, K, 3, 64) and overflow (B,) bool (see :func:`~.sparse.pressure_sparse`). Slots at or past
    ``min(count, K)`` are unused: their values are unspecified on the native kernels (as P2G's
    faces there; G2P reaches the pool through the table only)."""
    return pressure_sparse(faces, table, blocks, count, target_density, dt, cell_size, resolution, iterations, omega,
                           stiffness, pic, active_capacity)


def _pressure_kernel(faces, table, blocks, count, target_density, dt, cell_size, resolution, iterations, omega,
                     stiffness, pic, active_capacity, require_native):
    ns = _namespace(faces, require_native, "pressure")
    if ns is None:
        return pressure_sparse(faces, table, blocks, count, target_density, dt, cell_size, resolution, iterations,
                               omega, stiffness, pic, active_capacity)
    return tuple(ns.pressure(faces, table, blocks, count, target_density, dt, cell_size, resolution, iterations,
                             omega, stiffness, pic, active_capacity))


pressure_op.register_kernel("cpu")(_pressure_kernel)
pressure_op.register_kernel("cuda")(_pressure_kernel)


@pressure_op.register_fake
def _pressure_fake(faces, table, blocks, count, target_density, dt, cell_size, resolution, iterations, omega,
                   stiffness, pic, active_capacity, require_native):
    b, k = faces.shape[:2]
    return (faces.new_empty(b, k, BLOCK_CELLS), faces.new_empty(b, k, 3, BLOCK_CELLS),
            torch.empty(b, dtype=torch.bool, device=faces.device))


# -- G2P ---------------------------------------------------------------------------------------
@torch.library.custom_op("ams_torch::hair_hair_g2p", mutates_args=())
def g2p_op(x: torch.Tensor, v: torch.Tensor, field: torch.Tensor, table: torch.Tensor, frame: torch.Tensor,
           origin: torch.Tensor, free: torch.Tensor, dt: torch.Tensor, cell_size: float, resolution: int, pic: float,
           require_native: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """x, v: (B, P, 3); field: (B, K, 3, 64); table: (B, nb³) int32; free: (M,) bool, M | P;
    dt: (). Returns x', v' (B, P, 3)."""
    return g2p_sparse(x, v, field, table, frame, origin, free, dt, cell_size, resolution, pic)


def _g2p_kernel(x, v, field, table, frame, origin, free, dt, cell_size, resolution, pic, require_native):
    ns = _namespace(x, require_native, "G2P")
    if ns is None:
        return g2p_sparse(x, v, field, table, frame, origin, free, dt, cell_size, resolution, pic)
    return tuple(ns.g2p(x, v, field, table, frame, origin, free, dt, cell_size, resolution, pic))


g2p_op.register_kernel("cpu")(_g2p_kernel)
g2p_op.register_kernel("cuda")(_g2p_kernel)


@g2p_op.register_fake
def _g2p_fake(x, v, field, table, frame, origin, free, dt, cell_size, resolution, pic, require_native):
    return torch.empty_like(x, memory_format=torch.contiguous_format), \
        torch.empty_like(v, memory_format=torch.contiguous_format)


# -- calls from the stage ----------------------------------------------------------------------
def _direct(t: torch.Tensor) -> bool:
    """Call the kernel functions directly (skipping ~12 µs of custom-op dispatch per call): in
    eager mode on CPU/CUDA. Under torch.compile the registered ops (their fakes, their schemas)."""
    return native_kind("grid", t.device) is not None and not torch.compiler.is_compiling()


def p2g(x, v, m, frame, origin, cell_size: float, resolution: int, capacity: int, require_native: bool):
    """:func:`p2g_op` (no gradient: the stage calls it only when nothing requires grad)."""
    args = (x, v, m, frame, origin, cell_size, resolution, capacity, require_native)
    return _p2g_kernel(*args) if _direct(x) else p2g_op(*args)


def pressure(faces, table, blocks, count, target_density, dt, cell_size: float, resolution: int, iterations: int,
             omega: float, stiffness: float, pic: float, active_capacity: int, require_native: bool):
    """:func:`pressure_op` (no gradient)."""
    args = (faces, table, blocks, count, target_density, dt, cell_size, resolution, iterations, omega, stiffness, pic,
            active_capacity, require_native)
    return _pressure_kernel(*args) if _direct(faces) else pressure_op(*args)


def g2p(x, v, field, table, frame, origin, free, dt, cell_size: float, resolution: int, pic: float,
        require_native: bool):
    """:func:`g2p_op` (no gradient)."""
    args = (x, v, field, table, frame, origin, free, dt, cell_size, resolution, pic, require_native)
    return _g2p_kernel(*args) if _direct(x) else g2p_op(*args)
