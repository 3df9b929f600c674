"""The end of a frame (SPEC §4): pinned particles take the head's rigid velocity, and every
particle's speed relative to the head is measured for the divergence flag.

:func:`pin_and_speed` is the definition (torch). :func:`native_finish` runs it as one registered
op, ``torch.ops.ams_torch.finish``, whose CPU and CUDA kernels (``csrc/frame/finish.h``, in the
libraries ``cpu`` / ``cuda`` of :mod:`ams_torch.native.build`) do the same
arithmetic in one pass over the particles: the torch definition is five whole-array passes
(cross product, sum, select, difference, norm) that cost as much as the fused frame kernel
itself at 10k × 32 on a CPU. Anything the kernels cannot take (a gradient to keep, another
dtype or device, a pose without velocities) goes to the definition.
"""
from __future__ import annotations

from typing import List, Tuple

import torch

from ams_torch.geometry.pose import Pose
from ams_torch.native.dispatch import NATIVE_DTYPES, native_available, native_inputs, native_namespace
from ams_torch.sim.op_support import pose_tensors

__all__ = ["pin_and_speed", "native_finish", "native_finish_supported", "native_finish_diff_supported",
           "finish_op"]


def pin_and_speed(x: torch.Tensor, v: torch.Tensor, pinned: torch.Tensor, pose: Pose) -> tuple:
    """The frame's end, by definition.

    Args:
        x, v: (..., S, N, 3) m, m/s at the end of the frame.
        pinned: (S, N) bool, the particles that move with the head.
        pose: the head at the end of the frame (its velocities give the rigid velocity
            ``u + ω × (x − t)``; none: the head is at rest).
    Returns:
        (v', speed): v' (..., S, N, 3) m/s, the head's rigid velocity on pinned particles and v
        elsewhere; speed (..., S, N) m/s, |v' − rigid velocity| (NaN/Inf where x, v or the pose
        are not finite).
    """
    head = pose.velocity_at(x)  # the head's rigid velocity at every particle, (..., S, N, 3)
    v = torch.where(pinned[..., None], head, v)
    return v, torch.linalg.vector_norm(v - head, dim=-1)


def _finish_torch(x, v, num_pinned, pose):
    n = x.shape[-2]
    pinned = torch.arange(n, device=x.device)[None, :] < num_pinned[:, None]
    t, lin, ang = pose
    batch = t.shape[:-1] if t.numel() > 3 else ()
    rot = torch.eye(3, dtype=x.dtype, device=x.device).expand(batch + (3, 3))
    shaped = [a.reshape(batch + (3,)) for a in (t, lin, ang)]
    out, speed = pin_and_speed(x, v, pinned, Pose(rot, *shaped, check=False))
    return out.contiguous(), speed.contiguous()


@torch.library.custom_op("ams_torch::finish", mutates_args=())
def finish_op(x: torch.Tensor, v: torch.Tensor, num_pinned: torch.Tensor,
              pose: List[torch.Tensor]) -> Tuple[torch.Tensor, torch.Tensor]:
    """Registered op ``ams_torch::finish``; default (any device): :func:`pin_and_speed`.

    x, v: (..., S, N, 3) m, m/s; num_pinned: (S,) int64, the pinned prefix of each strand; pose:
    [translation (P, 3) m, linear velocity (P, 3) m/s, angular velocity (P, 3) rad/s] of the head
    at the end of the frame, P = 1 (shape (3,)) or the scenes' batch. Returns new contiguous
    (v' (..., S, N, 3), speed (..., S, N)).
    """
    return _finish_torch(x, v, num_pinned, pose)


def _finish_kernel(x, v, num_pinned, pose):
    ns = native_namespace("frame", x)  # inputs may keep their gradient: this op has its own adjoint
    if ns is None:
        return _finish_torch(x, v, num_pinned, pose)
    return tuple(ns.finish(x, v, num_pinned, pose))


finish_op.register_kernel("cpu")(_finish_kernel)
finish_op.register_kernel("cuda")(_finish_kernel)


@finish_op.register_fake
def _finish_fake(x, v, num_pinned, pose):
    return torch.empty_like(v, memory_format=torch.contiguous_format), x.new_empty(x.shape[:-1])


def native_finish_supported(x: torch.Tensor, v: torch.Tensor, pose: Pose) -> bool:
    """Whether the finish kernels take these inputs (traceable: Python checks of dtypes, devices,
    flags and ``requires_grad`` only): float32/float64 on CPU/CUDA, a pose with velocities, and
    no gradient to keep."""
    if not pose.has_velocity or v.dtype != x.dtype:
        return False
    return native_inputs(x, (x, v, pose.translation, pose.linear_velocity, pose.angular_velocity))


def native_finish(model, x: torch.Tensor, v: torch.Tensor, pose: Pose) -> tuple:
    """:func:`pin_and_speed` for ``model.pinned`` by the registered op (its native kernel when
    built). x, v: (..., S, N, 3) m, m/s; pose: the head at the end of the frame. Returns (v',
    speed) as :func:`pin_and_speed`. Traceable (Python checks of types and flags only)."""
    if not native_finish_supported(x, v, pose):
        return pin_and_speed(x, v, model.pinned, pose)
    (_, t, lin, ang), _ = pose_tensors(pose, x)
    return finish_op(x, v, model.num_pinned, [t, lin, ang])


