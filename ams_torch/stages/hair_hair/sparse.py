"""The block-sparse grid of the hair–hair stage: storage and work follow the hair, not the box.

The dense grid of :mod:`.transfer` and :mod:`.pressure` is the definition of the stage (SPEC §6);
this module computes the same values on the cells the hair occupies only, with static shapes and
no host synchronisation. It is the stage's torch path and the definition of the native kernels
(``ams_torch/native/csrc/grid``), which use the same layout.

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
from ams_torch.stages.hair_hair.transfer import apply_change, face_corner_rows, interpolate_change, to_head

__all__ = ["BLOCK", "BLOCK_CELLS", "blocks_per_axis", "block_layout", "pool_stencil", "pool_neighbours",
           "p2g_sparse", "pressure_sparse", "g2p_sparse", "pool_density", "active_cells", "densify"]

BLOCK = 4  # cells per block and axis
_SHIFT = 2  # BLOCK = 1 << _SHIFT
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
    it = torch.int32 if b * (nb3 + 1) < 2 ** 31 else torch.int64
    g = (xl.detach() - origin.to(xl.dtype)) / h
    f = torch.nan_to_num(torch.floor(g), nan=-2.0).clamp(-2, r + 2)
    f = f.permute(2, 0, 1).to(it, memory_format=torch.contiguous_format)  # (3, B, P): rows along P
    lo, hi = (f - 1).clamp_min(0), (f + 1).clamp_max(r)
    inside = (lo <= hi).all(0)  # (B, P)
    sel = torch.stack((lo, hi), 1) >> _SHIFT  # (3, 2, B, P): first and last block per axis (floor of /4)
    ids = ((sel[0, :, None] * nb + sel[1, None, :]) * nb)[:, :, None] + sel[2, None, None]  # (2, 2, 2, B, P)
    scene = torch.arange(b, device=xl.device, dtype=it)[:, None] * (nb3 + 1)
    ids = torch.where(inside, ids, nb3) + scene  # column nb3 of each scene: outside, discarded
    mark = torch.zeros(b * (nb3 + 1), dtype=torch.int32, device=xl.device).scatter_(0, ids.reshape(-1).long(), 1)
    mark = mark.reshape(b, nb3 + 1)[:, :nb3]
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

    xl: (B, P, 3) m; table: (B, nb³) int32. Returns, as rows (8, B, P) (corner 4i + 2j + k of
    each particle), the flat indices into a (B, K, 3, 64) pool followed by one sentinel (index
    B·K·3·64, for corners whose block has no slot), int32 (int64 for a pool of 2³¹ entries or
    more), and the weights.
    """
    lower, w = face_corner_rows(xl, origin, h, r, c)
    b, p = lower.shape[1:]
    nb = blocks_per_axis(r)
    none = b * capacity * 3 * BLOCK_CELLS  # the sentinel
    # integer work in int32 where every index fits (int64 products do not vectorise): per axis
    # the corners' two face indices (lower, lower + 1) ≥ 0, their block and place in it by
    # shifts, then the 8 corners by broadcasting
    it = torch.int32 if max(none, b * nb ** 3) < 2 ** 31 else torch.int64
    lower = lower.to(it)  # (3, B, P)
    q = torch.stack((lower, lower + 1), 1)  # (3, 2, B, P)
    blk, loc = q >> _SHIFT, q & (BLOCK - 1)
    scene = torch.arange(b, device=xl.device, dtype=it)[:, None]  # (B, 1)
    bid = ((blk[0, :, None] * nb + blk[1, None, :]) * nb)[:, :, None] + (blk[2] + scene * nb ** 3)[None, None]
    slot = table.reshape(-1).index_select(0, bid.reshape(-1)).reshape(8, b, p).to(it)
    # flat index ((scene K + slot) 3 + c) 64 + local
    lz = loc[2] + (scene * (capacity * 3 * BLOCK_CELLS) + c * BLOCK_CELLS)  # (2, B, P)
    local = ((loc[0, :, None] * BLOCK + loc[1, None, :]) * BLOCK)[:, :, None] + lz[None, None]
    idx = torch.where(slot >= 0, torch.add(local.reshape(8, b, p), slot, alpha=3 * BLOCK_CELLS), none)
    return idx, w


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
    size = b * capacity * 3 * BLOCK_CELLS
    # mass and c-momentum summed apart (1-D sums: a tight loop each), components in order
    mass = torch.zeros(size + 1, device=x.device, dtype=x.dtype)
    mom = torch.zeros(size + 1, device=x.device, dtype=x.dtype)
    for c in range(3):
        ic, wc = pool_stencil(xl, origin, cell_size, resolution, c, table, capacity)
        if stencils is not None:
            stencils.append((ic, wc))
        flat = ic.reshape(-1)  # corner-major: the sums' order (rounding) is the corners', then the particles'
        mass.index_add_(0, flat, (wc * m).reshape(-1))
        mom.index_add_(0, flat, (wc * (m * vl[..., c])).reshape(-1))
    faces = torch.stack((mass[:size], mom[:size]), -1)
    return faces.reshape(b, capacity, 3, BLOCK_CELLS, 2), table, blocks, count


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


