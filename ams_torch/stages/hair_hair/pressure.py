"""Volume preservation on the grid: a momentum-conserving unilateral pressure (SPEC §6).

The torch definition of the native ``pressure`` kernel. Derivation:

**Correction.** On every face f the grid velocity gets ``Δu_f = −(∇φ)_f / ρ_f`` with the face
density ``ρ_f = M_f / h³`` (M_f the face's P2G mass, kg; h the cell size) and a potential φ ≥ 0
at cell centres (kg/(m·s), a pressure impulse: Pa·s). G2P hands particle p the share
``Δv_p = Σ_f w_pf Δu_f`` (trilinear weights w_pf), so the particles' momentum changes by

    Σ_p m_p Δv_p = Σ_f (Σ_p m_p w_pf) Δu_f = Σ_f M_f Δu_f = −h³ Σ_f (∇φ)_f.

(The earlier form ``Δu_f = −(∇φ)_f`` gave ``−h³ Σ_f ρ_f (∇φ)_f``, which does not vanish when
the density varies: measured 8 % of Σ m|Δv| as net momentum in an asymmetric squeeze.)

**Where φ lives.** Per axis, Σ_f (∇φ)_f over a line of faces is ``Σ_i (φ_i − φ_{i−1}) / h``,
which telescopes to 0 with φ = 0 outside the grid, but only if every face is summed,
including faces whose mass is (near) zero, which no particle sees. So no such face may carry a
gradient: φ lives only on **active** cells, those whose six faces all have mass
``M_f > ε = 10⁻⁶ ρ₀ h³`` (face density above 10⁻⁶ of the target); φ = 0 on every other cell. A
face at or below ε then has two inactive neighbours, hence ∇φ = 0 and Δu = 0 there, and
``Σ_f M_f Δu_f = −h³ Σ_f (∇φ)_f = 0`` exactly (up to rounding). The threshold (rather than
M_f > 0) keeps 1/ρ_f ≤ 10⁶/ρ₀, finite in float32.

**Constraint.** With Δu as above, the divergence at cell c is
``(∇·Δu)_c = Σ_f (φ_c − φ_nb(f)) / (h² ρ_f)`` over its six faces (nb(f) the cell across f,
φ = 0 outside the grid). The unilateral density constraint ``∇·Δu ≥ b``, φ ≥ 0,
``φ (∇·Δu − b) = 0`` becomes the variable-coefficient complementarity problem

    Σ_f (φ_c − φ_nb) / ρ_f ≥ h² b_c,   φ_c ≥ 0,   φ_c (Σ_f (φ_c − φ_nb) / ρ_f − h² b_c) = 0

on active cells, solved by a fixed number of projected weighted-Jacobi sweeps from φ = 0:

    φ_c ← max(0, (1 − ω) φ_c + ω (h² b_c + Σ_f φ_nb / ρ_f) / Σ_f (1 / ρ_f)).

b is unchanged from before: the frame moved positions by Δt u, the stage moves them by Δt Δu, so
the linearised density after the correction is ``ρ (1 − Δt ∇·Δu)``; it reaches ρ₀ when
``∇·Δu = (1 − ρ₀/ρ)/Δt``, hence ``b = volume_stiffness (1 − ρ₀/ρ) / Δt`` (negative below the
target: such cells may be compressed up to ρ₀ by their neighbours' push, never pulled
together), and in cells above the target also ``b ≥ −∇·u`` (the corrected velocity stops
compressing them: an inelastic collision of wisps, tangential motion kept). ρ is the cell
density of :func:`~ams_torch.stages.hair_hair.transfer.cell_mass` / h³.

**No cell above the target.** Then every b ≤ 0 and, from φ = 0, every sweep gives
``max(0, ω h² b / Σ 1/ρ_f) = 0``: φ is exactly zero. The torch path runs the sweeps anyway (no
host-side branch on data); the native kernels skip them, with the same result.

The stage then interpolates ``pic · u + Δu`` (``field``) back to the particles (G2P).
"""
from __future__ import annotations

import torch

from ams_torch.stages.hair_hair.transfer import cell_mass, face_views

__all__ = ["ACTIVE_FACE_DENSITY", "pressure_torch"]

ACTIVE_FACE_DENSITY = 1e-6  # ε / (ρ₀ h³): faces at or below this share of the target carry no gradient


