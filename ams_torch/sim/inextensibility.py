"""Inextensibility after the substeps (SPEC §4): follow-the-leader with velocity correction.

Müller, Kim and Chentanez 2012, "Fast Simulation of Inextensible Hair and Fur" (DFTL):
walking from the root, each particle is moved onto the sphere of its rest edge length
around its (already corrected) predecessor; the correction d_i is fed back into the
velocities as ``v_i += (d_i − s·d_{i+1}) / Δt`` with s the damping factor, which removes
the non-physical momentum FTL alone would add.
"""
from __future__ import annotations

from typing import Optional

import torch


__all__ = ["follow_the_leader", "max_stretch"]


def follow_the_leader(x: torch.Tensor, v: torch.Tensor, edge_rest_length: torch.Tensor,
                      pinned: torch.Tensor, dt, damping: float,
                      fallback_dir: Optional[torch.Tensor] = None, *, limit: float = 0.0):
    """Project every edge back to its rest length, root to tip, and correct the velocities.

    Args:
        x: (..., S, N, 3) m, positions after the substeps.
        v: (..., S, N, 3) m/s.
        edge_rest_length: (S, N−1) m.
        pinned: (S, N) or (N,) bool; pinned particles are never moved (they lead).
        dt: the frame's length, s (the span over which the corrections happened).
        damping: s ∈ [0, 1] of DFTL (0: plain FTL velocities, 1: full correction).
        fallback_dir: (..., S, N−1, 3) unit directions used where an edge has collapsed
            to zero length (e.g. the rest directions carried by the head); without it
            such an edge stays collapsed. No NaN either way.
        limit: 0 (default): each edge is projected onto its rest length l. > 0: a strain
            limiter instead, each edge brought back into [(1 − limit) l, (1 + limit) l] with the
            same velocity correction (scripts/roller_coaster_convergence.py studies it).
    Returns:
        (x, v): (..., S, N, 3) each; with limit = 0 every free edge has its rest length to
        rounding.
    """
    n = x.shape[-2]
    pinned = pinned if pinned.dim() == 2 else pinned.expand(x.shape[-3], n)
    # the walk is sequential (N − 1 steps of small ops), so each step does the least: safe_normalize
    # inlined (its zero direction replaced by the fallback in the same where), the rest lengths and
    # masks sliced once, the corrections taken after the walk
    rests = edge_rest_length[..., None]  # (S, N − 1, 1)
    held = pinned[..., None]  # (S, N, 1)
    one = torch.ones_like(x[..., 0, 0])
    pts = [x[..., 0, :]]
    for i in range(1, n):
        xi = x[..., i, :]
        d = xi - pts[i - 1]
        sq = (d * d).sum(-1)
        nonzero = sq > 1e-20  # safe_normalize's test
        length = torch.sqrt(torch.where(nonzero, sq, one))
        unit = d / length[..., None]
        if fallback_dir is not None:
            unit = torch.where(nonzero[..., None], unit, fallback_dir[..., i - 1, :])
        else:
            unit = torch.where(nonzero[..., None], unit, torch.zeros_like(unit))
        rest = rests[..., i - 1, :]
        if limit:
            length = torch.where(nonzero, length, torch.zeros_like(length))[..., None]
            rest = torch.minimum(torch.maximum(length, (1 - limit) * rest), (1 + limit) * rest)
        new = torch.where(held[:, i], xi, pts[i - 1] + rest * unit)
        pts.append(new)
    x_new = torch.stack(pts, -2)
    # the corrections new − x (exactly 0 at the root, which never moves)
    zero = torch.zeros_like(x[..., :1, :])
    c = torch.cat((zero, x_new[..., 1:, :] - x[..., 1:, :]), -2)
    c_next = torch.cat((c[..., 1:, :], zero), -2)
    free = (~pinned).to(x.dtype)[..., None]
    v_new = v + free * (c - damping * c_next) / dt
    return x_new, v_new


def max_stretch(x: torch.Tensor, edge_rest_length: torch.Tensor) -> torch.Tensor:
    """Largest relative edge-length error |(|e| − l)/l| per strand: (..., S)."""
    length = (x[..., 1:, :] - x[..., :-1, :]).norm(dim=-1)
    return ((length - edge_rest_length) / edge_rest_length).abs().amax(-1)