def _with_sentinel(t: torch.Tensor) -> torch.Tensor:
    flat = t.reshape(-1)
    return torch.cat((flat, flat.new_zeros(1)))


def _cubes(t: torch.Tensor) -> torch.Tensor:
    """(B, K, 64, ...) → (B, K, 4, 4, 4, ...): a block's cells (or one component's faces) as a cube."""
    return t.reshape(t.shape[:2] + (BLOCK, BLOCK, BLOCK) + t.shape[3:])


def _shifted(cube: torch.Tensor, nbr: torch.Tensor, d: int) -> torch.Tensor:
    """The values of the next cell in direction d (0..5: x−, x+, y−, y+, z−, z+) for every cell of
    every block: cube (B, K, 4, 4, 4, ...), nbr (B, K, 6) slots from :func:`pool_neighbours`; the
    layer that leaves the block comes from the neighbouring block (zeros where it has no slot)."""
    axis, up = 2 + d // 2, d % 2 == 1
    b, k = cube.shape[:2]
    slot = nbr[..., d]
    layer = cube.narrow(axis, 0 if up else BLOCK - 1, 1)[torch.arange(b, device=cube.device)[:, None],
                                                          slot.clamp_min(0)]
    has = (slot >= 0).reshape((b, k) + (1,) * (layer.dim() - 2))
    layer = torch.where(has, layer, torch.zeros_like(layer))
    inner = cube.narrow(axis, 1, BLOCK - 1) if up else cube.narrow(axis, 0, BLOCK - 1)
    return torch.cat((inner, layer) if up else (layer, inner), axis)


def _velocity(mass: torch.Tensor, mom: torch.Tensor) -> torch.Tensor:
    """u = momentum / mass on faces, 0 where massless (pressure.py's ``vel``)."""
    return torch.where(mass > 0, mom / torch.where(mass > 0, mass, torch.ones_like(mass)), torch.zeros_like(mass))


def _inverse_density(mass: torch.Tensor, eps, h3: float) -> torch.Tensor:
    """1/ρ_f = h³ / M on faces above ε, 0 elsewhere (pressure.py's ``inv_rho``)."""
    has = mass > eps
    return torch.where(has, h3 / torch.where(has, mass, torch.ones_like(mass)), torch.zeros_like(mass))


def _active(faces: torch.Tensor, nbr: torch.Tensor, eps) -> torch.Tensor:
    """(B·K·64,) bool: the pool cells whose six faces all have mass above ε (the lower c-face of a
    cell is its own, the upper one the next cell's along c)."""
    active = None
    for c in range(3):
        mass = faces[:, :, c, :, 0]
        upper = _shifted(_cubes(mass), nbr, 2 * c + 1).reshape(mass.shape)
        both = (mass > eps) & (upper > eps)
        active = both if active is None else active & both
    return active.reshape(-1)