def _weighted_neighbour_sum(phi: torch.Tensor, lo, hi) -> torch.Tensor:
    """Σ_f φ_nb(f) / ρ_f per cell of (B, R, R, R), φ = 0 outside the grid; lo[c], hi[c] are 1/ρ_f
    of each cell's lower and upper c-face (B, R, R, R). Shifted slices accumulated into a fresh
    buffer in the order x−, x+, y−, y+, z−, z+ (as the native kernel)."""
    n = torch.zeros_like(phi)
    n[:, 1:] += lo[0][:, 1:] * phi[:, :-1]
    n[:, :-1] += hi[0][:, :-1] * phi[:, 1:]
    n[:, :, 1:] += lo[1][:, :, 1:] * phi[:, :, :-1]
    n[:, :, :-1] += hi[1][:, :, :-1] * phi[:, :, 1:]
    n[:, :, :, 1:] += lo[2][:, :, :, 1:] * phi[:, :, :, :-1]
    n[:, :, :, :-1] += hi[2][:, :, :, :-1] * phi[:, :, :, 1:]
    return n


def _face_gradient(phi: torch.Tensor, c: int, h: float) -> torch.Tensor:
    """∂φ/∂x_c on the c-faces (B, *face dims), φ = 0 outside the grid."""
    r = phi.shape[1 + c]
    pad_shape = list(phi.shape)
    pad_shape[1 + c] = 1
    zero = phi.new_zeros(pad_shape)
    p = torch.cat((zero, phi, zero), 1 + c)
    return (p.narrow(1 + c, 1, r + 1) - p.narrow(1 + c, 0, r + 1)) / h


def pressure_torch(faces: torch.Tensor, target_density: torch.Tensor, dt, cell_size: float, resolution: int,
                   iterations: int, omega: float, stiffness: float, pic: float):
    """The pressure solve and the face field for G2P (definition of the native ``pressure``).

    Args:
        faces: (B, 3, F, 2) face mass (kg) and momentum (kg·m/s) from P2G.
        target_density: () kg/m³, ρ₀.
        dt: s, float or 0-d tensor.
        cell_size: h, m; resolution: R.
        iterations, omega: Jacobi sweeps and relaxation weight ω.
        stiffness: volume_stiffness in [0, 1].
        pic: PIC share 1 − flip.
    Returns:
        phi: (B, R, R, R) kg/(m·s), the potential (0 off the active cells);
        field: (B, 3, F) m/s, ``pic · u + Δu`` on the faces, with u = momentum / mass (0 where
        massless) and ``Δu = −(∇φ)_f h³ / M_f`` (0 on faces at or below ε).
    """
    h = cell_size
    h2, h3 = h * h, h * h * h
    r = resolution
    b = faces.shape[0]
    rho0 = target_density.to(faces.dtype)
    mass, mom = faces[..., 0], faces[..., 1]
    has = mass > rho0 * (ACTIVE_FACE_DENSITY * h3)
    vel = torch.where(mass > 0, mom / torch.where(mass > 0, mass, torch.ones_like(mass)), torch.zeros_like(mass))
    inv_rho = torch.where(has, h3 / torch.where(has, mass, torch.ones_like(mass)), torch.zeros_like(mass))
    mass_c, vel_c, has_c, inv_c = (face_views(t, r) for t in (mass, vel, has, inv_rho))

    rho = cell_mass(mass_c) / h3
    div = None
    for c in range(3):
        dc = vel_c[c].narrow(1 + c, 1, r) - vel_c[c].narrow(1 + c, 0, r)
        div = dc if div is None else div + dc
    div = div / h
    lo = [inv_c[c].narrow(1 + c, 0, r) for c in range(3)]
    hi = [inv_c[c].narrow(1 + c, 1, r) for c in range(3)]
    active = None
    diag = None
    for c in range(3):
        both = has_c[c].narrow(1 + c, 0, r) & has_c[c].narrow(1 + c, 1, r)
        active = both if active is None else active & both
        diag = lo[c] + hi[c] if diag is None else diag + lo[c] + hi[c]
    safe = torch.where(active, rho, torch.ones_like(rho))
    rhs = stiffness * (1 - rho0 / safe) / dt
    rhs = torch.where(rho > rho0, torch.maximum(rhs, -div), rhs)
    coef = torch.where(active, omega / torch.where(active, diag, torch.ones_like(diag)), torch.zeros_like(diag))
    src = coef * (h2 * rhs)  # 0 off the active cells
    phi = torch.zeros_like(rho)
    for _ in range(iterations):
        nxt = src + coef * _weighted_neighbour_sum(phi, lo, hi)
        phi = (nxt + (1.0 - omega) * phi).clamp_min(0)
    field = []
    for c in range(3):
        du = -(_face_gradient(phi, c, h) * inv_c[c])
        field.append((pic * vel_c[c] + du).reshape(b, -1))
    return phi, torch.stack(field, 1)
