"""The hair–hair stage: one frame of P2G → pressure → G2P (→ detailed collisions), SPEC §6."""
from __future__ import annotations

import math
from typing import Callable, Optional

import torch

from ams_torch.geometry.pose import Pose
from ams_torch.stages.hair_hair.config import HairHairGrid
from ams_torch.stages.hair_hair.detailed import detailed_collisions
from ams_torch.native.dispatch import keeps_gradient
from ams_torch.stages.hair_hair.native import NATIVE_DTYPES, g2p, native_available, p2g, pressure
from ams_torch.stages.hair_hair.sparse import g2p_sparse, p2g_sparse, pressure_sparse
from ams_torch.stages.hair_hair.transfer import scene_frame, to_head

__all__ = ["BACKENDS", "hair_hair_stage", "make_stage", "grid_op"]

BACKENDS = ("auto", "native", "torch")


def _inputs(grid: HairHairGrid, x: torch.Tensor, v: torch.Tensor, mass, free: Optional[torch.Tensor]):
    """Validate (metadata only) and flatten: x, v (B, P, 3), m (B, P), free (N,) bool, lead dims."""
    if x.dim() < 3 or x.shape[-1] != 3:
        raise ValueError(f"x must have shape (..., S, N, 3); got {tuple(x.shape)}")
    s, n = x.shape[-3], x.shape[-2]
    if (s, n) != (grid.num_strands, grid.num_particles):
        raise ValueError(f"x has (S, N) = ({s}, {n}) but the grid was built for "
                         f"({grid.num_strands}, {grid.num_particles})")
    if not isinstance(v, torch.Tensor) or v.shape != x.shape:
        raise ValueError(f"v must be a tensor of the shape of x {tuple(x.shape)}; got "
                         f"{tuple(v.shape) if isinstance(v, torch.Tensor) else type(v).__name__}")
    if v.dtype != x.dtype or v.device != x.device:
        raise ValueError(f"v must have the dtype and device of x ({x.dtype}, {x.device}); got {v.dtype}, {v.device}")
    if not x.dtype.is_floating_point:
        raise ValueError(f"x must be a floating-point tensor; got {x.dtype}")
    lead = x.shape[:-3]
    b, p = math.prod(lead), s * n
    if isinstance(mass, torch.Tensor):
        mass = _like(mass, x)
    else:  # a fill, not a host-to-device copy (capturable by CUDA graphs)
        mass = torch.full((), float(mass), device=x.device, dtype=x.dtype)
    try:
        m = mass.reshape(b, p) if tuple(mass.shape) == tuple(lead) + (s, n) else mass.expand(*lead, s, n).reshape(b, p)
    except RuntimeError:
        raise ValueError(f"mass of shape {tuple(mass.shape)} does not broadcast to {tuple(lead) + (s, n)}")
    if free is None:
        free = torch.ones(n, dtype=torch.bool, device=x.device)
    elif not isinstance(free, torch.Tensor) or free.shape not in ((n,), (s, n)):
        raise ValueError(f"free must be a tensor of shape ({n},) or ({s}, {n}); got "
                         f"{tuple(free.shape) if isinstance(free, torch.Tensor) else type(free).__name__}")
    else:  # (M,) with particle p of a scene free when free[p mod M]
        free = (free if free.dtype == torch.bool and free.device == x.device
                else free.to(device=x.device, dtype=torch.bool)).reshape(-1)
    return x.reshape(b, p, 3), v.reshape(b, p, 3), m, free, lead


