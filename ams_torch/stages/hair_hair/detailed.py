"""Detailed collisions of the hair–hair stage: particle repulsion between strands (torch).

They run after the grid part (torch or native), on its output, in the head frame. A sort-based
spatial hash of cell size ``collision_radius``; each particle looks at up to
``collision_max_per_cell`` particles in each of its 27 neighbouring hash cells (more than that
in one cell are not seen: an approximation that the parameter controls), skipping particles of
its own strand. For each pair closer than the radius, positions are pushed apart by
``collision_stiffness`` of the overlap and the approaching part of the relative normal velocity
is removed (inelastic), shared by inverse mass (pinned particles are immovable), averaged over
each particle's contacts. Work O(P · 27 · K), memory O(P · 3 · K); static shapes, no host sync.
"""
from __future__ import annotations

import torch

__all__ = ["detailed_collisions"]


def detailed_collisions(grid, xl: torch.Tensor, vl: torch.Tensor, m: torch.Tensor, free_p: torch.Tensor):
    """Particle repulsion between strands through a sort-based spatial hash (head frame).

    grid: the :class:`HairHairGrid`; xl, vl: (B, P, 3) head-frame positions (m) and relative
    velocities (m/s) after the grid part; m: (B, P) kg; free_p: (P,) bool. Returns (dx, dv)
    (B, P, 3) corrections (m, m/s), not yet masked by ``free_p`` for the particle itself.
    The particles are sorted once by hash-cell key; each of the 9 (x, y) neighbour offsets is
    then one batched lookup (``searchsorted``) of up to K candidates in each of the 3 cells along
    z, so peak memory is O(P · 3 · K), not O(P · 27 · K).
    """
    cfg = grid.config
    r = cfg.collision_radius
    k = cfg.collision_max_per_cell
    hs = grid.hash_size
    b, p, _ = xl.shape
    dev, dtype = xl.device, xl.dtype
    cell = torch.floor((xl - grid.origin.to(dtype)) / r).clamp(-1, hs - 2).long() + 1  # in [0, hs − 1]
    scene = torch.arange(b, device=dev)[:, None]

    key = ((scene * hs + cell[..., 0]) * hs + cell[..., 1]) * hs + cell[..., 2]  # (B, P)
    sorted_key, order = torch.sort(key.reshape(-1))
    xf, vf = xl.reshape(b * p, 3), vl.reshape(b * p, 3)
    inv = free_p.to(dtype) / m  # (B, P) inverse mass, 0 for pinned particles
    inv_f = inv.reshape(-1)
    strand_i = (torch.arange(p, device=dev) // grid.num_particles)[None, :, None]
    slots = torch.arange(k, device=dev)
    oz = torch.arange(-1, 2, device=dev)  # the 3 offsets along z are one batched lookup
    push = torch.zeros_like(xl)
    stop = torch.zeros_like(xl)
    count = torch.zeros(b, p, device=dev, dtype=dtype)
    for ox in (-1, 0, 1):
        for oy in (-1, 0, 1):
            inside = torch.ones_like(key, dtype=torch.bool)
            for axis, o in enumerate((ox, oy)):
                if o:
                    ca = cell[..., axis] + o
                    inside = inside & (ca >= 0) & (ca < hs)
            cz = cell[..., 2, None] + oz  # (B, P, 3)
            inside = inside[..., None] & (cz >= 0) & (cz < hs)
            nkey = (key[..., None] + ((ox * hs) + oy) * hs + oz).reshape(-1)  # meaningful where inside
            start = torch.searchsorted(sorted_key, nkey).reshape(b, p, 3, 1)
            end = torch.searchsorted(sorted_key, nkey, right=True).reshape(b, p, 3, 1)
            slot = start + slots  # (B, P, 3, K)
            ok = ((slot < end) & inside[..., None]).reshape(b, p, 3 * k)
            j = order[slot.clamp_max(b * p - 1)].reshape(b, p, 3 * k)  # flat ids over B·P
            ok = ok & ((j % p) // grid.num_particles != strand_i)
            d = xl[:, :, None, :] - xf[j]
            dist = d.norm(dim=-1)
            ok = ok & (dist < r) & (dist > 0)
            nrm = d / torch.where(ok, dist, torch.ones_like(dist))[..., None]
            denom = inv[..., None] + inv_f[j]
            share = inv[..., None] / torch.where(denom > 0, denom, torch.ones_like(denom))
            wgt = torch.where(ok, share, torch.zeros_like(share))
            push = push + ((cfg.collision_stiffness * (r - dist) * wgt)[..., None] * nrm).sum(-2)
            vn = ((vl[:, :, None, :] - vf[j]) * nrm).sum(-1)
            stop = stop + (((-vn).clamp_min(0) * wgt)[..., None] * nrm).sum(-2)
            count = count + ok.sum(-1).to(dtype)
    count = count.clamp_min(1)[..., None]
    return push / count, stop / count
