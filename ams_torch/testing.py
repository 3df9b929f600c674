"""Input factories shared by the tests and the benchmarks (library code never imports this module).

Simple, deterministic grooms (metres, seconds, head frame with +y up):
``sphere_groom`` (strands on the upper half of a sphere "head"), ``curly_strand``,
``wisp``, ``head_groom`` and ``two_wisps`` (head motions: :mod:`ams_torch.apps.motion`).
"""
from __future__ import annotations

import math

import torch

from ams_torch.apps.identify import at_material_points
from ams_torch.grooms.simple import curly_strand, sphere_groom, wisp

__all__ = ["sphere_groom", "curly_strand", "wisp", "head_groom", "two_wisps", "shape_deviation", "at_material_points",
           "total_energy"]


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


def head_groom(strands=1000, particles=32, radius=0.1, length=0.25, seed=0, dtype=torch.float64):
    """Strands on the upper part of a sphere "head" of ``radius`` m at the origin (head frame, +y
    up): each leaves the scalp along the normal and turns outward-and-down over ``length`` m
    (±10 %). Vectorised and deterministic for a seed (the hair–hair tests' and benchmark's input).
    Returns (strands, particles, 3) metres."""
    g = torch.Generator().manual_seed(seed)
    i = torch.arange(strands, dtype=torch.float64)
    y = 1 - (i + 0.5) / strands * 0.95  # y ∈ (0.05, 1): Fibonacci points on the cap
    t = math.pi * (3 - math.sqrt(5)) * i
    rxz = (1 - y * y).sqrt()
    n = torch.stack((rxz * t.cos(), y, rxz * t.sin()), -1)
    n = n + 0.01 * torch.randn(strands, 3, generator=g, dtype=torch.float64)
    n = n / n.norm(dim=-1, keepdim=True)
    horiz = n * torch.tensor([1.0, 0.0, 1.0], dtype=torch.float64)
    hn = horiz.norm(dim=-1, keepdim=True)
    horiz = torch.where(hn > 1e-3, horiz / hn.clamp_min(1e-9), torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64))
    down = torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64)
    s = torch.linspace(0, 1, particles - 1, dtype=torch.float64)
    w = (3 * s).clamp(max=1.0)
    w = (w * w * (3 - 2 * w))[None, :, None]  # smoothstep: normal → outward-and-down
    d = (1 - w) * n[:, None, :] + w * (0.35 * horiz + down)[:, None, :]
    d = d / d.norm(dim=-1, keepdim=True)
    step = length * (1 + 0.1 * (2 * torch.rand(strands, 1, 1, generator=g, dtype=torch.float64) - 1)) / (particles - 1)
    x = torch.cat((radius * n[:, None, :], radius * n[:, None, :] + torch.cumsum(step * d, 1)), 1)
    return x.to(dtype)


def two_wisps(strands=64, n=8, width=0.04, length=0.08, gap=0.05, seed=0, dtype=torch.float64):
    """Two wisps of vertical strands with random roots, side by side along x. Returns (2·strands, n, 3)."""
    g = torch.Generator().manual_seed(seed)
    out = []
    for cx in (-gap / 2, gap / 2):
        roots = (torch.rand(strands, 3, generator=g, dtype=torch.float64) - 0.5) * width
        roots[:, 1] = 0
        roots[:, 0] += cx
        y = -torch.linspace(0, length, n, dtype=torch.float64)
        out.append(roots[:, None, :] + torch.stack((0 * y, y, 0 * y), -1)[None])
    return torch.cat(out).to(dtype)
