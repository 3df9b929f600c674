"""One function per physical term of the AMS model (SPEC §2–4).

Every function is batched over any leading dims ``...`` (scenes) and strands ``S``:
positions are ``(..., S, N, 3)`` metres. Forces are in newtons. Where a term is treated
implicitly, the function also returns the 3×3 stiffness blocks (N/m) that the assembly
in :mod:`ams_torch.sim.assembly` puts into the strand matrix.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

__all__ = [
    "spring_forces",
    "geometric_stiffness_factor",
    "integrity_force",
    "integrity_elongation_law",
    "integrity_force_nonhookean",
    "integrity_yield",
    "angular_force",
    "gravity_force",
    "drag_diagonal",
    "integrity_ghost_velocity_term",
    "angular_ghost_velocity_term",
    "safe_normalize",
]


def safe_normalize(d: torch.Tensor, eps: float = 1e-20) -> tuple[torch.Tensor, torch.Tensor]:
    """Unit vectors and lengths of ``d`` (..., 3); a zero vector gives a zero direction.

    Returns (d̂ (..., 3), |d| (...)). Gradients stay finite at d = 0.
    """
    sq = (d * d).sum(-1)
    nonzero = sq > eps
    length = torch.sqrt(torch.where(nonzero, sq, torch.ones_like(sq)))
    unit = torch.where(nonzero[..., None], d / length[..., None], torch.zeros_like(d))
    return unit, torch.where(nonzero, length, torch.zeros_like(length))


def _pad_pairs(f: torch.Tensor, k: int, front: bool) -> torch.Tensor:
    """Place per-pair values (..., N−k, C) onto particles (..., N, C): the pair's lower end
    (``front=True``: particles 0..N−k−1) or upper end (particles k..N−1)."""
    pad = (0, 0, 0, k) if front else (0, 0, k, 0)
    return F.pad(f, pad)


def _aligned_derivative(kappa: torch.Tensor, d: torch.Tensor, where: torch.Tensor) -> torch.Tensor:
    """An exact zero whose derivative is ``κ ∂d`` where ``where`` (..., M) holds, zero elsewhere.

    A term ``κ c(|d|) d`` with c → 1 as d → 0 (the angular spring's ``κ θ t̂ = κ (θ / sin θ) perp``,
    the non-Hookean law's ``κ L φ(e) d̂ = κ φ'(0) d`` near the anchor) is smooth at d = 0, but written
    with :func:`safe_normalize` its autograd derivative there is zero (the direction is zeroed with
    its gradient): at the rest state, where particles sit on their ghosts' directions and anchors,
    that dropped ``κ ∂d`` (the gradient with respect to x₀ was half the finite differences'). Adding
    this term restores it and changes no forward value (``d − d.detach()`` is an exact zero).
    kappa: broadcastable to (..., M) (a scalar, (S, 1) or (S, M)); d: (..., M, 3). Returns (..., M, 3)."""
    k = kappa[..., None] if kappa.dim() > 0 else kappa
    return torch.where(where[..., None], k * (d - d.detach()), torch.zeros_like(d))


def spring_forces(x: torch.Tensor, rest_length: torch.Tensor, stiffness, k: int, geometric: bool = False):
    """Linear springs between particles i and i+k (edge k=1, bending k=2, torsion k=3; SPEC §2).

    Force on i from j = i+k: ``κ (|x_j − x_i| − l) d̂_ij``, and the opposite on j.

    Args:
        x: (..., S, N, 3) positions, m.
        rest_length: (S, N−k) rest lengths l, m.
        stiffness: κ, N/m (float or tensor broadcastable to (..., S, N−k)).
        k: neighbour offset, 1 ≤ k < N.
        geometric: also return the positive part of the geometric stiffness (SPEC §4).
    Returns:
        force: (..., S, N, 3) N, the springs' force on every particle.
        block: (..., S, N−k, 3, 3) N/m, the stiffness of each pair used by the linearised
            implicit step: ``κ D_ij`` with ``D = d̂ d̂ᵀ`` (directions frozen), plus with
            ``geometric`` ``κ (1 − l/|d|)₊ (I − D)`` (:func:`geometric_stiffness_factor`).
    """
    d = x[..., k:, :] - x[..., :-k, :]
    unit, length = safe_normalize(d)
    kappa_pair = torch.as_tensor(stiffness, dtype=x.dtype, device=x.device)  # scalar, (S,1) or (S,N-k)
    f_pair = (kappa_pair * (length - rest_length))[..., None] * unit  # on the lower particle i
    force = _pad_pairs(f_pair, k, front=True) - _pad_pairs(f_pair, k, front=False)
    # the 3×3 blocks as rows (3, 3, ..., S, N−k): every op runs along the pairs (over 3×3 blocks
    # each op would walk rows of 3), the same products and sums; one transpose at the end
    rows = unit.movedim(-1, 0).contiguous()  # (3, ..., S, N−k)
    dd = rows[:, None] * rows[None, :]
    if geometric:
        g = geometric_stiffness_factor(length, rest_length)
        eye = torch.eye(3, dtype=x.dtype, device=x.device).reshape((3, 3) + (1,) * (rows.dim() - 1))
        dd = dd + g * (eye - dd)
    block = kappa_pair * dd
    return force, block.movedim((0, 1), (-2, -1)).contiguous()


#: relative stretch below which a spring has no geometric stiffness: follow-the-leader leaves edges at
#: their rest length up to rounding, where ``(1 − l/|d|)₊`` has its kink; without this slack the matrix
#: (and the gradient) would flip with the rounding of each edge (as the non-Hookean tangent would, SPEC §7)
GEOMETRIC_SLACK = 1.000001


def geometric_stiffness_factor(length: torch.Tensor, rest_length: torch.Tensor) -> torch.Tensor:
    """``(1 − l'/|d|)₊`` with ``l' = l (1 + 1e-6)`` (:data:`GEOMETRIC_SLACK`), dimensionless,
    (..., S, N−k): the positive part of the geometric stiffness of a stretched spring relative to
    κ (SPEC §4); 0 for a spring compressed, collapsed, or within 1e-6 of its rest length (where
    follow-the-leader leaves it, so rounding cannot switch the term on and off). length |d| and
    rest_length l in metres."""
    slack = rest_length * GEOMETRIC_SLACK
    safe = torch.where(length > 0, length, torch.ones_like(length))
    return torch.where(length > slack, 1.0 - slack / safe, torch.zeros_like(length))


def integrity_force(x: torch.Tensor, ghost: torch.Tensor, stiffness) -> torch.Tensor:
    """Zero-rest-length integrity spring toward the ghost (SPEC §3): ``T_I = κ_I (y − x)``.

    x, ghost: (..., S, N, 3) m; stiffness κ_I N/m. Returns (..., S, N, 3) N. Its implicit
    stiffness is ``κ_I I`` (added by the assembly). No direction is normalised, so x = y is
    exactly zero force (the authors' code divides by zero there).
    """
    kappa = torch.as_tensor(stiffness, dtype=x.dtype, device=x.device)
    if kappa.dim() > 0:  # per strand (S, 1) or per particle (S, N): broadcast over xyz
        kappa = kappa[..., None]
    return kappa * (ghost - x)


def angular_force(x: torch.Tensor, ghost: torch.Tensor, stiffness, reaction: bool = True, eps: float = 1e-12):
    """Angular spring rotating each segment toward its ghost segment (SPEC §3).

    With ``e = x_{i+1} − x_i``, ``g = y_{i+1} − y_i`` and θ = angle(e, g), the force on
    x_{i+1} is ``κ_α θ t̂`` where t̂ is the unit part of ĝ orthogonal to ê. θ = 0 or e ∥ g
    (or a zero-length segment) gives exactly zero force. The ghosts never feel the strand.

    ``reaction=True`` (the library default) also puts ``−κ_α θ t̂`` on x_i, so the spring is
    a pure torque on the segment (a couple, no net force) and derives from the potential
    ``½ κ_α |e| θ²``. ``reaction=False`` is the paper's literal one-particle force: it is not
    conservative (a follower load), and a free wisp under it flutters without settling
    (measured in tests/test_ablations.py), growing worse as the time step shrinks.

    Args:
        x, ghost: (..., S, N, 3) m.
        stiffness: κ_α, N/rad.
    Returns:
        force: (..., S, N, 3) N (zero on particle 0).
        tangent: (..., S, N−1, 3, 3) N/m, ``κ_α/|e| (I − êêᵀ)``: the (positive semi-definite)
            stiffness of the force with respect to the segment vector e, for the implicit step.
    """
    e_hat, e_len = safe_normalize(x[..., 1:, :] - x[..., :-1, :])
    g_hat, _ = safe_normalize(ghost[..., 1:, :] - ghost[..., :-1, :])
    cos = (e_hat * g_hat).sum(-1)
    perp = g_hat - e_hat * cos[..., None]  # |perp| = sin θ
    t_hat, sin = safe_normalize(perp, eps=eps * eps)
    theta = torch.atan2(sin, cos)
    kappa = torch.as_tensor(stiffness, dtype=x.dtype, device=x.device)
    f = (kappa * theta)[..., None] * t_hat + _aligned_derivative(kappa, perp, (sin == 0) & (cos > 0))
    force = F.pad(f, (0, 0, 1, 0))
    if reaction:
        force = force - F.pad(f, (0, 0, 0, 1))
    inv_len = torch.where(e_len > 0, 1.0 / torch.where(e_len > 0, e_len, torch.ones_like(e_len)),
                          torch.zeros_like(e_len))
    # as rows (3, 3, ..., S, N−1) (see spring_forces), one transpose at the end
    rows = e_hat.movedim(-1, 0).contiguous()
    eye = torch.eye(3, dtype=x.dtype, device=x.device).reshape((3, 3) + (1,) * (rows.dim() - 1))
    proj = eye - rows[:, None] * rows[None, :]
    tangent = (kappa * inv_len) * proj
    return force, tangent.movedim((0, 1), (-2, -1)).contiguous()


def gravity_force(mass: torch.Tensor, gravity: torch.Tensor) -> torch.Tensor:
    """Weight ``m g``. mass: (..., S, N) kg; gravity: (3,) m/s². Returns (..., S, N, 3) N."""
    return mass[..., None] * gravity


def drag_diagonal(drag_coefficient: torch.Tensor, h) -> torch.Tensor:
    """Linear drag ``−γ_i v_i`` against still air (SPEC §4 ``G``), taken implicitly: it adds
    ``Δt' γ_i`` to each particle's mass on the block diagonal (its explicit part is zero).

    drag_coefficient: (S, N) kg/s, γ_i = drag rate × m_i; h: substep Δt', s. Returns (S, N) kg.
    """
    return h * drag_coefficient


def integrity_ghost_velocity_term(scaled_tangent: torch.Tensor, ghost_velocity: torch.Tensor) -> torch.Tensor:
    """Right-hand-side term of the integrity spring from the ghosts' motion over the substep,
    ``Δt'² K w`` (K = −∂T_I/∂x: κ_I I for the Hookean law, the curve's tangent otherwise).

    scaled_tangent: Δt'² K, (..., S, N, 3, 3) kg, or (S, N)/(..., S, N) kg for K = κ_I I;
    ghost_velocity: (..., S, N, 3) m/s. Returns (..., S, N, 3) kg·m/s.
    """
    if scaled_tangent.dim() == ghost_velocity.dim() + 1:
        return torch.einsum("...ij,...j->...i", scaled_tangent, ghost_velocity)
    return scaled_tangent[..., None] * ghost_velocity


def angular_ghost_velocity_term(scaled_tangent: torch.Tensor, ghost_velocity: torch.Tensor, v: torch.Tensor,
                                reaction: bool) -> torch.Tensor:
    """Right-hand-side term of the implicit angular spring from the ghost segments' motion.

    scaled_tangent: Δt'² K, (..., S, N−1, 3, 3) kg, with K = κ_α/|e| (I − êêᵀ) of each segment;
    ghost_velocity, v: (..., S, N, 3) m/s. As a couple (``reaction``) the segment's two ends get
    ``∓Δt'² K (w_{i+1} − w_i)``; the one-particle form puts ``Δt'² K (v_i + w_{i+1} − w_i)`` on
    particle i+1 (its neighbour taken explicitly). Returns (..., S, N, 3) kg·m/s.
    """
    dw = ghost_velocity[..., 1:, :] - ghost_velocity[..., :-1, :]
    if reaction:
        g = torch.einsum("...ij,...j->...i", scaled_tangent, dw)
        return F.pad(g, (0, 0, 1, 0)) - F.pad(g, (0, 0, 0, 1))
    rel = v[..., :-1, :] + dw
    return F.pad(torch.einsum("...ij,...j->...i", scaled_tangent, rel), (0, 0, 1, 0))


def integrity_elongation_law(elongation: torch.Tensor, transition, breaking, soft_ratio):
    """The non-Hookean integrity curve (SPEC §7, paper Fig. 3) in units of κ_I · L.

    With elongation e (dimensionless, distance / local rest segment length L), t = transition,
    b = breaking point and ρ = soft_ratio ∈ (0, 1]:

    - e ≤ t: Hookean, ``φ = e``, slope 1;
    - t < e ≤ b: softening, ``φ = e − (1 − ρ)(e − t)² / (2 (b − t))``, slope falling from 1 to ρ;
    - e > b: yield, ``φ = φ(b)`` (the plastic update then moves the ghost).

    Returns (φ, s), both shaped like ``elongation``; the force magnitude is κ_I L φ. ``s`` is the
    slope used for the implicit tangent: dφ/de below the breaking point, and its value from
    below, ρ, at and beyond it (SPEC §7). The plastic update puts yielded particles exactly on
    e = b, so a slope that jumped there (ρ below, 0 above) would let rounding pick the matrix
    (measured: a 1e-12 m/s perturbation grew to 2.8 mm in 30 frames); this slope is continuous
    in e. φ is continuous, C¹ at the transition and non-decreasing, so the tangent is never
    negative. t, b, ρ: floats or tensors broadcastable to ``elongation`` (learnable).
    """
    span = breaking - transition
    over = (elongation - transition).clamp(min=0.0)
    over_c = torch.minimum(over, torch.as_tensor(span, dtype=elongation.dtype, device=elongation.device))
    below = torch.minimum(elongation, torch.as_tensor(transition, dtype=elongation.dtype, device=elongation.device))
    phi = below + over_c - (1.0 - soft_ratio) * over_c * over_c / (2.0 * span)
    slope = 1.0 - (1.0 - soft_ratio) * over_c / span
    return phi, slope


def integrity_force_nonhookean(x: torch.Tensor, anchor: torch.Tensor, preload: torch.Tensor, stiffness,
                               segment_length: torch.Tensor, transition: float = 0.5, breaking: float = 1.0,
                               soft_ratio: float = 0.25):
    """Non-Hookean integrity spring (SPEC §7): Hookean, then softer, then yielding.

    The ghost is ``y = anchor + preload/κ_I``: ``anchor`` is where the particle sits at rest
    and ``preload`` the constant sag-free force κ_I·(y − anchor) that holds its weight (SPEC §5;
    zero without sag-free). The elongation is ``e = |anchor − x| / L`` with L the particle's
    local rest segment length, i.e. the particle–ghost distance measured from the sag-free
    equilibrium (with ``sag_free=False`` exactly the particle–ghost distance over L). The force is

        T_I = preload + κ_I L φ(e) d̂,     d = anchor − x,

    with φ from :func:`integrity_elongation_law`; below the transition this equals the
    Hookean ``κ_I (y − x)`` exactly.

    Args:
        x, anchor: (..., S, N, 3) m, world positions of the particles and their rest anchors.
        preload: (..., S, N, 3) N, sag-free preload (world).
        stiffness: κ_I, N/m (float or (S, 1)/(S, N) tensor).
        segment_length: (S, N) m, local rest segment length L (> 0).
        transition, breaking: elongations (dimensionless) where softening and yield begin.
        soft_ratio: slope of the curve at the breaking point relative to κ_I, in (0, 1].
    Returns:
        force: (..., S, N, 3) N.
        tangent: (..., S, N, 3, 3) N/m, ``κ_I (φ'(e) d̂d̂ᵀ + φ(e)/e (I − d̂d̂ᵀ))``: −∂T_I/∂x, symmetric
            positive semi-definite (κ_I I below the transition), for the implicit diagonal.
        elongation: (..., S, N) dimensionless.
    """
    kappa = torch.as_tensor(stiffness, dtype=x.dtype, device=x.device)
    unit, dist = safe_normalize(anchor - x)
    e = dist / segment_length
    phi, slope = integrity_elongation_law(e, transition, breaking, soft_ratio)
    force = preload + (kappa * segment_length * phi)[..., None] * unit + \
        _aligned_derivative(kappa * slope, anchor - x, dist == 0)
    secant = torch.where(e > 0, phi / torch.where(e > 0, e, torch.ones_like(e)), torch.ones_like(e))
    eye = torch.eye(3, dtype=x.dtype, device=x.device)
    dd = unit[..., :, None] * unit[..., None, :]
    k = kappa[..., None, None] if kappa.dim() > 0 else kappa  # scalar or (S, 1)/(S, N)
    tangent = k * (slope[..., None, None] * dd + secant[..., None, None] * (eye - dd))
    return force, tangent, e


def integrity_yield(x_local: torch.Tensor, anchor_local: torch.Tensor, segment_length: torch.Tensor,
                    breaking: float, free: torch.Tensor) -> torch.Tensor:
    """Plastic flow of the integrity coupling (SPEC §7): move each anchor so that the
    elongation is at most the breaking point.

    x_local, anchor_local: (..., S, N, 3) m in the head frame; segment_length: (S, N) m;
    free: (N,) bool, particles allowed to yield (pinned ones keep their anchor).
    Returns the new anchors (..., S, N, 3) m: ``x + b L d̂`` where the elongation exceeded b,
    unchanged elsewhere.
    """
    unit, dist = safe_normalize(anchor_local - x_local)
    limit = breaking * segment_length
    over = (dist > limit) & free
    moved = x_local + limit[..., None] * unit
    return torch.where(over[..., None], moved, anchor_local)
