"""Input factories shared by the tests, the benchmarks and the demo.

Simple, deterministic grooms and motions (metres, seconds, head frame with +y up):
``sphere_groom`` (strands on the upper half of a sphere "head"), ``curly_strand``,
``wisp`` and ``shake_poses``.
"""
from __future__ import annotations

import math

import torch

from ams_torch.geometry.pose import Pose, axis_angle_to_matrix
from ams_torch.grooms.simple import curly_strand, sphere_groom, wisp

__all__ = ["sphere_groom", "curly_strand", "wisp", "shake_poses", "shape_deviation"]


def shake_poses(frames: int, dt: float, amplitude: float = 0.6, frequency: float = 1.5,
                axis=(0.0, 1.0, 0.0), translation_amplitude=(0.0, 0.0, 0.0), device=None,
                dtype=torch.float32) -> list:
    """A head shaking about ``axis``: angle(t) = amplitude·sin(2πft) radians, with exact
    angular velocity, plus an optional sinusoidal translation (metres, same frequency).
    Returns a list of :class:`Pose` for t = dt, 2dt, …, frames·dt (ends of frames)."""
    axis = torch.as_tensor(axis, dtype=torch.float64)
    axis = axis / axis.norm()
    ta = torch.as_tensor(translation_amplitude, dtype=torch.float64)
    poses = []
    w = 2 * math.pi * frequency
    for k in range(1, frames + 1):
        t = k * dt
        ang = amplitude * math.sin(w * t)
        omega = amplitude * w * math.cos(w * t)
        rot = axis_angle_to_matrix(axis * ang)
        trans = ta * math.sin(w * t)
        lin = ta * w * math.cos(w * t)
        poses.append(Pose(rot, trans, lin, axis * omega).to(device=device, dtype=dtype))
    return poses


def shape_deviation(x: torch.Tensor, rest: torch.Tensor, align: bool = False) -> torch.Tensor:
    """Mean particle distance (m) between x and rest, per strand: (..., S).

    With ``align=True`` each strand is first rigidly aligned to its rest shape (Kabsch), so
    only the loss of shape counts, not a rigid swing.
    """
    if not align:
        return (x - rest).norm(dim=-1).mean(-1)
    xc = x - x.mean(-2, keepdim=True)
    rc = rest - rest.mean(-2, keepdim=True)
    h = xc.transpose(-1, -2) @ rc
    u, _, vt = torch.linalg.svd(h)
    d = torch.sign(torch.linalg.det(u @ vt))
    diag = torch.ones_like(u[..., 0])
    diag = torch.cat((diag[..., :2], d[..., None]), -1)
    r = u @ torch.diag_embed(diag) @ vt
    return (xc @ r - rc).norm(dim=-1).mean(-1)