def _like(t: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """t on x's device and dtype (t itself when it already is: no op dispatched)."""
    return t if t.dtype == x.dtype and t.device == x.device else t.to(device=x.device, dtype=x.dtype)


def _dt_tensor(dt, like: torch.Tensor) -> torch.Tensor:
    if isinstance(dt, torch.Tensor):
        if dt.dim() != 0 or not dt.dtype.is_floating_point:
            raise ValueError(f"dt must be a number or a 0-d floating-point tensor; got shape {tuple(dt.shape)}, "
                             f"{dt.dtype}")
        return dt.to(device=like.device, dtype=like.dtype)
    if isinstance(dt, bool) or not isinstance(dt, (int, float)) or not (math.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be a positive number of seconds; got {dt!r}")
    return torch.full((), float(dt), device=like.device, dtype=like.dtype)


def _use_native(backend: str, tensors, dtype) -> bool:
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}; got {backend!r}")
    if backend == "torch":
        return False
    grad = keeps_gradient(tensors)
    if backend == "native":
        if grad:
            raise ValueError("hair_hair backend='native' has no gradient: an input requires grad (use 'auto' "
                             "or 'torch', or call under torch.no_grad())")
        if dtype not in NATIVE_DTYPES:
            raise ValueError(f"hair_hair backend='native' takes float32 or float64; got {dtype}")
        return True
    return not grad and dtype in NATIVE_DTYPES


@torch.library.custom_op("ams_torch::hair_hair_grid", mutates_args=())
def grid_op(xf: torch.Tensor, vf: torch.Tensor, m: torch.Tensor, frame: torch.Tensor, origin: torch.Tensor,
            target: torch.Tensor, dt: torch.Tensor, free: torch.Tensor, cell_size: float, resolution: int,
            capacity: int, iterations: int, omega: float, stiffness: float, pic: float,
            active_capacity: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The grid part of the stage (P2G → pressure → G2P) as one differentiable op: the stage's
    flattened inputs xf, vf (B, P, 3) m, m/s; m (B, P) kg; frame (B, 6, 3); origin (3,) m; target,
    dt () tensors; free (M,) bool; the grid's settings. Returns x', v' (B, P, 3) and overflow (B,)
    bool. Default (any device): the torch definition (``sparse.py``); CPU and CUDA: the native
    kernels (``p2g``, ``pressure``, ``g2p``) where built. Its backward (``register_autograd``) runs
    the native adjoint kernels (:func:`_native_adjoint`), or where a library has none the torch
    definition's vector-Jacobian product recomputed (:func:`_recomputed_adjoint`); nothing of the
    grid is kept between the passes: only the inputs are saved."""
    stencils: list = []
    solve = (iterations, omega, stiffness, pic)
    faces, table, blocks, count = p2g_sparse(xf, vf, m, frame, origin, cell_size, resolution, capacity, stencils)
    _, field, overflow = pressure_sparse(faces, table, blocks, count, target, dt, cell_size, resolution, *solve,
                                         active_capacity)
    x1, v1 = g2p_sparse(xf, vf, field, table, frame, origin, free, dt, cell_size, resolution, pic, stencils)
    return x1.contiguous(), v1.contiguous(), overflow


def _grid_kernel(xf, vf, m, frame, origin, target, dt, free, cell_size, resolution, capacity, iterations, omega,
                 stiffness, pic, active_capacity):
    xc, vc, fc, oc = (t.detach().contiguous() for t in (xf, vf, frame, origin))
    solve = (iterations, omega, stiffness, pic)
    faces, table, blocks, count = p2g(xc, vc, m.detach().contiguous(), fc, oc, cell_size, resolution, capacity, False)
    _, field, overflow = pressure(faces, table, blocks, count, target, dt, cell_size, resolution, *solve,
                                  active_capacity, False)
    x1, v1 = g2p(xc, vc, field, table, fc, oc, free, dt, cell_size, resolution, pic, False)
    return x1, v1, overflow


grid_op.register_kernel("cpu")(_grid_kernel)
grid_op.register_kernel("cuda")(_grid_kernel)


@grid_op.register_fake
def _grid_fake(xf, vf, m, frame, origin, target, dt, free, cell_size, resolution, capacity, iterations, omega,
               stiffness, pic, active_capacity):
    return (torch.empty_like(xf, memory_format=torch.contiguous_format),
            torch.empty_like(vf, memory_format=torch.contiguous_format),
            torch.empty(xf.shape[0], dtype=torch.bool, device=xf.device))


def _grid_setup(ctx, inputs, output):
    xf, vf, m, frame, origin, target, dt, free, h, r, k, iterations, omega, stiffness, pic, active = inputs
    ctx.save_for_backward(xf, vf, m, frame, origin, target, dt, free)
    ctx.meta = (h, r, k, (iterations, omega, stiffness, pic), active)


@torch.library.custom_op("ams_torch::hair_hair_grid_adjoint", mutates_args=(), device_types=("cpu", "cuda"))
def grid_adjoint_op(xf: torch.Tensor, vf: torch.Tensor, m: torch.Tensor, frame: torch.Tensor, origin: torch.Tensor,
                    target: torch.Tensor, dt: torch.Tensor, free: torch.Tensor, gx: torch.Tensor, gv: torch.Tensor,
                    cell_size: float, resolution: int, capacity: int, iterations: int, omega: float,
                    stiffness: float, pic: float,
                    active_capacity: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The vector-Jacobian product of :func:`grid_op` by the native adjoint kernels
    (:func:`_native_adjoint`) for the adjoints gx, gv of x', v': the adjoints of xf, vf, m and frame.
    CPU and CUDA only (the op has no other implementation): :func:`grid_op`'s backward calls it
    where :func:`native_adjoint_namespace` finds the kernels, and otherwise recomputes the torch
    definition's product itself (autograd, which does not record inside an op's kernel)."""
    ns = native_adjoint_namespace(xf)
    if ns is None:
        raise RuntimeError("ams_torch::hair_hair_grid_adjoint: called without the native grid adjoint kernels "
                           "(grid_op's backward checks native_adjoint_namespace first)")
    meta = (cell_size, resolution, capacity, (iterations, omega, stiffness, pic), active_capacity)
    return tuple(_native_adjoint(ns, (xf, vf, m, frame, origin, target, dt, free), meta, gx, gv))


@grid_adjoint_op.register_fake
def _grid_adjoint_fake(xf, vf, m, frame, *rest):
    return tuple(torch.empty_like(t, memory_format=torch.contiguous_format) for t in (xf, vf, m, frame))


def _grid_backward(ctx, gx, gv, _overflow):
    xf, vf, m, frame, origin, target, dtt, free = ctx.saved_tensors
    h, r, k, solve, active = ctx.meta
    needs = ctx.needs_input_grad[:4]
    if native_adjoint_namespace(xf) is None:
        res = _recomputed_adjoint((xf, vf, m, frame, origin, target, dtt, free), ctx.meta, needs, gx, gv)
    else:
        gx = torch.zeros_like(xf) if gx is None else gx.contiguous()
        gv = torch.zeros_like(vf) if gv is None else gv.contiguous()
        grads = grid_adjoint_op(xf, vf, m, frame, origin, target, dtt, free, gx, gv, h, r, k, *solve, active)
        res = [g if n else None for g, n in zip(grads, needs)]
    return (*res,) + (None,) * 12


grid_op.register_autograd(_grid_backward, setup_context=_grid_setup)


def native_adjoint_namespace(x: torch.Tensor):
    """The native library holding the grid's adjoint kernels for ``x``'s device and dtype, or None
    (not built, or a library without them; on CUDA under torch's deterministic mode, whose float
    atomics would sum in a varying order: the recomputed torch definition instead)."""
    from ams_torch.native.dispatch import native_namespace

    if x.is_cuda and torch.are_deterministic_algorithms_enabled():
        return None  # the CUDA kernels' float atomics (P2G, G2P's adjoint) sum in a varying order
    ns = native_namespace("grid_adjoint", x)
    return ns if ns is not None and hasattr(ns, "pressure_adjoint") else None


def _recomputed_adjoint(saved, meta, needs, gx, gv):
    """The torch definition's vector-Jacobian product (autograd on ``sparse.py``, recomputed)."""
    xf, vf, m, frame, origin, target, dtt, free = saved
    h, r, k, solve, active = meta
    leaves = [t.detach().requires_grad_(n) for t, n in zip((xf, vf, m, frame), needs)]
    with torch.enable_grad():
        stencils: list = []
        faces, table, blocks, count = p2g_sparse(leaves[0], leaves[1], leaves[2], leaves[3], origin, h, r, k, stencils)
        _, field, _ = pressure_sparse(faces, table, blocks, count, target, dtt, h, r, *solve, active,
                                      native_sweeps=True)
        x1, v1 = g2p_sparse(leaves[0], leaves[1], field, table, leaves[3], origin, free, dtt, h, r, solve[3],
                            stencils)
        outs = [(o, g) for o, g in ((x1, gx), (v1, gv)) if g is not None]
        wrt = [t for t, n in zip(leaves, needs) if n]
        grads = iter(torch.autograd.grad([o for o, _ in outs], wrt, [g for _, g in outs], allow_unused=True))
    res = [next(grads) if n else None for n in needs]
    return [torch.zeros_like(t) if (n and g is None) else g for g, n, t in zip(res, needs, leaves)]


def _native_adjoint(ns, saved, meta, gx, gv):
    """The grid part's vector-Jacobian product by the native adjoint kernels: the adjoints of xf, vf,
    m and frame for gx, gv (B, P, 3).

    In the head frame the kernels recompute P2G (native ``p2g`` with the identity frame, so its
    stencils are those of the adjoints) and the pressure's field, then run the adjoints of G2P
    (FLIP/PIC blend; ``g2p_adjoint``), of the pressure (the face field, the sweeps, the cell terms;
    ``pressure_adjoint``) and of P2G (``p2g_adjoint``). The changes of frame around them are
    differentiated here, written out (a few elementwise operations per particle; no autograd, so
    this runs inside an op's kernel): into the head frame (``transfer.to_head``: xl = Rᵀ (x − T),
    vl = Rᵀ (v − V − W × (x − T))) and back (``transfer.apply_change``: x' = x + R (dt Δv),
    v' = v + R Δv, Δv zero for pinned particles)."""
    xf, vf, m, frame, origin, target, dtt, free = saved
    h, r, k, solve, active = meta
    iterations, omega, stiffness, pic = solve
    rot, trans, lin, ang = frame[:, :3], frame[:, 3], frame[:, 4], frame[:, 5]
    rel = xf - trans[:, None, :]
    vr = vf - lin[:, None, :] - torch.cross(ang[:, None, :].expand_as(rel), rel, dim=-1)
    xl = torch.einsum("bji,bpj->bpi", rot, rel).contiguous()
    vl = torch.einsum("bji,bpj->bpi", rot, vr).contiguous()
    md, oc = m.contiguous(), origin.contiguous()
    b, p = xf.shape[:2]
    ident = torch.zeros(b, 6, 3, dtype=xf.dtype, device=xf.device)
    ident[:, :3] = torch.eye(3, dtype=xf.dtype, device=xf.device)
    faces, table, blocks, count = ns.p2g(xl, vl, md, ident, oc, h, r, k)
    _, field, _ = ns.pressure(faces, table, blocks, count, target, dtt, h, r, iterations, omega, stiffness, pic,
                              active)
    world = dtt * gx + gv  # adjoint of R Δv
    free_p = free.to(device=xf.device, dtype=torch.bool).repeat(p // free.shape[0])[None, :, None]
    g_dv = torch.where(free_p, torch.einsum("bij,bpi->bpj", rot, world), torch.zeros_like(world)).contiguous()
    g_xl2, g_vl2, g_field, dv = ns.g2p_adjoint(xl, vl, field, table, oc, g_dv, h, r, pic)
    g_faces = ns.pressure_adjoint(faces, table, blocks, count, target, dtt, h, r, iterations, omega, stiffness, pic,
                                  g_field)
    g_xl1, g_vl1, g_m = ns.p2g_adjoint(xl, vl, md, oc, table, g_faces, h, r)
    g_xl, g_vl = g_xl1 + g_xl2, g_vl1 + g_vl2
    # into the head frame: a = R v̄l; v̄ = a, V̄ = −Σ a, r̄el = R x̄l + W × a, W̄ = −Σ rel × a, R̄ from both
    a = torch.einsum("bij,bpj->bpi", rot, g_vl)
    g_rel = torch.einsum("bij,bpj->bpi", rot, g_xl) + torch.cross(ang[:, None, :].expand_as(a), a, dim=-1)
    g_frame = torch.zeros_like(frame)
    g_frame[:, :3] = torch.einsum("bpj,bpi->bji", rel, g_xl) + torch.einsum("bpj,bpi->bji", vr, g_vl)
    g_frame[:, 3] = -g_rel.sum(1)
    g_frame[:, 4] = -a.sum(1)
    g_frame[:, 5] = -torch.cross(rel, a, dim=-1).sum(1)
    # back to the world: x' = x + R (dt Δv), v' = v + R Δv
    dv = torch.where(free_p, dv, torch.zeros_like(dv))
    g_frame[:, :3] += torch.einsum("bpi,bpj->bij", world, dv)
    return [g_rel + gx, a + gv, g_m, g_frame]


def hair_hair_stage(grid: Optional[HairHairGrid], x: torch.Tensor, v: torch.Tensor, mass,
                    head_pose: Optional[Pose], dt, free: Optional[torch.Tensor] = None, backend: str = "auto",
                    with_overflow: bool = False, recompute: bool = False):
    """Hair–hair interaction for one frame (SPEC §6), run after inextensibility.

    Args:
        grid: from :meth:`HairHair.build`; ``None`` returns ``(x, v)`` untouched (disabled).
        x: (..., S, N, 3) metres, world positions at the end of the frame.
        v: (..., S, N, 3) m/s, world velocities at the end of the frame (same dtype/device).
        mass: kg, broadcastable to (..., S, N).
        head_pose: head :class:`Pose` at the end of the frame (world ← head frame, batch dims
            broadcastable to ``...``); missing velocities count as zero; None = identity at rest.
        dt: frame length, seconds: a positive number or a 0-d tensor (not checked for sign: no
            host sync).
        free: (N,) bool (the same for every strand) or (S, N) bool, particles the stage may
            move (default: all). Pinned particles still contribute mass to the grid but are
            returned unchanged.
        backend: ``"auto"`` (default): the native kernels when they are built, the dtype is
            float32/float64 and nothing requires grad (``AMS_TORCH_NATIVE=0`` disables them);
            otherwise the torch definition. ``"native"``: the native kernels or an error.
            ``"torch"``: the torch definition (differentiable).
        with_overflow: also return the overflow flag.
        recompute: when an input requires grad and the native kernels are built (float32 /
            float64): the forward by the native kernels and the backward by the native adjoint
            kernels, the grid recomputed from the inputs (nothing of it kept between the passes;
            without adjoint kernels the torch definition's vector-Jacobian product, recomputed); a
            gradient frame of a native simulator asks for it.
    Returns:
        (x', v'): (..., S, N, 3) metres and m/s, with ``x' = x + dt (v' − v)`` for the grid part
        (plus the position push of detailed collisions, when enabled); with ``with_overflow``,
        (x', v', overflow): overflow () bool, True when some scene's hair occupied more blocks
        than ``grid.capacity`` (the blocks beyond it were left out of this frame's grid) or had
        more active cells than ``grid.active_capacity`` (the cells beyond it kept φ = 0): the
        result is not the grid's, and ``Simulator.check`` raises. Never set when both
        capacities are the whole grid.

    No host synchronisation, no data-dependent branch or shape: capturable by
    ``torch.compile(fullgraph=True)`` and CUDA graphs (for graphs, keep the grid, ``free``,
    ``head_pose`` and a tensor ``mass`` on the device of x: a scalar ``mass``/``dt`` becomes a
    fill, a host tensor would be a copy). Detailed collisions always run in torch, after the
    grid part.
    """
    if grid is None:
        return (x, v, torch.zeros((), dtype=torch.bool, device=x.device)) if with_overflow else (x, v)
    cfg = grid.config
    xf, vf, m, free, lead = _inputs(grid, x, v, mass, free)
    dtt = _dt_tensor(dt, x)
    frame = scene_frame(head_pose, lead, xf.shape[0], x.dtype, x.device)
    origin = _like(grid.origin, x)
    target = _like(grid.target_density, x)
    h, r, k, pic = grid.cell_size, grid.resolution, grid.capacity, 1.0 - cfg.flip
    solve = (cfg.pressure_iterations, cfg.jacobi_omega, cfg.volume_stiffness, pic)
    if (recompute and backend == "auto" and keeps_gradient((xf, vf, m, frame)) and x.dtype in NATIVE_DTYPES
            and native_available(x.device, x.dtype)):
        x1, v1, overflow = grid_op(xf, vf, m, frame, origin.contiguous(), target, dtt, free, h, r, k, *solve,
                                   grid.active_capacity)
    elif _use_native(backend, (xf, vf, m, frame, origin, target, dtt), x.dtype):
        strict = backend == "native"
        xc, vc, frame, origin = xf.contiguous(), vf.contiguous(), frame.contiguous(), origin.contiguous()
        faces, table, blocks, count = p2g(xc, vc, m.contiguous(), frame, origin, h, r, k, strict)
        _, field, overflow = pressure(faces, table, blocks, count, target, dtt, h, r, *solve, grid.active_capacity,
                                      strict)
        x1, v1 = g2p(xc, vc, field, table, frame, origin, free, dtt, h, r, pic, strict)
    else:
        stencils: list = []
        faces, table, blocks, count = p2g_sparse(xf, vf, m, frame, origin, h, r, k, stencils)
        _, field, overflow = pressure_sparse(faces, table, blocks, count, target, dtt, h, r, *solve,
                                             grid.active_capacity)
        x1, v1 = g2p_sparse(xf, vf, field, table, frame, origin, free, dtt, h, r, pic, stencils)
    if cfg.detailed_collisions:
        x1, v1 = _after_detailed_collisions(grid, xf, x1, v1, m, frame, free)
    out = x1.reshape(x.shape), v1.reshape(v.shape)
    return out + (overflow.any(),) if with_overflow else out


def _after_detailed_collisions(grid, x, x1, v1, m, frame, free):
    """Detailed collisions on the grid part's output x1, v1 (B, P, 3), in the head frame; the
    relative velocity is taken against the rigid motion at the input positions x, as the grid
    part did. Returns the corrected (x, v) (B, P, 3)."""
    xl, vl = to_head(frame, x1, v1, x_rigid=x)
    p = x.shape[1]
    free_p = free.repeat(p // free.shape[0])
    cx, cv = detailed_collisions(grid, xl, vl, m, free_p)
    free3 = free_p[None, :, None]
    rot = frame[:, :3]
    dx = torch.einsum("bij,bpj->bpi", rot, torch.where(free3, cx, torch.zeros_like(cx)))
    dv = torch.einsum("bij,bpj->bpi", rot, torch.where(free3, cv, torch.zeros_like(cv)))
    return x1 + dx, v1 + dv


def make_stage(grid: Optional[HairHairGrid], mass, free: Optional[torch.Tensor] = None,
               backend: str = "auto") -> Optional[Callable]:
    """Wrap :func:`hair_hair_stage` as an integrator stage ``(x, v, pose, dt, state) -> (x, v)``.

    Args: grid (None → returns None), mass kg broadcastable to (..., S, N), free (N,) or (S, N)
    bool, backend as in :func:`hair_hair_stage`.
    """
    if grid is None:
        return None
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}; got {backend!r}")

    def stage(x, v, pose, dt, state=None):
        return hair_hair_stage(grid, x, v, mass, pose, dt, free, backend)

    return stage
