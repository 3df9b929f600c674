"""The hair–solid contact response (SPEC §8, paper Eq. 10), as dense masked tensor updates.

Every particle is tested against every collider and the response is applied where the
particle is inside, with a fixed number of push-out passes. On a GPU and under torch.compile this
runs on every particle, masked: no gathers of contact particles, no data-dependent shapes or
branches, so the stage can be compiled and captured; eager on the CPU the response and its
push-out run on the inside particles only (gathered, then scattered back: the same arithmetic).
"""
from __future__ import annotations

from typing import Optional, Sequence, Tuple

import torch

from ams_torch.geometry.pose import Pose
from ams_torch.stages.collide.poses import flat_pose
from ams_torch.stages.collide.shapes import Collider

__all__ = ["collide", "collider_distances", "contact_response"]


def _world_to_local(xf: torch.Tensor, rot: torch.Tensor, trans: torch.Tensor) -> torch.Tensor:
    """xf (B, K, 3), rot (B, 3, 3), trans (B, 3) → rows Rᵀ (x − T), as x R − T R in one fused op."""
    offset = -(trans[:, None, :] @ rot)  # (B, 1, 3)
    if rot.shape[0] == 1:
        return torch.addmm(offset[0], xf[0], rot[0])[None]
    return torch.baddbmm(offset, xf, rot)


def collider_distances(x: torch.Tensor, colliders: Sequence[Collider], world_poses: Sequence[Optional[Pose]]
                       ) -> torch.Tensor:
    """Signed distance of every particle to every collider (metres, negative inside).

    x: (..., S, N, 3) world positions, metres → (C, ..., S, N) for C colliders.
    """
    if len(colliders) == 0:
        return x.new_zeros((0,) + x.shape[:-1])
    batch = x.shape[:-3]
    xf = x.reshape(-1, x.shape[-3] * x.shape[-2], 3)
    out = []
    for col, pose in zip(colliders, world_poses):
        rot, trans, _, _ = flat_pose(pose, batch, x)
        out.append(col.distance(_world_to_local(xf, rot, trans)).reshape(x.shape[:-1]))
    return torch.stack(out)


def _length(t: torch.Tensor, dim: int) -> torch.Tensor:
    """|t| along ``dim`` (of size 3). Along the last dim: ``norm``; along another (rows, each
    component contiguous along the particles): the square root of the sum of squares, with
    ``norm``'s zero gradient at zero (never NaN)."""
    if dim == -1:
        return t.norm(dim=-1)
    sq = (t * t).sum(dim)
    nonzero = sq > 0
    return torch.where(nonzero, torch.sqrt(torch.where(nonzero, sq, 1.0)), 0.0)


def contact_response(v: torch.Tensor, vc: torch.Tensor, n: torch.Tensor, friction, dim: int = -1) -> torch.Tensor:
    """Coulomb contact response of SPEC §8 for particles in contact.

    v, vc: (..., 3) m/s, particle and collider velocities at the particle; n: (..., 3) unit
    outward normal; friction μ ≥ 0; dim: the vectors' dim (default the last; the collision
    stage keeps particles as rows (B, 3, P), dim=1). With v_rel = v − v_c split into normal
    v_N = (v_rel·n) n and tangential v_T, the approaching normal part is removed
    (Δv_N = max(0, −v_rel·n)) and friction scales the tangential part:

        v' = v_c + max(v_rel·n, 0) n + max(0, 1 − μ Δv_N / |v_T|) v_T      (|v_T| = 0 → v_T = 0)

    Returns v' (..., 3) m/s.
    """
    vrel = v - vc
    vn = (vrel * n).sum(dim, keepdim=True)
    vt = vrel - vn * n
    vt_len = _length(vt, dim).unsqueeze(dim)
    dvn = (-vn).clamp_min(0)
    keep = (1 - friction * dvn / vt_len.clamp_min(1e-30)).clamp_min(0)
    keep = torch.where(vt_len > 0, keep, torch.zeros_like(keep))
    return vc + vn.clamp_min(0) * n + keep * vt


