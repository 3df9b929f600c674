"""Frames and particle ↔ grid transfers of the hair–hair stage: the torch definition.

Layout shared with the native kernels (``ams_torch/native/csrc/grid``):

* ``frame``: (B, 6, 3) per scene, rows 0–2 the head rotation R (world ← head), row 3 its
  translation T (m), row 4 its linear velocity V (m/s), row 5 its angular velocity W (rad/s,
  world frame). Missing velocities are zeros (which leaves every value exactly as if they
  were not subtracted).
* ``faces``: (B, 3, F, 2) with F = (R+1)·R·R: for each velocity component c, the face grid of
  dims ``face_dims(R, c)`` (R+1 samples along axis c, R along the others) flattened row-major,
  holding [..., 0] the P2G mass (kg) and [..., 1] the P2G c-momentum (kg·m/s, head frame,
  relative to the grid's rigid motion).
* face fields ``(B, 3, F)`` in the same flat layout; cell fields ``(B, R, R, R)``.
"""
from __future__ import annotations

import math
from typing import Optional, Tuple

import torch

from ams_torch.geometry.pose import Pose

__all__ = ["face_dims", "num_faces", "scene_frame", "to_head", "face_corners", "face_corner_rows", "face_stencil",
           "p2g_torch",
           "g2p_torch", "cell_mass", "grid_density"]


def face_dims(r: int, c: int) -> Tuple[int, int, int]:
    """Sample counts of the c-face grid: R+1 along axis c, R along the other two."""
    return tuple(r + 1 if d == c else r for d in range(3))


def num_faces(r: int) -> int:
    """F = (R+1)·R·R, faces per component."""
    return (r + 1) * r * r


def scene_frame(head_pose: Optional[Pose], lead: tuple, b: int, dtype, device) -> torch.Tensor:
    """The (B, 6, 3) frame tensor (module docstring) of ``head_pose`` broadcast to ``lead`` dims.

    head_pose: world ← head frame, batch dims broadcastable to ``lead``; None = identity at rest.
    """
    if head_pose is None:
        eye = torch.eye(3, device=device, dtype=dtype)
        return torch.cat((eye, torch.zeros(3, 3, device=device, dtype=dtype))).expand(b, 6, 3)
    def flat(t, tail):  # no op dispatched for what already has the right device, dtype and shape
        if t.dtype != dtype or t.device != torch.device(device):
            t = t.to(device=device, dtype=dtype)
        if tuple(t.shape) != tuple(lead) + tail:
            t = t.expand(*lead, *tail)
        return t.reshape((b,) + ((1, 3) if tail == (3,) else tail))

    try:
        rows = [flat(head_pose.rotation, (3, 3))]
        for vec in (head_pose.translation, head_pose.linear_velocity, head_pose.angular_velocity):
            rows.append(torch.zeros(b, 1, 3, device=device, dtype=dtype) if vec is None else flat(vec, (3,)))
    except RuntimeError:
        raise ValueError(f"head_pose batch shape {tuple(head_pose.rotation.shape[:-2])} does not "
                         f"broadcast to the leading dims of x {tuple(lead)}")
    return torch.cat(rows, 1)


def to_head(frame: torch.Tensor, x: torch.Tensor, v: Optional[torch.Tensor], x_rigid: Optional[torch.Tensor] = None):
    """Head-frame positions and velocities relative to the grid's rigid motion.

    frame: (B, 6, 3); x, v: (B, P, 3) world m, m/s. ``xl = Rᵀ (x − T)`` and
    ``vl = Rᵀ (v − V − W × (x_rigid − T))`` with ``x_rigid = x`` unless given.
    Returns xl (B, P, 3) m and vl (B, P, 3) m/s (None if v is None).
    """
    rot = frame[:, :3]
    rel = x - frame[:, 3, None, :]
    xl = torch.einsum("bji,bpj->bpi", rot, rel)
    if v is None:
        return xl, None
    if x_rigid is not None:
        rel = x_rigid - frame[:, 3, None, :]
    vr = v - frame[:, 4, None, :] - torch.cross(frame[:, 5, None, :].expand_as(rel), rel, dim=-1)
    return xl, torch.einsum("bji,bpj->bpi", rot, vr)


def face_corners(xl: torch.Tensor, origin: torch.Tensor, h: float, r: int, c: int):
    """Lower corner and trilinear weights of head-frame points on the c-face grid.

    xl: (B, P, 3) m; origin: (3,) m; h: cell size m. Returns the lower corner (B, P, 3) long
    (face indices per axis) and the weights (B, P, 8) of corners (i, j, k) ∈ {0, 1}³ at
    ``4 i + 2 j + k``, zero for samples outside the grid. Per axis the lower corner is clamped to
    [0, n − 2] and only the weights of corners that exist are kept (a particle half outside
    keeps the share of the samples inside; one fully outside gets zero weights).
    """
    bc, w = face_corner_rows(xl, origin, h, r, c)
    return bc.permute(1, 2, 0), w.permute(1, 2, 0).contiguous()


