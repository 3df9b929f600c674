"""The block-sparse grid of the hair–hair stage: storage and work follow the hair, not the box.

The dense grid of :mod:`.transfer` and :mod:`.pressure` is the definition of the stage (SPEC §6);
this module computes the same values on the cells the hair occupies only, with static shapes and
no host synchronisation. It is the stage's torch path and the definition of the native kernels
(``ams_torch/solver/csrc/grid``), which use the same layout.

**Blocks.** The grid is cut into blocks of ``BLOCK³ = 4³`` cells: block (I, J, K) holds the cells,
and for each component c the c-faces, with indices (4I + a, 4J + b, 4K + e), a, b, e ∈ [0, 4),
local index ``(4 a + b) 4 + e``. ``nb = R // 4 + 1`` blocks per axis cover every face grid (R + 1
samples along its own axis); block id ``(I nb + J) nb + K``. Each scene has a pool of K slots
(``HairHairGrid.capacity``, configuration: a static shape):

* ``table`` (B, nb³) int32: the slot of each block, −1 where the block holds no hair (or did not fit);
* ``blocks`` (B, K) int32: the block id of each slot, −1 for unused slots;
* ``count`` (B,) int32: the blocks the hair occupies; ``count > K`` is an **overflow** (blocks
  beyond the capacity are dropped, which the stage reports: never silent);
* ``faces`` (B, K, 3, 64, 2): per slot and component the block's 64 faces, mass kg and
  c-momentum kg·m/s (head frame, relative to the grid's motion), as the dense ``faces``;
* ``phi`` (B, K, 64) kg/(m·s) and ``field`` (B, K, 3, 64) m/s, as the dense ``phi`` and ``field``.

Slots at or beyond ``min(count, K)`` are unused: their contents are unspecified (zeros here; the
native kernels leave them unwritten) and nothing reads them.

**Which blocks.** Per axis, a particle at cell coordinate g (``f = ⌊g⌋``) weighs faces with index
in ``[f − 1, f + 1] ∩ [0, R]`` only (its own component's stencil starts at f, the others' at
``⌊g − ½⌋ ∈ {f − 1, f}``): the blocks that meet that box (at most 2 per axis) are marked, nothing
for a particle fully outside. Slots follow block order (a prefix sum over the marks), on every CPU
path.

**Why the values are the dense ones.** Every face that receives mass lies in a marked block; a
block that is not marked is zero in the dense grid (no mass, so field 0; its cells inactive, so
φ = 0), and is read as zero here (a sentinel). Cells beyond the dense grid (index R, inside the
last block) have a face no particle reaches: never active, φ = 0, so the sweeps and the face field
may read them where the dense code reads "outside the grid = 0". Neighbour sums then add exact
zeros where the dense sum skips a term, in the dense order: results agree to rounding (the order
of the P2G sums aside).
"""
from __future__ import annotations

from typing import Optional

import torch

from ams_torch.stages.hair_hair.pressure import ACTIVE_FACE_DENSITY
from ams_torch.stages.hair_hair.transfer import apply_change, face_corners, interpolate_change, to_head

__all__ = ["BLOCK", "BLOCK_CELLS", "blocks_per_axis", "block_layout", "pool_stencil", "pool_neighbours",
           "p2g_sparse", "pressure_sparse", "g2p_sparse", "densify"]

BLOCK = 4  # cells per block and axis
BLOCK_CELLS = BLOCK ** 3
_STRIDES = (BLOCK * BLOCK, BLOCK, 1)  # of the local index, per axis


def blocks_per_axis(r: int) -> int:
    """nb = R // 4 + 1: blocks per axis covering every face grid of a resolution-R grid."""
    return r // BLOCK + 1


def _corner_offsets(device) -> torch.Tensor:
    o = torch.arange(2, device=device)
    return torch.stack(torch.meshgrid(o, o, o, indexing="ij"), -1).reshape(8, 3)  # corner 4i + 2j + k