# -- the adjoint (gradient frames of a native simulator) ----------------------------------------------

def _finish_setup(ctx, inputs, output):
    x, v, num_pinned, pose = inputs
    ctx.save_for_backward(x, v, num_pinned, *pose)


def _finish_backward(ctx, g_v, g_speed):
    """The vector-Jacobian product of ``ams_torch::finish``: the native ``finish_adjoint``
    (``csrc/frame/finish_adjoint.h``; op group ``finish_adjoint``) where built, else autograd on the
    torch definition. Returns the adjoints of x, v, num_pinned (None) and the pose [t, lin, ang]."""
    x, v, num_pinned, t, lin, ang = ctx.saved_tensors
    g_v = torch.zeros_like(v) if g_v is None else g_v.contiguous()
    g_speed = None if g_speed is None else g_speed.contiguous()
    ns = native_namespace("finish_adjoint", x)
    if ns is None or not hasattr(ns, "finish_adjoint"):
        leaves = [a.detach().requires_grad_() for a in (x, v, t, lin, ang)]
        with torch.enable_grad():
            out, speed = _finish_torch(leaves[0], leaves[1], num_pinned, leaves[2:])
            pairs = [(out, g_v)] + ([(speed, g_speed)] if g_speed is not None else [])
            grads = torch.autograd.grad([o for o, _ in pairs], leaves, [g for _, g in pairs], allow_unused=True)
        grads = [torch.zeros_like(a) if g is None else g for g, a in zip(grads, leaves)]
        return grads[0], grads[1], None, list(grads[2:])
    g_x, g_vin, g_pose = ns.finish_adjoint(x, v, num_pinned, [t, lin, ang], g_v, g_speed)
    strands = x.shape[-3]
    per_scene = g_pose.reshape(-1, strands, 9).sum(1)  # (B, 9): the strands' sums, in one order
    pose_grads = []
    for k, a in enumerate((t, lin, ang)):
        part = per_scene[:, 3 * k:3 * k + 3]
        pose_grads.append((part.sum(0) if a.numel() == 3 else part).reshape(a.shape))
    return g_x, g_vin, None, pose_grads


finish_op.register_autograd(_finish_backward, setup_context=_finish_setup)


def native_finish_diff_supported(x: torch.Tensor, v: torch.Tensor, pose: Pose) -> bool:
    """Whether a gradient frame's end can run the native forward and adjoint: a pose with
    velocities, float32/float64 on CPU/CUDA, and the kernels built (on first call)."""
    if not pose.has_velocity or v.dtype != x.dtype or x.dtype not in NATIVE_DTYPES:
        return False
    return native_available("frame", x.device, x.dtype) and native_available("finish_adjoint", x.device, x.dtype)


class _NativeYieldAdjoint(torch.autograd.Function):
    """The plastic yield's anchors (:func:`ams_torch.sim.forces.integrity_yield`) with its native
    adjoint: the forward is the torch definition (no graph kept; no native forward exists: the
    stage is a few elementwise operations), the backward the ``yield_adjoint`` kernel
    (``csrc/frame/finish_adjoint.h``). Inputs: x_local, anchor (..., S, N, 3) m head frame, limit
    (S, N) m (breaking × segment length), free (S, N) bool. Returns the new anchors."""

    @staticmethod
    def forward(ctx, x_local, anchor, limit, free):
        from ams_torch.sim.forces import safe_normalize

        ctx.save_for_backward(x_local, anchor, limit, free)
        unit, dist = safe_normalize(anchor - x_local)
        over = (dist > limit) & free
        return torch.where(over[..., None], x_local + limit[..., None] * unit, anchor)

    @staticmethod
    def backward(ctx, g):
        x_local, anchor, limit, free = ctx.saved_tensors
        ns = native_namespace("finish_adjoint", x_local)
        gx, ga, gl = ns.yield_adjoint(x_local.contiguous(), anchor.contiguous(), limit.contiguous(), free.contiguous(),
                                      g.contiguous())
        g_limit = gl.reshape((-1,) + tuple(limit.shape)).sum(0) if ctx.needs_input_grad[2] else None
        return gx, ga, g_limit, None


def native_yield_diff(x_local: torch.Tensor, anchor: torch.Tensor, segment_length: torch.Tensor, breaking,
                      free: torch.Tensor) -> torch.Tensor:
    """:func:`~ams_torch.sim.forces.integrity_yield` in a gradient frame of a native simulator: the
    same values, its adjoint by the native ``yield_adjoint`` where built (float32 / float64 on CPU /
    CUDA), else the torch definition itself. Arguments and result as that function."""
    from ams_torch.sim.forces import integrity_yield

    if (x_local.dtype not in NATIVE_DTYPES or anchor.dtype != x_local.dtype
            or not native_available("finish_adjoint", x_local.device, x_local.dtype)):
        return integrity_yield(x_local, anchor, segment_length, breaking, free)
    limit = breaking * segment_length
    free_b = free.to(device=x_local.device, dtype=torch.bool).expand(limit.shape)
    return _NativeYieldAdjoint.apply(x_local, anchor, limit.to(x_local.dtype), free_b)