def pool_density(faces: torch.Tensor, table: torch.Tensor, blocks: torch.Tensor, cell_size: float,
                 resolution: int) -> torch.Tensor:
    """(B, K·64) kg/m³: the density of every pool cell, as :func:`~.transfer.grid_density` gives it
    on the dense grid (cells without a slot have none, i.e. 0)."""
    h3 = cell_size * cell_size * cell_size
    nbr = pool_neighbours(blocks, table, resolution)
    total = None
    for c in range(3):
        mass = faces[:, :, c, :, 0]
        upper = _shifted(_cubes(mass), nbr, 2 * c + 1).reshape(mass.shape)
        pair = 0.5 * (mass + upper)
        total = pair if total is None else total + pair
    return (total / 3.0 / h3).reshape(faces.shape[0], -1)


def active_cells(faces: torch.Tensor, table: torch.Tensor, blocks: torch.Tensor, target_density: torch.Tensor,
                 cell_size: float, resolution: int) -> torch.Tensor:
    """(B,) int64: cells that can carry φ (all six faces above ε) in each scene's pool."""
    h = cell_size
    eps = target_density.to(faces.dtype) * (ACTIVE_FACE_DENSITY * h * h * h)
    return _active(faces, pool_neighbours(blocks, table, resolution), eps).reshape(faces.shape[0], -1).sum(1)