def block_layout(xl: torch.Tensor, origin: torch.Tensor, h: float, r: int, capacity: int):
    """The blocks the particles occupy and their slots.

    xl: (B, P, 3) m, head-frame positions; origin: (3,) m; h: cell size m; r: R; capacity: K slots.
    Returns table (B, nb³) int32, blocks (B, K) int32 and count (B,) int32 (module docstring).
    """
    b = xl.shape[0]
    nb = blocks_per_axis(r)
    nb3 = nb ** 3
    g = (xl.detach() - origin.to(xl.dtype)) / h
    f = torch.nan_to_num(torch.floor(g), nan=-2.0).clamp(-2, r + 2).long()
    lo, hi = (f - 1).clamp_min(0), (f + 1).clamp_max(r)
    inside = (lo <= hi).all(-1)
    sel = torch.stack((lo, hi), -2) // BLOCK  # (B, P, 2, 3): first and last block per axis
    i, j, k = sel[..., 0], sel[..., 1], sel[..., 2]
    ids = (i[..., :, None, None] * nb + j[..., None, :, None]) * nb + k[..., None, None, :]
    ids = torch.where(inside[..., None, None, None], ids, nb3).reshape(b, -1)
    mark = torch.zeros(b, nb3 + 1, dtype=torch.int32, device=xl.device).scatter_(1, ids, 1)[:, :nb3]
    pos = mark.cumsum(1)  # int64
    slot = pos - 1
    ok = (mark > 0) & (slot < capacity)
    table = torch.where(ok, slot, -1).to(torch.int32)
    every = torch.arange(nb3, device=xl.device).expand(b, nb3)
    blocks = torch.full((b, capacity + 1), -1, dtype=torch.int64, device=xl.device)
    blocks = blocks.scatter_(1, torch.where(ok, slot, capacity), every)[:, :capacity]  # slot K: discarded
    return table, blocks.to(torch.int32), pos[:, -1].to(torch.int32)


def pool_stencil(xl: torch.Tensor, origin: torch.Tensor, h: float, r: int, c: int, table: torch.Tensor,
                 capacity: int):
    """The trilinear c-face stencil of :func:`~.transfer.face_corners` in the pool.

    xl: (B, P, 3) m; table: (B, nb³) int32. Returns flat indices (B, P, 8) long into a
    (B, K, 3, 64) pool followed by one sentinel (index B·K·3·64, for corners whose block has no
    slot) and the weights (B, P, 8).
    """
    bc, w = face_corners(xl, origin, h, r, c)
    b = bc.shape[0]
    nb = blocks_per_axis(r)
    q = bc[..., None, :] + _corner_offsets(bc.device)  # (B, P, 8, 3) face indices of the corners
    blk, loc = q // BLOCK, q % BLOCK
    bid = (blk[..., 0] * nb + blk[..., 1]) * nb + blk[..., 2]
    slot = table.long().gather(1, bid.reshape(b, -1)).reshape(bid.shape)
    local = (loc[..., 0] * BLOCK + loc[..., 1]) * BLOCK + loc[..., 2]
    scene = torch.arange(b, device=bc.device)[:, None, None] * capacity
    idx = ((scene + slot) * 3 + c) * BLOCK_CELLS + local
    return torch.where(slot >= 0, idx, b * capacity * 3 * BLOCK_CELLS), w


def p2g_sparse(x: torch.Tensor, v: torch.Tensor, m: torch.Tensor, frame: torch.Tensor, origin: torch.Tensor,
               cell_size: float, resolution: int, capacity: int, stencils: Optional[list] = None):
    """P2G on the block pool (definition of the native ``p2g``).

    x, v: (B, P, 3) world m, m/s; m: (B, P) kg; frame: (B, 6, 3); origin: (3,) m; cell_size: h m;
    resolution: R; capacity: K. Returns faces (B, K, 3, 64, 2), table (B, nb³) int32, blocks
    (B, K) int32, count (B,) int32. ``stencils``, when a list, receives the three (indices,
    weights) of :func:`pool_stencil` for :func:`g2p_sparse`.
    """
    xl, vl = to_head(frame, x, v)
    table, blocks, count = block_layout(xl, origin, cell_size, resolution, capacity)
    b = x.shape[0]
    idx, vals = [], []
    for c in range(3):
        ic, wc = pool_stencil(xl, origin, cell_size, resolution, c, table, capacity)
        if stencils is not None:
            stencils.append((ic, wc))
        idx.append(ic)
        mv = torch.stack((m, m * vl[..., c]), -1)  # (B, P, 2): mass, c-momentum
        vals.append(wc[..., None] * mv[:, :, None, :])
    size = b * capacity * 3 * BLOCK_CELLS
    acc = torch.zeros(size + 1, 2, device=x.device, dtype=x.dtype)
    acc = acc.index_add(0, torch.stack(idx, 0).reshape(-1), torch.stack(vals, 0).reshape(-1, 2))
    return acc[:size].reshape(b, capacity, 3, BLOCK_CELLS, 2), table, blocks, count


