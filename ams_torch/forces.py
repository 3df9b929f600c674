"""One function per physical term of the AMS model (SPEC §2–4).

Every function is batched over any leading dims ``...`` (scenes) and strands ``S``:
positions are ``(..., S, N, 3)`` metres. Forces are in newtons. Where a term is treated
implicitly, the function also returns the 3×3 stiffness blocks (N/m) that the assembly
in :mod:`ams_torch.integrator` puts into the strand matrix.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

__all__ = [
    "spring_forces",
    "integrity_force",
    "angular_force",
    "gravity_force",
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


def spring_forces(x: torch.Tensor, rest_length: torch.Tensor, stiffness, k: int):
    """Linear springs between particles i and i+k (edge k=1, bending k=2, torsion k=3; SPEC §2).

    Force on i from j = i+k: ``κ (|x_j − x_i| − l) d̂_ij``, and the opposite on j.

    Args:
        x: (..., S, N, 3) positions, m.
        rest_length: (S, N−k) rest lengths l, m.
        stiffness: κ, N/m (float or tensor broadcastable to (..., S, N−k)).
        k: neighbour offset, 1 ≤ k < N.
    Returns:
        force: (..., S, N, 3) N, the springs' force on every particle.
        block: (..., S, N−k, 3, 3) N/m, ``κ D_ij`` with ``D = d̂ d̂ᵀ`` (directions frozen), the
            stiffness of each pair used by the linearised implicit step.
    """
    d = x[..., k:, :] - x[..., :-k, :]
    unit, length = safe_normalize(d)
    kappa_pair = torch.as_tensor(stiffness, dtype=x.dtype, device=x.device)  # scalar, (S,1) or (S,N-k)
    f_pair = (kappa_pair * (length - rest_length))[..., None] * unit  # on the lower particle i
    force = _pad_pairs(f_pair, k, front=True) - _pad_pairs(f_pair, k, front=False)
    block = kappa_pair[..., None, None] * unit[..., :, None] * unit[..., None, :]
    return force, block


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
    f = (kappa * theta)[..., None] * t_hat
    force = F.pad(f, (0, 0, 1, 0))
    if reaction:
        force = force - F.pad(f, (0, 0, 0, 1))
    inv_len = torch.where(e_len > 0, 1.0 / torch.where(e_len > 0, e_len, torch.ones_like(e_len)),
                          torch.zeros_like(e_len))
    eye = torch.eye(3, dtype=x.dtype, device=x.device)
    proj = eye - e_hat[..., :, None] * e_hat[..., None, :]
    tangent = (kappa * inv_len)[..., None, None] * proj
    return force, tangent


def gravity_force(mass: torch.Tensor, gravity: torch.Tensor) -> torch.Tensor:
    """Weight ``m g``. mass: (..., S, N) kg; gravity: (3,) m/s². Returns (..., S, N, 3) N."""
    return mass[..., None] * gravity