def _listed_neighbours(cell: torch.Tensor, nbr: torch.Tensor, k: int) -> torch.Tensor:
    """(B, L, 6) long: the pool cells (within their scene; K·64 = none) next to the pool cells
    ``cell`` (B, L) (K·64 = no cell) in the directions x−, x+, y−, y+, z−, z+; nbr (B, K, 6) the
    neighbour slots."""
    none = k * BLOCK_CELLS
    scene = torch.arange(cell.shape[0], device=cell.device)[:, None]
    slot, loc = cell >> (3 * _SHIFT), cell & (BLOCK_CELLS - 1)  # cell ≥ 0: // 64 and % 64
    safe = slot.clamp(0, k - 1)
    coords = [(loc >> (a * _SHIFT)) & (BLOCK - 1) for a in range(3)]  # along z, y, x (strides 1, 4, 16)
    out = []
    for d in range(6):
        stride, step = _STRIDES[d // 2], (1 if d % 2 else -1)
        coord = coords[2 - d // 2] + step  # (loc // stride) % BLOCK + step
        leave = (coord < 0) | (coord >= BLOCK)
        to = torch.where(leave, nbr[scene, safe, d], slot)
        local = loc + step * stride - torch.where(leave, step * BLOCK * stride, 0)
        out.append(torch.where((to >= 0) & (cell < none), to * BLOCK_CELLS + local, none))
    return torch.stack(out, -1)


def _faces_by_component(faces: torch.Tensor) -> torch.Tensor:
    """(3, 2, B·K·64): per component the pool's face masses and momenta as contiguous rows (the
    cell terms gather them by 1-D index_select)."""
    return faces.permute(2, 4, 0, 1, 3).reshape(3, 2, -1)


def _take_faces(comp: torch.Tensor, index: torch.Tensor, size: int) -> torch.Tensor:
    """comp (2, size) one component's face masses and momenta at index (L,); zeros where
    index == size (the "none" index). Returns (2, L)."""
    got = comp.index_select(1, index.clamp(max=size - 1))
    return torch.where(index < size, got, torch.zeros_like(got))


def _solve(faces, nbr, active, rho0, dt, h: float, cap: int, iterations: int, omega: float, stiffness: float,
           comps: Optional[torch.Tensor] = None, native_sweeps: bool = False):
    """φ (B·K·64,) on the pool, the listed cells (B·cap,) and their neighbours (B·cap, 6) (global
    pool cells; B·K·64 = none): the projected Jacobi sweeps of pressure.py, run on a list of each
    scene's active cells (static capacity ``cap``, in cell order; cells beyond it are left out,
    which the caller reports). The cell terms (ρ, ∇·u, 1/ρ_f of the six faces, b) are those of
    pressure.py for the listed cells; an inactive cell has coef = src = 0 and stays 0, so the
    values are those of sweeping every cell."""
    b, k = faces.shape[:2]
    h2, h3 = h * h, h * h * h
    dev = faces.device
    cells = k * BLOCK_CELLS
    act = active.reshape(b, cells)
    pos = act.long().cumsum(1) - 1
    ok = act & (pos < cap)
    every = torch.arange(cells, device=dev).expand(b, cells)
    listed = torch.full((b, cap + 1), cells, dtype=torch.long, device=dev)
    listed = listed.scatter_(1, torch.where(ok, pos, cap), every)[:, :cap]  # column cap: discarded
    scene = torch.arange(b, device=dev)[:, None]
    near = _listed_neighbours(listed, nbr, k)  # (B, cap, 6) pool cells within the scene
    none = b * cells
    g = torch.where(listed < cells, listed + scene * cells, none).reshape(-1)  # (B·cap,) global pool cells
    near_g = torch.where(near < cells, near + scene[..., None] * cells, none).reshape(-1, 6)
    comps = _faces_by_component(faces) if comps is None else comps
    m_lo, v_lo, lo, m_hi, v_hi, hi = [], [], [], [], [], []
    for c in range(3):
        for out_m, out_v, out_i, at in ((m_lo, v_lo, lo, g), (m_hi, v_hi, hi, near_g[:, 2 * c + 1])):
            mm = _take_faces(comps[c], at, none)
            out_m.append(mm[0])
            out_v.append(_velocity(mm[0], mm[1]))
            out_i.append(_inverse_density(mm[0], rho0 * (ACTIVE_FACE_DENSITY * h3), h3))
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
    diag = None
    for c in range(3):
        diag = lo[c] + hi[c] if diag is None else diag + lo[c] + hi[c]
    on = g < none  # listed (every listed cell is active)
    safe = torch.where(on, rho, torch.ones_like(rho))
    rhs = stiffness * (1 - rho0 / safe) / dt
    rhs = torch.where(rho > rho0, torch.maximum(rhs, -div), rhs)
    coef = torch.where(on, omega / torch.where(on, diag, torch.ones_like(diag)), torch.zeros_like(diag))
    src = coef * (h2 * rhs)
    weights = (lo[0], hi[0], lo[1], hi[1], lo[2], hi[2])
    # list slots of the neighbours, one contiguous row per direction; slot B·cap is a zero that
    # stays zero (its src, coef and weights are 0)
    rank = torch.where(ok, pos + scene * cap, b * cap)  # pool cell → list slot, or B·cap
    rank = torch.cat((rank, rank.new_full((b, 1), b * cap)), 1)  # column `cells`: no neighbour
    nbr_l = torch.gather(rank, 1, near.reshape(b, -1)).reshape(-1, 6).t()
    nbr_l = torch.cat((nbr_l, nbr_l.new_full((6, 1), b * cap)), 1).reshape(-1)  # (6·(B·cap + 1),)
    pad = lambda t: torch.cat((t, t.new_zeros(1)))  # noqa: E731
    src, coef = pad(src), pad(coef)
    w_l = torch.stack([pad(w) for w in weights])  # (6, B·cap + 1)
    ns = _sweeps_namespace(src) if native_sweeps else None
    if torch.is_grad_enabled() and any(t.requires_grad for t in (src, coef, w_l)):
        phi_l = (_NativeSweeps if ns is not None else _Sweeps).apply(src, coef, w_l, nbr_l, iterations, omega)
    elif ns is not None:
        phi_l = ns.sweeps(src, coef, w_l, nbr_l, iterations, omega)
    else:
        phi_l = _sweeps(src, coef, w_l, nbr_l, iterations, omega)
    phi = torch.zeros(none + 1, dtype=faces.dtype, device=dev)
    phi.scatter_(0, pad(g), phi_l)  # the padding slot (and unused list slots) land on slot `none`
    return phi[:-1], g, near_g


def _sweeps(src, coef, w_l, nbr_l, iterations: int, omega: float, history: Optional[list] = None) -> torch.Tensor:
    """``iterations`` projected weighted-Jacobi sweeps from φ = 0 on the listed cells (L + 1 values,
    the last a zero that stays zero): φ ← max(0, src + coef Σ_d w_d φ[nbr_d] + (1 − ω) φ), the six
    neighbours gathered at once (``nbr_l`` (6·(L + 1),), ``w_l`` (6, L + 1)) and summed in the
    order x−, x+, y−, …. ``history``: receives φ before each sweep."""
    phi_l = torch.zeros_like(src)
    for _ in range(iterations):
        if history is not None:
            history.append(phi_l)
        n = (w_l * phi_l.index_select(0, nbr_l).view(w_l.shape)).sum(0)
        nxt = src + coef * n
        phi_l = (nxt + (1.0 - omega) * phi_l).clamp_min(0)
    return phi_l


class _Sweeps(torch.autograd.Function):
    """:func:`_sweeps` with its vector-Jacobian product written out: the forward keeps φ before each
    sweep (iterations × (L + 1) values) instead of autograd's tensors of every sweep (the gathered
    neighbours, the products, the masks: ~10 times more), and the backward runs the sweeps in
    reverse. The derivatives are the loop's own: clamp_min passes the gradient where its input is
    ≥ 0 (as torch's), the gather's adjoint is an index_add over the same neighbour list."""

    @staticmethod
    def forward(ctx, src, coef, w_l, nbr_l, iterations, omega):
        history: list = []
        phi = _sweeps(src, coef, w_l, nbr_l, iterations, omega, history)
        ctx.save_for_backward(src, coef, w_l, nbr_l, *history)
        ctx.omega = omega
        return phi

    @staticmethod
    def backward(ctx, g):
        src, coef, w_l, nbr_l, *history = ctx.saved_tensors
        omega = ctx.omega
        g_src, g_coef, g_w = torch.zeros_like(src), torch.zeros_like(coef), torch.zeros_like(w_l)
        for phi in reversed(history):
            gathered = phi.index_select(0, nbr_l).view(w_l.shape)
            n = (w_l * gathered).sum(0)
            pre = src + coef * n + (1.0 - omega) * phi
            a = torch.where(pre >= 0, g, torch.zeros_like(g))
            g_src += a
            g_coef += a * n
            t = coef * a  # adjoint of n
            g_w += t * gathered
            g = (1.0 - omega) * a
            g = g.index_add(0, nbr_l, (w_l * t).reshape(-1))
        return g_src, g_coef, g_w, None, None, None


def _sweeps_namespace(src: torch.Tensor):
    """The native library holding the sweeps' kernels for ``src``'s device and dtype, or None (also on
    CUDA under torch's deterministic mode: the CUDA adjoint's scatter is atomicAdd, in a varying
    order; the torch definition's written-out product, ``_Sweeps``, instead)."""
    from ams_torch.native.dispatch import native_namespace

    if src.is_cuda and torch.are_deterministic_algorithms_enabled():
        return None
    return native_namespace("grid", src)


class _NativeSweeps(torch.autograd.Function):
    """:func:`_sweeps` and its vector-Jacobian product (:class:`_Sweeps`) by the native kernels
    (``csrc/grid/sweeps.h``: ``sweeps``, ``sweeps_adjoint``, the same operations; the adjoint runs the
    sweeps again keeping φ before each). Nothing but the inputs is kept between the passes."""

    @staticmethod
    def forward(ctx, src, coef, w_l, nbr_l, iterations, omega):
        ctx.save_for_backward(src, coef, w_l, nbr_l)
        ctx.meta = (iterations, omega)
        return _sweeps_namespace(src).sweeps(src, coef, w_l, nbr_l, iterations, omega)

    @staticmethod
    def backward(ctx, g):
        src, coef, w_l, nbr_l = ctx.saved_tensors
        g_src, g_coef, g_w = _sweeps_namespace(src).sweeps_adjoint(src, coef, w_l, nbr_l, *ctx.meta, g.contiguous())
        return g_src, g_coef, g_w, None, None, None


def pressure_sparse(faces: torch.Tensor, table: torch.Tensor, blocks: torch.Tensor, count: torch.Tensor,
                    target_density: torch.Tensor, dt, cell_size: float, resolution: int, iterations: int, omega: float,
                    stiffness: float, pic: float, active_capacity: Optional[int] = None, native_sweeps: bool = False):
    """The pressure solve and the face field on the pool (definition of the native ``pressure``):
    :func:`~.pressure.pressure_torch` cell by cell and face by face, in its order of operations.

    faces: (B, K, 3, 64, 2) from :func:`p2g_sparse`; table (B, nb³), blocks (B, K), count (B,)
    int32; target_density () kg/m³; dt s; the rest as ``pressure_torch``; active_capacity: the
    active cells per scene the sweeps hold (a static capacity, default every pool cell: the
    sweeps and the cell terms cost this, not the pool; see :func:`_solve`). Returns phi
    (B, K, 64) kg/(m·s), field (B, K, 3, 64) m/s and overflow (B,) bool: the scene's hair
    occupied more than K blocks (``count > K``: P2G left blocks out) or, with sweeps, had more
    active cells than ``active_capacity`` (the cells beyond it kept φ = 0). ``native_sweeps``: the
    sweeps (and, when differentiated, their adjoint) by the native kernels where built (the hair–hair
    adjoint of native gradient frames asks for it; the torch path keeps the definition).
    """
    h = cell_size
    h3 = h * h * h
    b, k = faces.shape[:2]
    cap = k * BLOCK_CELLS if active_capacity is None else min(int(active_capacity), k * BLOCK_CELLS)
    rho0 = target_density.to(faces.dtype)
    eps = rho0 * (ACTIVE_FACE_DENSITY * h3)
    nbr = pool_neighbours(blocks, table, resolution)
    # field = pic u + Δu with Δu = −(∇φ)_f / ρ_f: φ is 0 off the listed cells, so Δu = −0 on every
    # face but those of listed cells, where pic u + Δu is computed and written below
    field = []
    for c in range(3):
        mass, mom = faces[:, :, c, :, 0], faces[:, :, c, :, 1]
        field.append(pic * _velocity(mass, mom))
    field = torch.stack(field, 2)  # (B, K, 3, 64)
    blocks_over = count > k
    if iterations == 0:
        return faces.new_zeros(b, k, BLOCK_CELLS), field, blocks_over
    active = _active(faces, nbr, eps)
    comps = _faces_by_component(faces)
    phi, g, near_g = _solve(faces, nbr, active, rho0, dt, h, cap, iterations, omega, stiffness, comps, native_sweeps)
    none = b * k * BLOCK_CELLS
    listed = torch.zeros(none + 1, dtype=torch.bool, device=faces.device)
    listed[g] = True  # slot `none`: unused list slots
    listed[none] = False
    phi_pad = torch.cat((phi, phi.new_zeros(1)))
    out = torch.cat((field.permute(2, 0, 1, 3).reshape(3, -1), field.new_zeros(3, 1)), 1)  # (3, none + 1)
    for c in range(3):
        below = near_g[:, 2 * c]  # the cell under each listed cell's lower c-face
        above = near_g[:, 2 * c + 1]  # the cell over its upper c-face (whose lower c-face that is)
        # each face once: a listed cell's lower face, and its upper face unless the cell above is
        # listed too (then it is that cell's lower face)
        for face, hi, lo, use in ((g, g, below, g < none), (above, above, g, (above < none) & ~listed[above])):
            mm = _take_faces(comps[c], face, none)
            grad = (phi_pad[hi] - phi_pad[lo]) / h
            du = -(grad * _inverse_density(mm[0], eps, h3))
            value = pic * _velocity(mm[0], mm[1]) + du
            out[c].index_put_((torch.where(use, face, none),), value)
    field = out[:, :-1].reshape(3, b, k, BLOCK_CELLS).permute(1, 2, 0, 3)
    return phi.reshape(b, k, BLOCK_CELLS), field, blocks_over | (active.reshape(b, -1).sum(1) > cap)


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
        dvl.append(interpolate_change(flat, idx, w, vl[..., c], pic, corner_dim=0))
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