def pool_neighbours(blocks: torch.Tensor, table: torch.Tensor, r: int) -> torch.Tensor:
    """(B, K, 6) long: the slot of each slot's neighbouring block in the directions x−, x+, y−,
    y+, z−, z+, or −1 (no such block, no slot, or an unused slot)."""
    b, k = blocks.shape
    nb = blocks_per_axis(r)
    blk = blocks.long()
    valid = blk >= 0
    blk = blk.clamp_min(0)
    coords = torch.stack((blk // (nb * nb), (blk // nb) % nb, blk % nb), -1)  # (B, K, 3)
    eye = torch.eye(3, dtype=torch.long, device=blocks.device)
    steps = torch.stack((-eye, eye), 1).reshape(6, 3)  # x−, x+, y−, y+, z−, z+
    nc = coords[:, :, None, :] + steps  # (B, K, 6, 3)
    ok = valid[..., None] & ((nc >= 0) & (nc < nb)).all(-1)
    nid = ((nc[..., 0] * nb + nc[..., 1]) * nb + nc[..., 2]).clamp(0, nb ** 3 - 1)
    slot = table.long().gather(1, nid.reshape(b, -1)).reshape(b, k, 6)
    return torch.where(ok, slot, -1)


def _cell_neighbours(nbr: torch.Tensor) -> torch.Tensor:
    """(B, K, 64, 6) long: flat index of each pool cell's six neighbours (x−, x+, y−, y+, z−, z+)
    into a (B·K·64) cell array followed by one zero sentinel (index B·K·64)."""
    b, k = nbr.shape[:2]
    dev = nbr.device
    loc = torch.arange(BLOCK_CELLS, device=dev)
    local_nb, cross = [], []
    for d in range(6):
        axis, step = d // 2, (1 if d % 2 else -1)
        stride = _STRIDES[axis]
        coord = (loc // stride) % BLOCK + step
        out = (coord < 0) | (coord >= BLOCK)
        cross.append(out)
        local_nb.append(loc + step * stride - torch.where(out, step * BLOCK * stride, 0))
    local_nb, cross = torch.stack(local_nb, -1), torch.stack(cross, -1)  # (64, 6)
    scene = torch.arange(b, device=dev)[:, None] * k
    own = scene + torch.arange(k, device=dev)  # (B, K) global slot
    other = torch.where(nbr >= 0, scene[..., None] + nbr, -1)  # (B, K, 6)
    slot = torch.where(cross, other[:, :, None, :], own[:, :, None, None])
    return torch.where(slot >= 0, slot * BLOCK_CELLS + local_nb, b * k * BLOCK_CELLS)


def _with_sentinel(t: torch.Tensor) -> torch.Tensor:
    flat = t.reshape(-1)
    return torch.cat((flat, flat.new_zeros(1)))


def pressure_sparse(faces: torch.Tensor, table: torch.Tensor, blocks: torch.Tensor, target_density: torch.Tensor,
                    dt, cell_size: float, resolution: int, iterations: int, omega: float, stiffness: float,
                    pic: float):
    """The pressure solve and the face field on the pool (definition of the native ``pressure``):
    :func:`~.pressure.pressure_torch` cell by cell and face by face, in its order of operations.

    faces: (B, K, 3, 64, 2) from :func:`p2g_sparse`; table (B, nb³), blocks (B, K) int32;
    target_density () kg/m³; dt s; the rest as ``pressure_torch``. Returns phi (B, K, 64)
    kg/(m·s) and field (B, K, 3, 64) m/s.
    """
    h = cell_size
    h2, h3 = h * h, h * h * h
    b, k = faces.shape[:2]
    rho0 = target_density.to(faces.dtype)
    mass, mom = faces[..., 0], faces[..., 1]  # (B, K, 3, 64)
    eps = rho0 * (ACTIVE_FACE_DENSITY * h3)
    vel = torch.where(mass > 0, mom / torch.where(mass > 0, mass, torch.ones_like(mass)), torch.zeros_like(mass))
    has = mass > eps
    inv = torch.where(has, h3 / torch.where(has, mass, torch.ones_like(mass)), torch.zeros_like(mass))
    nbr = _cell_neighbours(pool_neighbours(blocks, table, resolution)).reshape(-1, 6)  # (B·K·64, 6)
    lower = [[t[:, :, c].reshape(-1) for c in range(3)] for t in (mass, vel, inv)]
    upper = [[_with_sentinel(t[:, :, c])[nbr[:, 2 * c + 1]] for c in range(3)] for t in (mass, vel, inv)]
    (m_lo, v_lo, lo), (m_hi, v_hi, hi) = lower, upper

    total = None
    for c in range(3):
        pair = 0.5 * (m_lo[c] + m_hi[c])
        total = pair if total is None else total + pair
    rho = total / 3.0 / h3
    div = None
    for c in range(3):
        dc = v_hi[c] - v_lo[c]
        div = dc if div is None else div + dc
    div = div / h
    active = None
    diag = None
    for c in range(3):
        both = (m_lo[c] > eps) & (m_hi[c] > eps)
        active = both if active is None else active & both
        diag = lo[c] + hi[c] if diag is None else diag + lo[c] + hi[c]
    safe = torch.where(active, rho, torch.ones_like(rho))
    rhs = stiffness * (1 - rho0 / safe) / dt
    rhs = torch.where(rho > rho0, torch.maximum(rhs, -div), rhs)
    coef = torch.where(active, omega / torch.where(active, diag, torch.ones_like(diag)), torch.zeros_like(diag))
    src = coef * (h2 * rhs)  # 0 off the active cells
    phi = torch.zeros_like(rho)
    weights = (lo[0], hi[0], lo[1], hi[1], lo[2], hi[2])
    for _ in range(iterations):
        padded = _with_sentinel(phi)
        n = weights[0] * padded[nbr[:, 0]]
        for d in range(1, 6):
            n = n + weights[d] * padded[nbr[:, d]]
        nxt = src + coef * n
        phi = (nxt + (1.0 - omega) * phi).clamp_min(0)
    padded = _with_sentinel(phi)
    field = []
    for c in range(3):
        grad = (phi - padded[nbr[:, 2 * c]]) / h
        du = -(grad * lo[c])
        field.append((pic * v_lo[c] + du).reshape(b, k, BLOCK_CELLS))
    return phi.reshape(b, k, BLOCK_CELLS), torch.stack(field, 2)


def g2p_sparse(x: torch.Tensor, v: torch.Tensor, field: torch.Tensor, table: torch.Tensor, frame: torch.Tensor,
               origin: torch.Tensor, free: torch.Tensor, dt, cell_size: float, resolution: int, pic: float,
               stencils: Optional[list] = None):
    """G2P from the pool (definition of the native ``g2p``): :func:`~.transfer.g2p_torch` with the
    field read through the block table. field: (B, K, 3, 64) m/s; table: (B, nb³) int32; the rest
    as ``g2p_torch``. Returns x', v' (B, P, 3) world m and m/s."""
    xl, vl = to_head(frame, x, v)
    k = field.shape[1]
    flat = _with_sentinel(field)
    dvl = []
    for c in range(3):
        idx, w = stencils[c] if stencils is not None else pool_stencil(xl, origin, cell_size, resolution, c, table, k)
        dvl.append(interpolate_change(flat, idx, w, vl[..., c], pic))
    return apply_change(x, v, torch.stack(dvl, -1), frame, free, dt)


def densify(pool: torch.Tensor, blocks: torch.Tensor, r: int) -> torch.Tensor:
    """The dense layout of a pool tensor, zero where no block is (for tests and inspection).

    pool: (B, K, 3, 64, ...) faces → (B, 3, F, ...) as the dense ``faces``/``field``, or
    (B, K, 64) cells → (B, R, R, R) as the dense ``phi``. blocks: (B, K) int32.
    """
    b, k = blocks.shape
    nb = blocks_per_axis(r)
    side = nb * BLOCK
    cells = pool.dim() == 3
    tail = tuple(pool.shape[3:] if cells else pool.shape[4:])
    comps = 1 if cells else 3
    vals = pool.reshape(b, k, comps, BLOCK, BLOCK, BLOCK, *tail)
    blk = blocks.long()
    coords = torch.stack((blk // (nb * nb), (blk // nb) % nb, blk % nb), -1)
    out = pool.new_zeros(b, comps, nb, nb, nb, BLOCK, BLOCK, BLOCK, *tail)
    used = blk >= 0
    bi, si = torch.nonzero(used, as_tuple=True)
    ci = coords[bi, si]
    out[bi, :, ci[:, 0], ci[:, 1], ci[:, 2]] = vals[bi, si]
    order = (0, 1, 2, 5, 3, 6, 4, 7) + tuple(range(8, 8 + len(tail)))
    grid = out.permute(order).reshape(b, comps, side, side, side, *tail)
    if cells:
        return grid[:, 0, :r, :r, :r]
    parts = []
    for c in range(3):
        dims = tuple(r + 1 if d == c else r for d in range(3))
        parts.append(grid[:, c, :dims[0], :dims[1], :dims[2]].reshape(b, -1, *tail))
    return torch.stack(parts, 1)