def face_corner_rows(xl: torch.Tensor, origin: torch.Tensor, h: float, r: int, c: int):
    """:func:`face_corners` as rows: the lower corner (3, B, P) long and the weights (8, B, P)
    (corner-major: every op on them runs along P)."""
    dims = face_dims(r, c)
    g = (xl - origin.to(xl.dtype)) / h
    half = torch.full((3,), 0.5, device=xl.device, dtype=xl.dtype)
    g = g - torch.where(torch.arange(3, device=xl.device) == c, torch.zeros_like(half), half)
    base = torch.floor(g)
    f = g - base
    i0 = base.clamp(-2, max(dims) + 1).long()  # far outside: any index with zero weights
    bc = torch.stack([i0[..., a].clamp(0, dims[a] - 2) for a in range(3)])  # (3, B, P)
    d = i0 - bc.permute(1, 2, 0)  # 0 inside; −1 / 1 half outside; else fully outside
    one_f = 1 - f
    zero = torch.zeros_like(f)
    w0 = torch.where(d == 0, one_f, torch.where(d == -1, f, zero))
    w1 = torch.where(d == 0, f, torch.where(d == 1, one_f, zero))
    # the 8 products (w_x w_y) w_z as rows along P
    wa = torch.stack((w0.permute(2, 0, 1), w1.permute(2, 0, 1)), 1)  # (3, 2, B, P)
    w = wa[0, :, None, None] * wa[1, None, :, None] * wa[2, None, None, :]  # (2, 2, 2, B, P)
    return bc, w.reshape(8, g.shape[0], g.shape[1])


def face_stencil(xl: torch.Tensor, origin: torch.Tensor, h: float, r: int, c: int):
    """Trilinear stencil of head-frame points on the dense c-face grid.

    xl: (B, P, 3) m; origin: (3,) m; h: cell size m. Returns flat indices (B, P, 8) long into a
    (B, 3, F) face field (scene b, component c starts at ``(3 b + c) F``) and weights (B, P, 8)
    of :func:`face_corners`.
    """
    dims = face_dims(r, c)
    bc, w = face_corners(xl, origin, h, r, c)
    b = bc.shape[0]
    flat = (bc[..., 0] * dims[1] + bc[..., 1]) * dims[2] + bc[..., 2]
    flat = flat + ((torch.arange(b, device=bc.device) * 3 + c) * num_faces(r))[:, None]
    o = torch.arange(2, device=bc.device)
    offs = ((o[:, None, None] * dims[1] + o[None, :, None]) * dims[2] + o[None, None, :]).reshape(8)
    return flat[..., None] + offs, w


def _face_mass_momentum(xl, vl, m, origin, h: float, r: int, stencils=None):
    b = xl.shape[0]
    idx, vals = [], []
    for c in range(3):
        ic, wc = face_stencil(xl, origin, h, r, c)
        if stencils is not None:
            stencils.append((ic, wc))
        idx.append(ic)
        if vl is None:
            vals.append((wc * m[..., None])[..., None])
        else:
            mv = torch.stack((m, m * vl[..., c]), -1)  # (B, P, 2): mass, c-momentum
            vals.append(wc[..., None] * mv[:, :, None, :])
    k = vals[0].shape[-1]
    idx = torch.stack(idx, 0).reshape(-1)
    vals = torch.stack(vals, 0).reshape(-1, k)
    acc = torch.zeros(b * 3 * num_faces(r), k, device=xl.device, dtype=xl.dtype).index_add(0, idx, vals)
    return acc.reshape(b, 3, num_faces(r), k)


def p2g_torch(x: torch.Tensor, v: torch.Tensor, m: torch.Tensor, frame: torch.Tensor, origin: torch.Tensor,
              cell_size: float, resolution: int, stencils: Optional[list] = None) -> torch.Tensor:
    """P2G (definition of the native ``p2g``): trilinear mass and momentum on the face grids.

    x, v: (B, P, 3) world m, m/s; m: (B, P) kg; frame: (B, 6, 3); origin: (3,) m (head frame);
    cell_size: h, m; resolution: R. Returns faces (B, 3, F, 2): kg and kg·m/s (head frame,
    relative to the grid's motion). ``stencils``, when a list, receives the three
    (indices, weights) of :func:`face_stencil` for reuse by :func:`g2p_torch`.
    """
    xl, vl = to_head(frame, x, v)
    return _face_mass_momentum(xl, vl, m, origin, cell_size, resolution, stencils)


