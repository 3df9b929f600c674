"""What the registered ops of the step share: the dtypes their native kernels take, and a pose's
tensors in the layout the ops read (batch () or the scenes')."""
from __future__ import annotations

from typing import Optional

import torch

from ams_torch.geometry.pose import Pose

__all__ = ["NATIVE_DTYPES", "as_like", "pose_tensors"]

#: the dtypes of the native kernels (others take the torch definition)
NATIVE_DTYPES = (torch.float32, torch.float64)


def as_like(t: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """t on x's device and dtype (t itself when it already is)."""
    return t if t.dtype == x.dtype and t.device == x.device else t.to(device=x.device, dtype=x.dtype)


def pose_tensors(pose: Optional[Pose], x: torch.Tensor) -> tuple:
    """[R, t, lin, ω] for the op (batch () or x's scenes) and whether the pose has velocities."""
    batch = x.shape[:-3]
    if pose is None:
        pose = Pose.identity(device=x.device, dtype=x.dtype)
    r, t = as_like(pose.rotation, x), as_like(pose.translation, x)
    vel = pose.has_velocity
    lin, ang = (as_like(pose.linear_velocity, x), as_like(pose.angular_velocity, x)) if vel else (t, t)
    out = []
    for a, tail in ((r, 2), (t, 1), (lin, 1), (ang, 1)):
        if tuple(a.shape[:-tail]) not in ((), tuple(batch)):  # a prefix of the scene dims: broadcast
            own = a.shape[:-tail]
            a = a.reshape(own + (1,) * (len(batch) - len(own)) + a.shape[-tail:]).expand(
                batch + a.shape[-tail:]).contiguous()
        out.append(a)
    return out, vel
