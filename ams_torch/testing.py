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

__all__ = ["sphere_groom", "curly_strand", "wisp", "shake_poses", "shape_deviation", "at_material_points",
           "total_energy"]


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


def at_material_points(rest: torch.Tensor, x: torch.Tensor, points: int = 33) -> torch.Tensor:
    """Positions of x at fixed material points: the rest arc-length fractions k / (points − 1).

    rest: (S, N, 3) m, the rest shape that defines arc length; x: (..., S, N, 3) m, a simulated
    state of that groom. Each material point is interpolated linearly along the simulated
    polyline between the two particles whose rest arc lengths bracket it, so grooms of
    different N can be compared point for point (errors in N are measured this way, not by
    particle index). Returns (..., S, points, 3) m.
    """
    seg = (rest[:, 1:] - rest[:, :-1]).norm(dim=-1)
    arc = torch.nn.functional.pad(seg.cumsum(-1), (1, 0))
    arc = arc / arc[:, -1:]
    u = torch.linspace(0, 1, points, dtype=rest.dtype, device=rest.device).expand(rest.shape[0], points).contiguous()
    idx = torch.searchsorted(arc.contiguous(), u).clamp(1, rest.shape[1] - 1)  # (S, points)
    a0, a1 = arc.gather(1, idx - 1), arc.gather(1, idx)
    t = ((u - a0) / (a1 - a0)).clamp(0, 1)[..., None]
    lead = x.shape[:-3]
    gather = lambda i: torch.gather(x, -2, i[..., None].expand(lead + i.shape + (3,)))  # noqa: E731
    x0, x1 = gather(idx - 1), gather(idx)
    return x0 + t.to(x.dtype) * (x1 - x0)


def total_energy(sim, state) -> torch.Tensor:
    """Conservative energy of a state, J: () tensor, summed over strands.

    Kinetic ½ m |v|² plus the spring potentials ½ κ (|x_{i+k} − x_i| − l_k)² of the edge (k = 1),
    bend (k = 2) and torsion (k = 3) springs, the integrity springs ½ κ_I |y − x|² to the ghosts
    y, and the angular couple ½ κ_α |e| θ² (θ the angle between edge e and its ghost edge), with
    the simulator's per-segment coefficients. ``state.x``, ``state.v``: (S, N, 3) m, m/s (one
    scene; no batch dims). The energy that gravity, drag, inextensibility, contact and the
    non-Hookean law add or remove is not in it: compare it across steps without them.
    """
    from ams_torch.sim.model import coefficients

    m = sim.model
    c = coefficients(m)
    x, v = state.x, state.v
    e = 0.5 * (c.mass * (v * v).sum(-1)).sum()
    for k, kappa in ((1, c.edge), (2, c.bend), (3, c.torsion)):
        length = (x[:, k:] - x[:, :-k]).norm(dim=-1)
        e = e + 0.5 * (kappa * (length - m.rest_lengths[k - 1]) ** 2).sum()
    y = state.ghosts()
    e = e + 0.5 * (c.integrity * ((y - x) ** 2).sum(-1)).sum()
    ed = x[:, 1:] - x[:, :-1]
    g = y[:, 1:] - y[:, :-1]
    cos = (ed * g).sum(-1) / (ed.norm(dim=-1) * g.norm(dim=-1))
    theta = torch.acos(cos.clamp(-1, 1))
    return e + 0.5 * (c.angular * ed.norm(dim=-1) * theta ** 2).sum()