def collide(x: torch.Tensor, v: torch.Tensor, dt, colliders: Sequence[Collider],
            world_poses: Sequence[Optional[Pose]], free: Optional[torch.Tensor] = None
            ) -> Tuple[torch.Tensor, torch.Tensor]:
    """Hair–solid contact response for one frame (SPEC §8), colliders processed in order.

    Args:
        x: (..., S, N, 3) world positions at the end of the frame (after the substeps,
            inextensibility and hair–hair), metres. They are the candidate positions
            ``x_start + Δt v`` of SPEC §8, so contact is tested with σ(x) < 0 directly.
        v: (..., S, N, 3) world velocities, m/s.
        dt: frame length Δt, seconds (0 gives pure projection, see below).
        colliders: sequence of :class:`Collider`; empty → (x, v) returned unchanged, no work.
        world_poses: world :class:`Pose` of each collider at the end of the frame, batch dims
            equal to x's leading ``...`` or none; velocities give the collider's rigid velocity
            field (``None`` velocities = static). See :func:`resolve_world_poses`.
        free: optional (N,) or (S, N) bool, True for simulated particles; pinned ones are never
            touched.

    For each particle with σ(x) < 0 the velocity becomes :func:`contact_response` with the
    collider's velocity v_c at x and n = ∇σ/|∇σ| (world); the position is made consistent with
    it, x ← x + Δt (v' − v) (that is x_start + Δt v', SPEC §8: with high friction a resting
    particle does not creep), and if it is still inside it is pushed out along the normal by the
    penetration depth, x' = x − σ(x) n(x), ``collider.projection_iterations`` times (a fixed
    number of passes; each leaves particles already outside where they are). Differentiable
    w.r.t. x and v.

    Returns: (x', v'), same shapes as x, v.
    """
    if len(colliders) == 0:
        return x, v
    if len(world_poses) != len(colliders):
        raise ValueError(f"got {len(world_poses)} world poses for {len(colliders)} colliders")
    if x.shape != v.shape or x.dim() < 3 or x.shape[-1] != 3:
        raise ValueError(f"x and v must both be (..., S, N, 3), got {tuple(x.shape)} and {tuple(v.shape)}")
    shape, batch = x.shape, x.shape[:-3]
    s_count, n_count = shape[-3], shape[-2]
    # particles as rows (B, 3, P): every op below runs along P
    xr = x.reshape(-1, s_count * n_count, 3).transpose(1, 2).contiguous()
    vr = v.reshape(-1, s_count * n_count, 3).transpose(1, 2).contiguous()
    free_k = None
    if free is not None:
        free = torch.as_tensor(free, device=x.device).bool()
        if free.shape not in ((n_count,), (s_count, n_count)):
            raise ValueError(f"free mask must have shape ({n_count},) or ({s_count}, {n_count}); got "
                             f"{tuple(free.shape)}")
        free_k = free.expand(s_count, n_count).reshape(s_count * n_count)
    for col, pose in zip(colliders, world_poses):
        xr, vr, _, _ = _response_rows(col, flat_pose(pose, batch, x), xr, vr, dt, free_k)
    return (xr.transpose(1, 2).contiguous().reshape(shape), vr.transpose(1, 2).contiguous().reshape(shape))


def _to_local_rows(xr: torch.Tensor, rot: torch.Tensor, trans: torch.Tensor) -> torch.Tensor:
    """xr (B, 3, P) world rows, rot (B, 3, 3), trans (B, 3) → local rows Rᵀ (x − T) = Rᵀ x − Rᵀ T."""
    offset = -(rot.transpose(1, 2) @ trans[:, :, None])  # (B, 3, 1)
    if rot.shape[0] == 1:
        return torch.addmm(offset[0], rot[0].t(), xr[0])[None]
    return torch.baddbmm(offset, rot.transpose(1, 2), xr)


def _rotate_rows(d: torch.Tensor, rot: torch.Tensor) -> torch.Tensor:
    """R d for rows d (B, 3, P) with R (B, 3, 3)."""
    if rot.shape[0] == 1:
        return (rot[0] @ d[0])[None]
    return rot @ d


def _cross_rows(a: torch.Tensor, r: torch.Tensor) -> torch.Tensor:
    """a × r for a (B, 3) and rows r (B, 3, P): (B, 3, P), component by component (the cross
    product's own formula, each term a long vector op)."""
    a0, a1, a2 = (a[:, i, None] for i in range(3))
    r0, r1, r2 = r.unbind(1)
    return torch.stack((a1 * r2 - a2 * r1, a2 * r0 - a0 * r2, a0 * r1 - a1 * r0), 1)


def _sample_rows(col: Collider, local: torch.Tensor) -> tuple:
    """σ (B, P) and the local normals as rows (B, 3, P) at local rows (B, 3, P)."""
    b, _, p = local.shape
    rows = local[0] if b == 1 else local.transpose(0, 1).reshape(3, b * p)
    by_rows = getattr(col, "distance_and_normal_rows", None)
    if by_rows is not None:
        sigma, normal = by_rows(rows)
    else:  # a collider given by its distance_and_normal alone (e.g. the native op's views)
        sigma, normal = col.distance_and_normal(rows.t().contiguous())
        normal = normal.t()
    return sigma.reshape(b, p), normal.reshape(3, b, p).transpose(0, 1)


