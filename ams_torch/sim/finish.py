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
from ams_torch.native.dispatch import native_inputs, native_namespace
from ams_torch.sim.op_support import pose_tensors

__all__ = ["pin_and_speed", "native_finish", "native_finish_supported", "finish_op"]


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
    ns = native_namespace("frame", x, (x, v, *pose))
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