def g2p_torch(x: torch.Tensor, v: torch.Tensor, field: torch.Tensor, frame: torch.Tensor, origin: torch.Tensor,
              free: torch.Tensor, dt, cell_size: float, resolution: int, pic: float,
              stencils: Optional[list] = None):
    """G2P with the FLIP/PIC blend and the change back to the world (definition of ``g2p``).

    field: (B, 3, F) m/s, ``pic · u + Δu`` on the faces (see ``pressure.py``); free: (M,) bool
    with M dividing P (N or S·N), particle p of a scene is free when ``free[p mod M]``; dt: s (float or 0-d tensor); pic: the
    PIC share 1 − flip. Per particle (head frame, I = trilinear interpolation, wsum = its total
    weight on the grid): ``Δv = I(field) − pic · wsum · v_rel``, i.e. the FLIP update
    ``v + I(Δu)`` blended with the PIC velocity ``I(u + Δu)`` (the weight missing outside the
    grid falls back to the particle's own velocity); zero for pinned particles. Returns
    ``x' = x + dt R Δv`` and ``v' = v + R Δv``: (B, P, 3) world m and m/s.
    """
    xl, vl = to_head(frame, x, v)
    flat = field.reshape(-1)
    dvl = []
    for c in range(3):
        idx, w = stencils[c] if stencils is not None else face_stencil(xl, origin, cell_size, resolution, c)
        dvl.append(interpolate_change(flat, idx, w, vl[..., c], pic))
    return apply_change(x, v, torch.stack(dvl, -1), frame, free, dt)


def interpolate_change(flat: torch.Tensor, idx: torch.Tensor, w: torch.Tensor, vl_c: torch.Tensor, pic: float,
                       corner_dim: int = -1):
    """One component of a particle's G2P change ``I(field) − pic · wsum · v_rel``: flat (M,) face
    values m/s, idx / w (B, P, 8) a stencil into it (idx int32 or int64; ``corner_dim=0``: rows
    (8, B, P)), vl_c (B, P) m/s. Returns (B, P) m/s."""
    return (flat.index_select(0, idx.reshape(-1)).view(idx.shape) * w).sum(corner_dim) - \
        pic * w.sum(corner_dim) * vl_c


def apply_change(x: torch.Tensor, v: torch.Tensor, dvl: torch.Tensor, frame: torch.Tensor, free: torch.Tensor, dt):
    """``x + dt R Δv`` and ``v + R Δv`` (Δv zero where not ``free[p mod M]``): x, v, dvl (B, P, 3)
    world m, m/s and head-frame m/s; frame (B, 6, 3); free (M,) bool; dt s."""
    p = x.shape[1]
    free_p = free.to(device=x.device, dtype=torch.bool).repeat(p // free.shape[0])
    dvl = torch.where(free_p[None, :, None], dvl, torch.zeros_like(dvl))
    dxl = dt * dvl
    rot = frame[:, :3]
    return x + torch.einsum("bij,bpj->bpi", rot, dxl), v + torch.einsum("bij,bpj->bpi", rot, dvl)


def face_views(field: torch.Tensor, r: int):
    """The three components of a (B, 3, F, ...) face tensor as (B, *face_dims(R, c), ...) views."""
    b = field.shape[0]
    return [field[:, c].reshape(b, *face_dims(r, c), *field.shape[3:]) for c in range(3)]


def cell_mass(face_mass) -> torch.Tensor:
    """Cell-centred mass (B, R, R, R) kg from the three face-mass grids (B, *face dims): the mean
    over axes of the average of the cell's two faces."""
    total = None
    for c, mf in enumerate(face_mass):
        r = mf.shape[1 + c] - 1
        pair = 0.5 * (mf.narrow(1 + c, 0, r) + mf.narrow(1 + c, 1, r))
        total = pair if total is None else total + pair
    return total / 3.0


def grid_density(grid, x: torch.Tensor, mass, head_pose: Optional[Pose] = None) -> torch.Tensor:
    """Hair density on the grid, as the stage sees it.

    Args:
        grid: a :class:`HairHairGrid`.
        x: (..., S, N, 3) metres, world positions.
        mass: kg, broadcastable to (..., S, N).
        head_pose: head pose (world ← head frame); None = identity.
    Returns:
        (..., R, R, R) kg/m³, cell-centred, indexed [i, j, k] along the head frame's x, y, z.
    """
    if x.dim() < 3 or x.shape[-1] != 3:
        raise ValueError(f"x must have shape (..., S, N, 3); got {tuple(x.shape)}")
    lead = x.shape[:-3]
    b = math.prod(lead)
    p = x.shape[-3] * x.shape[-2]
    try:
        m = torch.as_tensor(mass, device=x.device, dtype=x.dtype).expand(x.shape[:-1]).reshape(b, p)
    except RuntimeError:
        raise ValueError(f"mass of shape {tuple(torch.as_tensor(mass).shape)} does not broadcast to "
                         f"{tuple(x.shape[:-1])}")
    frame = scene_frame(head_pose, lead, b, x.dtype, x.device)
    xl, _ = to_head(frame, x.reshape(b, p, 3), None)
    r, h = grid.resolution, grid.cell_size
    faces = _face_mass_momentum(xl, None, m, grid.origin, h, r)[..., 0]
    rho = cell_mass(face_views(faces, r)) / (h * h * h)
    return rho.reshape(*lead, r, r, r)