def _respond(col: Collider, flat: tuple, xr: torch.Tensor, vr: torch.Tensor, n_local: torch.Tensor, dt,
             skin: float, friction) -> tuple:
    """The response and the push-out passes of particles as rows xr, vr (B, 3, P) m, m/s with their
    local normals n_local (B, 3, P): (x', v') as rows, for every particle (the caller keeps them
    where the particle is inside)."""
    rot, trans, lin, ang = flat
    n = _rotate_rows(n_local, rot)
    if lin is not None:
        vc = lin[:, :, None] + _cross_rows(ang, xr - trans[:, :, None])
    else:
        vc = torch.zeros_like(vr)
    v_new = contact_response(vr, vc, n, col.friction if friction is None else friction, dim=1)
    x_new = xr + dt * (v_new - vr)
    for _ in range(max(1, col.projection_iterations)):
        s_new, nl_new = _sample_rows(col, _to_local_rows(x_new, rot, trans))
        depth = (skin - s_new).clamp_min(0) if skin else (-s_new).clamp_min(0)
        x_new = x_new + depth[:, None, :] * _rotate_rows(nl_new, rot)
    return x_new, v_new


def _compacts(xr: torch.Tensor, rot: torch.Tensor) -> bool:
    """Whether the response may run on the inside particles only (:func:`_response_rows`): CPU
    tensors in eager mode (the particles' count is known on the host, no device to wait for) and one
    pose for every scene. On a GPU, under torch.compile or in a CUDA graph the response runs on
    every particle, masked (no data-dependent shape, no host sync: capturable)."""
    return xr.device.type == "cpu" and rot.shape[0] == 1 and not torch.compiler.is_compiling()


def _response_rows(col: Collider, flat: tuple, xr: torch.Tensor, vr: torch.Tensor, dt, free_k=None, *,
                   tol: float = 0.0, skin: float = 0.0, friction=None) -> tuple:
    """:func:`collider_response` on particles as rows: xr, vr (B, 3, P) m, m/s. Returns
    (x', v') as rows (B, 3, P), σ (B, P) and inside (B, P).

    Each particle's arithmetic is the same on both routes: masked (every particle, kept where
    inside) or, where :func:`_compacts`, on the inside particles gathered into rows (1, 3, K) and
    scattered back (a particle in contact is ~1 % of a groom: the push-out passes' samples of the
    collider are the stage's cost)."""
    rot, trans, _, _ = flat
    sigma, n_local = _sample_rows(col, _to_local_rows(xr, rot, trans))
    inside = sigma < -tol if tol else sigma < 0
    if free_k is not None:
        inside = inside & free_k
    if _compacts(xr, rot):
        b, _, p = xr.shape
        idx = inside.reshape(-1).nonzero().squeeze(1)  # (K,) over the scenes' particles
        if idx.numel() == 0:
            return xr, vr, sigma, inside
        cols = [t.transpose(0, 1).reshape(3, b * p) if b > 1 else t[0] for t in (xr, vr, n_local)]
        x_k, v_k = _respond(col, flat, cols[0][:, idx][None], cols[1][:, idx][None], cols[2][:, idx][None], dt, skin,
                            friction)
        out = [c.index_copy(1, idx, k[0]) for c, k in ((cols[0], x_k), (cols[1], v_k))]
        out = [o.reshape(3, b, p).transpose(0, 1) if b > 1 else o[None] for o in out]
        return out[0], out[1], sigma, inside
    x_new, v_new = _respond(col, flat, xr, vr, n_local, dt, skin, friction)
    mask = inside[:, None, :]
    return torch.where(mask, x_new, xr), torch.where(mask, v_new, vr), sigma, inside


def collider_response(col: Collider, flat: tuple, xf: torch.Tensor, vf: torch.Tensor, dt, free_k=None, *,
                      tol: float = 0.0, skin: float = 0.0, friction=None) -> tuple:
    """One collider's part of :func:`collide`, on flattened particles.

    Args:
        col: the collider; flat: its world pose as :func:`~ams_torch.stages.collide.poses.flat_pose`
            gives it (R (B, 3, 3), t (B, 3) m, linear (B, 3) m/s and angular (B, 3) rad/s
            velocity, or None for a static collider).
        xf, vf: (B, P, 3) m, m/s; dt: s; free_k: (P,) bool or None (all free).
        tol, skin, friction: study knobs (scripts/roller_coaster_convergence.py); the defaults
            are :func:`collide` itself: contact is σ < −tol, the push-out goes to σ = +skin, and
            ``friction`` replaces the collider's μ when given.
    Returns:
        (x', v', σ, inside): (B, P, 3) m, m/s after the response; σ (B, P) m at the input
        positions and inside (B, P) bool, the particles it moved.
    """
    xr, vr, sigma, inside = _response_rows(col, flat, xf.transpose(1, 2).contiguous(), vf.transpose(1, 2).contiguous(),
                                           dt, free_k, tol=tol, skin=skin, friction=friction)
    return xr.transpose(1, 2).contiguous(), vr.transpose(1, 2).contiguous(), sigma, inside
