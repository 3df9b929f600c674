"""Hair–hair interaction on a background grid that moves rigidly with the head (SPEC §6).

The paper's §3.2 (after McAdams et al. 2009, but with a grid attached to the head): once per
frame, after inextensibility, the particles' mass and momentum are rasterised to an Eulerian
grid, the grid velocity is corrected so that hair does not pile up beyond a target density,
and the result goes back to the particles with a FLIP/PIC blend (the PIC share smooths
velocities between neighbouring strands: hair–hair friction). Optional "detailed collisions"
then push apart particles of different strands that come closer than a radius.

Choices (written down here because the paper leaves them open):

* **Frame.** Everything happens in the head frame. Velocities are taken relative to the grid's
  rigid motion, ``v_rel = Rᵀ (v − V − ω × (x − T))``, so a groom moving rigidly with the head
  has zero grid velocity and comes back unchanged (no damping of rigid motion). The change
  computed on the grid is rotated back to the world and added to the incoming velocity.
* **Grid.** A cube of ``R³`` cubic cells (edge ``h``) around the groom's reach in the head frame:
  the box of the roots ± the longest strand's arc length (and the rest positions), its largest
  side enlarged by ``bounds_padding``. Staggered (MAC) layout: velocity component ``c`` lives on
  the faces normal to axis ``c`` (``(R+1)·R·R`` per component); the pressure potential and the
  density at cell centres. Transfers are trilinear (weights from each particle to the 8 nearest
  samples of each face grid), done with ``index_add`` (P2G) and gathers (G2P), no Python loop
  over particles. Particles outside the grid keep their velocity (their missing weight falls
  back to their own velocity).
* **Density.** A cell's mass is the mean over the three axes of the average of its two face
  masses (a smoothed cell-centred rasterisation); density = mass / h³ in kg/m³.
* **Volume preservation** (unilateral, as Narain et al. 2010 do for granular media): a velocity
  potential ``φ ≥ 0`` (m²/s) at cell centres, ``Δu = −∇φ`` on faces, with the complementarity
  conditions ``∇·Δu ≥ b``, ``φ ≥ 0``, ``φ (∇·Δu − b) = 0``. Since the frame's positions are
  ``x = xⁿ + Δt u`` and the stage moves them by ``Δt Δu``, the linearised density after the
  correction is ``ρ (1 − Δt ∇·Δu)``; it reaches the target ``ρ₀`` when
  ``∇·Δu = (1 − ρ₀/ρ)/Δt``. So ``b = volume_stiffness · (1 − ρ₀/ρ) / Δt`` everywhere (negative
  below the target: such cells may be compressed up to ``ρ₀`` by their neighbours' push but are
  never pulled together), and in cells above the target also ``b ≥ −∇·u``: the corrected
  velocity stops compressing them (without this, colliding wisps keep their approach speed and
  squeeze sideways through each other; with it the approach is removed as in an inelastic
  collision, while tangential motion is kept). Solved with a fixed number of projected
  weighted-Jacobi sweeps on the 7-point Laplacian; ``φ = 0`` in empty cells and outside the grid
  (free surface).
* **FLIP/PIC.** Per particle, ``v_flip = v + I(Δu)`` and ``v_pic = I(u + Δu)`` (``I`` trilinear
  interpolation), blended ``flip · v_flip + (1 − flip) · v_pic``.
* **Positions.** The stage replaces the frame's end velocity ``v`` by ``v'`` and moves the
  positions consistently with the backward-Euler position update ``x = xⁿ + Δt v``:
  ``x' = x + Δt (v' − v)``. (Detailed collisions, below, move positions and velocities by
  separate amounts, so that resolving an overlap does not inject a separating velocity.)
* **Detailed collisions** (``detailed_collisions=True``): a sort-based spatial hash of cell
  size ``collision_radius`` in the head frame; each particle looks at up to
  ``collision_max_per_cell`` particles in each of its 27 neighbouring hash cells (more than that
  in one cell are not seen: an approximation that the parameter controls), skipping particles of
  its own strand. For each pair closer than the radius, positions are pushed apart by
  ``collision_stiffness`` of the overlap and the approaching part of the relative normal
  velocity is removed (inelastic), shared by inverse mass (pinned particles are immovable),
  averaged over each particle's contacts. Work is O(P · 27 · K), memory O(P · K).
* **Batching.** Leading dims ``...`` of ``x`` are flattened into ``B`` scenes, each with its own
  copy of the grid (one ``index_add`` over ``B`` grids; the Jacobi sweeps run on ``(B, R, R, R)``).

Nothing is allocated unless a scene enables hair–hair: :func:`build_hair_hair` returns ``None``
for a ``None`` config and :func:`hair_hair_stage` with ``grid=None`` returns its inputs.
Per-frame grid buffers are temporaries of the stage (PyTorch's caching allocator reuses them).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Optional, Tuple

import torch
import torch.nn.functional as F

from ams_torch.geometry.pose import Pose

__all__ = ["HairHair", "HairHairGrid", "build_hair_hair", "hair_hair_stage", "grid_density", "make_stage"]


def _check_int(name: str, value, minimum: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ValueError(f"HairHair.{name} must be an integer ≥ {minimum}; got {value!r}")


def _check_real(name: str, value, lo: float, hi: float = math.inf, lo_open: bool = False) -> None:
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    ok = ok and (value > lo if lo_open else value >= lo) and value <= hi
    if not ok:
        lo_s = f"> {lo}" if lo_open else f"≥ {lo}"
        hi_s = "" if hi == math.inf else f" and ≤ {hi}"
        raise ValueError(f"HairHair.{name} must be a finite number {lo_s}{hi_s}; got {value!r}")


@dataclass(frozen=True)
class HairHair:
    """Configuration of the hair–hair stage (SPEC §6). SI units; all fields validated.

    Fields:
        resolution: cells per axis R of the cubic grid (R³ cells). Paper: 128; authors' code: 64.
        flip: FLIP share in [0, 1]; the PIC share ``1 − flip`` smooths velocities between
            neighbouring strands and acts as hair–hair friction. Default 0.95 (authors: 0.8).
        pressure_iterations: projected weighted-Jacobi sweeps of the volume-preservation solve
            (0 switches it off). Default 50 (as the authors' code).
        jacobi_omega: Jacobi relaxation weight in (0, 1]. Default 0.6 (as the authors' code).
        target_density: ρ₀, kg/m³: cells denser than this are pushed apart. ``None`` (default)
            derives it from the rest groom: ``target_density_margin ×`` the peak rest density
            on the grid, so the groom at rest is never pushed.
        target_density_margin: multiplier (> 0) used when ``target_density`` is None. Default 1.1.
        volume_stiffness: share in [0, 1] of a cell's density excess removed per frame.
            Default 1.0.
        bounds_padding: relative enlargement (≥ 0) of the grid's side over the groom's reach
            (roots ± the longest strand). Default 0.3 (the authors enlarge their box by 30 %).
        detailed_collisions: run the particle–particle repulsion after the grid. Default False.
        collision_radius: m, distance below which particles of different strands repel (and
            the spatial-hash cell size). Default 2e-3.
        collision_stiffness: share in [0, 1] of a pair's overlap removed per frame. Default 0.5.
        collision_max_per_cell: particles examined per neighbouring hash cell (≥ 1). Default 8.
    """

    resolution: int = 128
    flip: float = 0.95
    pressure_iterations: int = 50
    jacobi_omega: float = 0.6
    target_density: Optional[float] = None
    target_density_margin: float = 1.1
    volume_stiffness: float = 1.0
    bounds_padding: float = 0.3
    detailed_collisions: bool = False
    collision_radius: float = 2e-3
    collision_stiffness: float = 0.5
    collision_max_per_cell: int = 8

    def __post_init__(self):
        _check_int("resolution", self.resolution, 2)
        _check_real("flip", self.flip, 0.0, 1.0)
        _check_int("pressure_iterations", self.pressure_iterations, 0)
        _check_real("jacobi_omega", self.jacobi_omega, 0.0, 1.0, lo_open=True)
        if self.target_density is not None:
            _check_real("target_density", self.target_density, 0.0, lo_open=True)
        _check_real("target_density_margin", self.target_density_margin, 0.0, lo_open=True)
        _check_real("volume_stiffness", self.volume_stiffness, 0.0, 1.0)
        _check_real("bounds_padding", self.bounds_padding, 0.0)
        if not isinstance(self.detailed_collisions, bool):
            raise ValueError(f"HairHair.detailed_collisions must be a bool; got {self.detailed_collisions!r}")
        _check_real("collision_radius", self.collision_radius, 0.0, lo_open=True)
        _check_real("collision_stiffness", self.collision_stiffness, 0.0, 1.0)
        _check_int("collision_max_per_cell", self.collision_max_per_cell, 1)

    def build(self, rest_positions, particle_mass, device=None, dtype=None) -> "HairHairGrid":
        """Fit the grid to the rest groom and allocate its fixed data.

        Args:
            rest_positions: (S, N, 3) metres, rest groom in the head frame (array or tensor).
            particle_mass: kg, a number or a tensor broadcastable to (S, N), positive.
            device, dtype: of the grid's tensors (default: those of ``rest_positions``, float32
                for non-tensors).
        Returns:
            a :class:`HairHairGrid`.
        """
        if dtype is None:
            dtype = rest_positions.dtype if isinstance(rest_positions, torch.Tensor) else torch.float32
        rest = torch.as_tensor(rest_positions, device=device, dtype=dtype)
        if rest.dim() != 3 or rest.shape[-1] != 3 or rest.shape[0] < 1 or rest.shape[1] < 2:
            raise ValueError(f"rest_positions must have shape (S, N, 3) with S ≥ 1, N ≥ 2; got {tuple(rest.shape)}")
        if not bool(torch.isfinite(rest).all()):
            raise ValueError("rest_positions contain non-finite values")
        s, n = rest.shape[:2]
        mass = torch.as_tensor(particle_mass, device=rest.device, dtype=dtype)
        try:
            mass = mass.expand(s, n)
        except RuntimeError:
            raise ValueError(f"particle_mass of shape {tuple(mass.shape)} does not broadcast to (S, N) = ({s}, {n})")
        if not bool((mass > 0).all()) or not bool(torch.isfinite(mass).all()):
            raise ValueError("particle_mass must be positive and finite")
        reach = (rest[:, 1:] - rest[:, :-1]).norm(dim=-1).sum(-1).max()
        roots = rest[:, 0]
        flat = rest.reshape(-1, 3)
        lo = torch.minimum(roots.amin(0) - reach, flat.amin(0))
        hi = torch.maximum(roots.amax(0) + reach, flat.amax(0))
        side = float((hi - lo).max()) * (1.0 + self.bounds_padding)
        side = max(side, 1e-6)
        h = side / self.resolution
        origin = (lo + hi) / 2 - side / 2
        grid = HairHairGrid(config=self, resolution=self.resolution, cell_size=h, origin=origin,
                            target_density=torch.ones((), device=rest.device, dtype=dtype),
                            num_strands=s, num_particles=n,
                            hash_size=int(math.ceil(side / self.collision_radius)) + 3)
        if self.target_density is not None:
            target = torch.as_tensor(self.target_density, device=rest.device, dtype=dtype)
        else:
            rho = grid_density(grid, rest, mass, None)
            target = rho.max() * self.target_density_margin
        return HairHairGrid(config=self, resolution=self.resolution, cell_size=h, origin=origin,
                            target_density=target, num_strands=s, num_particles=n, hash_size=grid.hash_size)


@dataclass(frozen=True)
class HairHairGrid:
    """Fixed data of the hair–hair grid (built by :meth:`HairHair.build`; no batch dims).

    Fields:
        config: the :class:`HairHair` it was built from.
        resolution: R, cells per axis.
        cell_size: h, metres (cubic cells).
        origin: (3,) metres, the grid's lower corner in the head frame.
        target_density: () kg/m³, ρ₀.
        num_strands, num_particles: S and N of the groom it was fitted to.
        hash_size: cells per axis of the detailed-collision hash (cell size = collision radius).
    """

    config: HairHair
    resolution: int
    cell_size: float
    origin: torch.Tensor
    target_density: torch.Tensor
    num_strands: int
    num_particles: int
    hash_size: int

    @property
    def extent(self) -> float:
        """Side of the cubic grid, metres."""
        return self.cell_size * self.resolution


def build_hair_hair(config: Optional[HairHair], rest_positions, particle_mass, device=None,
                    dtype=None) -> Optional[HairHairGrid]:
    """``config.build(...)``, or ``None`` (nothing allocated, nothing run) when ``config`` is None.

    Args as :meth:`HairHair.build`: rest_positions (S, N, 3) m in the head frame, particle_mass kg
    broadcastable to (S, N).
    """
    if config is None:
        return None
    if not isinstance(config, HairHair):
        raise ValueError(f"hair_hair must be a HairHair config or None; got {type(config).__name__}")
    return config.build(rest_positions, particle_mass, device=device, dtype=dtype)


# ---------------------------------------------------------------------------------------------
# frames
# ---------------------------------------------------------------------------------------------
def _flatten(grid: HairHairGrid, x: torch.Tensor, v: Optional[torch.Tensor], mass, head_pose: Optional[Pose]):
    """Flatten leading dims and go to the head frame.

    Returns xl (B, P, 3) head-frame positions, vl (B, P, 3) head-frame velocities relative to the
    grid's rigid motion (None if v is None), m (B, P) kg, rot (B, 3, 3), lead dims.
    """
    if x.dim() < 3 or x.shape[-1] != 3:
        raise ValueError(f"x must have shape (..., S, N, 3); got {tuple(x.shape)}")
    s, n = x.shape[-3], x.shape[-2]
    if (s, n) != (grid.num_strands, grid.num_particles):
        raise ValueError(f"x has (S, N) = ({s}, {n}) but the grid was built for "
                         f"({grid.num_strands}, {grid.num_particles})")
    if v is not None and v.shape != x.shape:
        raise ValueError(f"v must have the shape of x {tuple(x.shape)}; got {tuple(v.shape)}")
    lead = x.shape[:-3]
    b = math.prod(lead)
    p = s * n
    dt_, dev = x.dtype, x.device
    mass = torch.as_tensor(mass, device=dev, dtype=dt_)
    try:
        m = mass.expand(*lead, s, n).reshape(b, p)
    except RuntimeError:
        raise ValueError(f"mass of shape {tuple(mass.shape)} does not broadcast to {tuple(lead) + (s, n)}")
    xf = x.reshape(b, p, 3)
    if head_pose is None:
        rot = torch.eye(3, device=dev, dtype=dt_).expand(b, 3, 3)
        trans = torch.zeros(b, 3, device=dev, dtype=dt_)
        lin = ang = None
    else:
        try:
            rot = head_pose.rotation.to(device=dev, dtype=dt_).expand(*lead, 3, 3).reshape(b, 3, 3)
            trans = head_pose.translation.to(device=dev, dtype=dt_).expand(*lead, 3).reshape(b, 3)
            lin = ang = None
            if head_pose.linear_velocity is not None:
                lin = head_pose.linear_velocity.to(device=dev, dtype=dt_).expand(*lead, 3).reshape(b, 3)
            if head_pose.angular_velocity is not None:
                ang = head_pose.angular_velocity.to(device=dev, dtype=dt_).expand(*lead, 3).reshape(b, 3)
        except RuntimeError:
            raise ValueError(f"head_pose batch shape {tuple(head_pose.rotation.shape[:-2])} does not "
                             f"broadcast to the leading dims of x {tuple(lead)}")
    rel = xf - trans[:, None, :]
    xl = torch.einsum("bji,bpj->bpi", rot, rel)
    vl = None
    if v is not None:
        vr = v.reshape(b, p, 3)
        if lin is not None:
            vr = vr - lin[:, None, :]
        if ang is not None:
            vr = vr - torch.cross(ang[:, None, :].expand_as(rel), rel, dim=-1)
        vl = torch.einsum("bji,bpj->bpi", rot, vr)
    return xl, vl, m, rot, lead


# ---------------------------------------------------------------------------------------------
# transfers
# ---------------------------------------------------------------------------------------------
def _stencil(g: torch.Tensor, dims: Tuple[int, int, int], scene_size: int = 0):
    """Trilinear stencil. g: (B, P, 3) continuous sample coordinates (sample i at g = i) on a grid
    of ``dims`` samples (each ≥ 2). Returns flat indices (B, P, 8) long (scene b's grid starts at
    ``b · scene_size``) and weights (B, P, 8), zero for samples outside the grid.

    Per axis the lower corner is clamped to [0, n − 2] and the weights are moved onto the two
    corners that exist, so the 8 indices are one base index plus fixed offsets."""
    base = torch.floor(g)
    f = g - base
    i0 = base.long()
    bc = torch.stack([i0[..., a].clamp(0, dims[a] - 2) for a in range(3)], -1)  # (B, P, 3)
    d = i0 - bc  # 0 inside; −1 / 1 half outside; else fully outside
    one_f = 1 - f
    zero = torch.zeros_like(f)
    w0 = torch.where(d == 0, one_f, torch.where(d == -1, f, zero))
    w1 = torch.where(d == 0, f, torch.where(d == 1, one_f, zero))
    wa = torch.stack((w0, w1), -1)  # (B, P, 3, 2)
    w = wa[..., 0, :, None, None] * wa[..., 1, None, :, None] * wa[..., 2, None, None, :]
    b, p = g.shape[:2]
    flat = (bc[..., 0] * dims[1] + bc[..., 1]) * dims[2] + bc[..., 2]
    if scene_size:
        flat = flat + torch.arange(b, device=g.device)[:, None] * scene_size
    o = torch.arange(2, device=g.device)
    offs = ((o[:, None, None] * dims[1] + o[None, :, None]) * dims[2] + o[None, None, :]).reshape(8)
    return flat[..., None] + offs, w.reshape(b, p, 8)


def _face_dims(r: int, c: int) -> Tuple[int, int, int]:
    return tuple(r + 1 if d == c else r for d in range(3))


def _face_coords(grid: HairHairGrid, xl: torch.Tensor, c: int) -> torch.Tensor:
    """Sample coordinates (B, P, 3) of head-frame points on the face grid of component c."""
    g = (xl - grid.origin.to(xl.dtype)) / grid.cell_size
    half = torch.full((3,), 0.5, device=xl.device, dtype=xl.dtype)
    shift = torch.where(torch.arange(3, device=xl.device) == c, torch.zeros_like(half), half)
    return g - shift


def _p2g_face(grid: HairHairGrid, xl, vl, m, c: int):
    """Rasterise mass and c-momentum to the c-face grid. Returns mass and velocity
    (B, *face dims) (velocity = momentum / mass, 0 where empty), and the stencil."""
    r = grid.resolution
    dims = _face_dims(r, c)
    size = dims[0] * dims[1] * dims[2]
    b = xl.shape[0]
    idx, w = _stencil(_face_coords(grid, xl, c), dims, size)
    if vl is None:
        vals = (w * m[..., None]).reshape(-1, 1)
    else:
        mv = torch.stack((m, m * vl[..., c]), -1)  # (B, P, 2): mass, c-momentum
        vals = (w[..., None] * mv[:, :, None, :]).reshape(-1, 2)
    acc = torch.zeros(b * size, vals.shape[1], device=xl.device, dtype=xl.dtype).index_add(0, idx.reshape(-1), vals)
    mass = acc[:, 0].reshape(b, *dims)
    if vl is None:
        return mass, None, (idx, w)
    mom = acc[:, 1].reshape(b, *dims)
    vel = mom / torch.where(mass > 0, mass, torch.ones_like(mass))
    vel = torch.where(mass > 0, vel, torch.zeros_like(vel))
    return mass, vel, (idx, w)


def _g2p(field: torch.Tensor, stencil) -> torch.Tensor:
    """Trilinear interpolation of a (B, *dims) grid field at the stencil's particles: (B, P)."""
    idx, w = stencil
    return (field.reshape(-1)[idx] * w).sum(-1)


def _cell_mass(face_mass) -> torch.Tensor:
    """Cell-centred mass (B, R, R, R) kg: mean over axes of the average of the two faces."""
    total = 0
    for c, mf in enumerate(face_mass):
        r = mf.shape[1 + c] - 1
        total = total + 0.5 * (mf.narrow(1 + c, 0, r) + mf.narrow(1 + c, 1, r))
    return total / 3.0


def grid_density(grid: HairHairGrid, x: torch.Tensor, mass, head_pose: Optional[Pose] = None) -> torch.Tensor:
    """Hair density on the grid, as the stage sees it.

    Args:
        grid: a :class:`HairHairGrid`.
        x: (..., S, N, 3) metres, world positions.
        mass: kg, broadcastable to (..., S, N).
        head_pose: head pose (world ← head frame); None = identity.
    Returns:
        (..., R, R, R) kg/m³, cell-centred, indexed [i, j, k] along the head frame's x, y, z.
    """
    xl, _, m, _, lead = _flatten(grid, x, None, mass, head_pose)
    face_mass = [_p2g_face(grid, xl, None, m, c)[0] for c in range(3)]
    rho = _cell_mass(face_mass) / grid.cell_size ** 3
    r = grid.resolution
    return rho.reshape(*lead, r, r, r)


# ---------------------------------------------------------------------------------------------
# volume preservation
# ---------------------------------------------------------------------------------------------
def _neighbour_sum(phi: torch.Tensor) -> torch.Tensor:
    """Sum of the 6 face neighbours of each cell of (B, R, R, R), zero outside.

    Accumulates shifted slices into a fresh buffer (in place on that buffer only, which
    autograd handles: no input is modified); several times faster on CPU than padding."""
    n = torch.zeros_like(phi)
    n[:, 1:] += phi[:, :-1]
    n[:, :-1] += phi[:, 1:]
    n[:, :, 1:] += phi[:, :, :-1]
    n[:, :, :-1] += phi[:, :, 1:]
    n[:, :, :, 1:] += phi[:, :, :, :-1]
    n[:, :, :, :-1] += phi[:, :, :, 1:]
    return n


def _divergence(face_vel, h: float) -> torch.Tensor:
    """Cell-centred divergence (B, R, R, R) 1/s of a staggered velocity (three face grids)."""
    out = 0
    for c, u in enumerate(face_vel):
        r = u.shape[1 + c] - 1
        out = out + (u.narrow(1 + c, 1, r) - u.narrow(1 + c, 0, r))
    return out / h


def _pressure_potential(grid: HairHairGrid, rho: torch.Tensor, div_u: torch.Tensor, dt) -> torch.Tensor:
    """Velocity potential φ (B, R, R, R) m²/s ≥ 0 of the unilateral density constraint
    ``∇·(−∇φ) ≥ b`` (see the module docstring), by projected weighted Jacobi.

    rho: (B, R, R, R) kg/m³; div_u: (B, R, R, R) 1/s, divergence of the grid velocity.
    """
    cfg = grid.config
    h2 = grid.cell_size ** 2
    rho0 = grid.target_density.to(rho.dtype)
    filled = rho > rho0 * 1e-6
    safe = torch.where(filled, rho, torch.ones_like(rho))
    b = cfg.volume_stiffness * (1 - rho0 / safe) / dt
    b = torch.where(rho > rho0, torch.maximum(b, -div_u), b)
    mask = filled.to(rho.dtype)
    omega = cfg.jacobi_omega
    # φ ← max(0, (1 − ω) φ + ω (h² b + Σ_neighbours φ) / 6) in filled cells, 0 elsewhere
    src = torch.where(filled, b * (h2 * omega / 6.0), torch.zeros_like(b))
    phi = torch.zeros_like(rho)
    for _ in range(cfg.pressure_iterations):
        nxt = torch.addcmul(src, _neighbour_sum(phi), mask, value=omega / 6.0)
        phi = nxt.add(phi, alpha=1.0 - omega).clamp_min(0)
    return phi


def _face_gradient(phi: torch.Tensor, c: int, h: float) -> torch.Tensor:
    """∂φ/∂x_c on the c-faces (B, *face dims), φ = 0 outside the grid."""
    pad = [0, 0, 0, 0, 0, 0]
    pad[2 * (2 - c)] = 1
    pad[2 * (2 - c) + 1] = 1
    p = F.pad(phi, tuple(pad))
    n = p.shape[1 + c]
    return (p.narrow(1 + c, 1, n - 1) - p.narrow(1 + c, 0, n - 1)) / h


# ---------------------------------------------------------------------------------------------
# detailed collisions
# ---------------------------------------------------------------------------------------------
def _detailed_collisions(grid: HairHairGrid, xl, vl, m, free_p, dt):
    """Particle repulsion between strands through a sort-based spatial hash (head frame).

    xl, vl: (B, P, 3) head-frame positions (m) and relative velocities (m/s) after the grid
    stage; m: (B, P) kg; free_p: (P,) bool. Returns (dx, dv) (B, P, 3) corrections (m, m/s).
    The particles are sorted once by hash-cell key; each of the 27 neighbour offsets is then
    one batched lookup (``searchsorted``) of up to K candidates per particle, so peak memory is
    O(P · K), not O(P · 27 · K).
    """
    cfg = grid.config
    r = cfg.collision_radius
    k = cfg.collision_max_per_cell
    hs = grid.hash_size
    b, p, _ = xl.shape
    dev, dtype = xl.device, xl.dtype
    cell = torch.floor((xl - grid.origin.to(dtype)) / r).long().clamp(-1, hs - 2) + 1  # in [0, hs − 1]
    scene = torch.arange(b, device=dev)[:, None]

    key = ((scene * hs + cell[..., 0]) * hs + cell[..., 1]) * hs + cell[..., 2]  # (B, P)
    sorted_key, order = torch.sort(key.reshape(-1))
    xf, vf = xl.reshape(b * p, 3), vl.reshape(b * p, 3)
    free_f = free_p.to(dtype)
    inv = free_f / m  # (B, P) inverse mass, 0 for pinned particles
    inv_f = inv.reshape(-1)
    strand_i = (torch.arange(p, device=dev) // grid.num_particles)[None, :, None]
    slots = torch.arange(k, device=dev)
    push = torch.zeros_like(xl)
    stop = torch.zeros_like(xl)
    count = torch.zeros(b, p, device=dev, dtype=dtype)
    for ox in (-1, 0, 1):
        for oy in (-1, 0, 1):
            for oz in (-1, 0, 1):
                inside = torch.ones_like(key, dtype=torch.bool)
                for axis, o in enumerate((ox, oy, oz)):
                    if o:
                        ca = cell[..., axis] + o
                        inside = inside & (ca >= 0) & (ca < hs)
                nkey = (key + ((ox * hs) + oy) * hs + oz).reshape(-1)  # meaningful where inside
                start = torch.searchsorted(sorted_key, nkey).reshape(b, p, 1)
                end = torch.searchsorted(sorted_key, nkey, right=True).reshape(b, p, 1)
                slot = start + slots  # (B, P, K)
                j = order[slot.clamp_max(b * p - 1)]  # flat ids over B·P
                ok = (slot < end) & inside[..., None] & ((j % p) // grid.num_particles != strand_i)
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


# ---------------------------------------------------------------------------------------------
# the stage
# ---------------------------------------------------------------------------------------------
def hair_hair_stage(grid: Optional[HairHairGrid], x: torch.Tensor, v: torch.Tensor, mass,
                    head_pose: Optional[Pose], dt, free: Optional[torch.Tensor] = None):
    """Hair–hair interaction for one frame (SPEC §6), run after inextensibility.

    Args:
        grid: from :meth:`HairHair.build`; ``None`` returns ``(x, v)`` untouched (disabled).
        x: (..., S, N, 3) metres, world positions at the end of the frame.
        v: (..., S, N, 3) m/s, world velocities at the end of the frame.
        mass: kg, broadcastable to (..., S, N).
        head_pose: head :class:`Pose` at the end of the frame (world ← head frame, batch dims
            broadcastable to ``...``); missing velocities count as zero; None = identity at rest.
        dt: frame length, seconds.
        free: (N,) bool, particles the stage may move (default: all). Pinned particles still
            contribute mass to the grid but are returned unchanged.
    Returns:
        (x', v'): (..., S, N, 3) metres and m/s, with ``x' = x + dt (v' − v)`` for the grid part
        (plus the position push of detailed collisions, when enabled).
    """
    if grid is None:
        return x, v
    if isinstance(dt, (int, float)) and not (math.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be a positive number of seconds; got {dt!r}")
    cfg = grid.config
    xl, vl, m, rot, lead = _flatten(grid, x, v, mass, head_pose)
    b, p, _ = xl.shape
    n = grid.num_particles
    if free is None:
        free_p = torch.ones(p, dtype=torch.bool, device=x.device)
    else:
        if free.shape != (n,):
            raise ValueError(f"free must have shape ({n},); got {tuple(free.shape)}")
        free_p = free.to(device=x.device, dtype=torch.bool).repeat(grid.num_strands)

    face_mass, face_vel, stencils = [], [], []
    for c in range(3):
        mf, uf, st = _p2g_face(grid, xl, vl, m, c)
        face_mass.append(mf)
        face_vel.append(uf)
        stencils.append(st)
    if cfg.pressure_iterations > 0:
        rho = _cell_mass(face_mass) / grid.cell_size ** 3
        phi = _pressure_potential(grid, rho, _divergence(face_vel, grid.cell_size), dt)
    else:
        phi = None
    pic = 1.0 - cfg.flip
    dvl = []
    for c in range(3):
        field = pic * face_vel[c]
        if phi is not None:
            field = field - _face_gradient(phi, c, grid.cell_size)
        wsum = stencils[c][1].sum(-1)
        dvl.append(_g2p(field, stencils[c]) - pic * wsum * vl[..., c])
    dvl = torch.stack(dvl, -1)  # (B, P, 3) head frame
    dvl = torch.where(free_p[None, :, None], dvl, torch.zeros_like(dvl))
    dxl = dt * dvl
    if cfg.detailed_collisions:
        cx, cv = _detailed_collisions(grid, xl + dxl, vl + dvl, m, free_p, dt)
        free3 = free_p[None, :, None]
        dxl = dxl + torch.where(free3, cx, torch.zeros_like(cx))
        dvl = dvl + torch.where(free3, cv, torch.zeros_like(cv))
    dv = torch.einsum("bij,bpj->bpi", rot, dvl).reshape(x.shape)
    dx = torch.einsum("bij,bpj->bpi", rot, dxl).reshape(x.shape)
    return x + dx, v + dv


def make_stage(grid: Optional[HairHairGrid], mass, free: Optional[torch.Tensor] = None) -> Optional[Callable]:
    """Wrap :func:`hair_hair_stage` as an integrator stage ``(x, v, pose, dt, state) -> (x, v)``.

    Args: grid (None → returns None), mass kg broadcastable to (..., S, N), free (N,) bool.
    """
    if grid is None:
        return None

    def stage(x, v, pose, dt, state=None):
        return hair_hair_stage(grid, x, v, mass, pose, dt, free)

    return stage
