"""Assembly of one substep's linear system (SPEC §4), composed from the terms of :mod:`forces`.

Per substep of length Δt' the linearised backward-Euler step, in its symmetric form, is

    [(m_i + Δt'γ_i) I + Δt'² Σ_j κ_ij D_ij + Δt'² H_i] v_i − Σ_j Δt'² κ_ij D_ij v_j
        = m_i v_iⁿ + Δt' (f_elastic + f_biphasic + f_ext) + Δt'² (ghost-velocity terms)

stored as the lower band of a block-heptadiagonal matrix, ``blocks[..., i, k] = A[i, i−k]``
(:func:`ams_torch.solver.solve_banded`). Pinned rows become ``m_i I v_i = m_i v_pin``, their
coupling to free particles moved to the right-hand side, so the matrix stays SPD.

Profiler labels: ``ams_torch.assembly`` (all of it), ``ams_torch.springs``, ``ams_torch.biphasic``.
"""
from __future__ import annotations

from typing import Optional

import torch
import torch.nn.functional as F
from torch.profiler import record_function

from ams_torch.sim import forces
from ams_torch.sim.model import Coefficients, Model
from ams_torch.sim.state import Config
from ams_torch.solver.reference import banded_matvec

__all__ = ["assemble_system"]


def _pad_n(t: torch.Tensor, before: int, after: int) -> torch.Tensor:
    """Zero-pad (..., S, M, 3, 3) along the particle dim M."""
    return F.pad(t, (0, 0, 0, 0, before, after))


def _add_pair(diag: torch.Tensor, hk: torch.Tensor, k: int) -> None:
    """In place: a pair term hk (..., S, N−k, 3, 3) on the diagonal blocks of both its ends, the
    lower ends first (the values of ``diag + pad(hk, 0, k) + pad(hk, k, 0)`` without the padded
    copies). diag: (..., S, N, 3, 3), a tensor of the assembly's own (never an input)."""
    n = diag.shape[-3]
    diag[..., : n - k, :, :] += hk
    diag[..., k:, :, :] += hk


def assemble_system(model: Model, coeffs: Coefficients, config: Config, x: torch.Tensor, v: torch.Tensor,
                    ghost: torch.Tensor, ghost_velocity: torch.Tensor, pin_velocity: torch.Tensor, h,
                    external_force: Optional[torch.Tensor] = None, sag_offset: Optional[torch.Tensor] = None):
    """Assemble one substep's SPD block-heptadiagonal system for every strand.

    Args:
        model, coeffs, config: the groom's fixed data, its coefficients (:func:`coefficients`)
            and the step's settings.
        x, v: (..., S, N, 3) positions (m) and velocities (m/s) at the substep start.
        ghost: (..., S, N, 3) m, ghost positions y at the substep start (world).
        ghost_velocity: (..., S, N, 3) m/s, ghost velocities w over the substep.
        pin_velocity: (..., S, N, 3) m/s, prescribed velocities (read on pinned particles).
        h: substep length Δt', s.
        external_force: (..., S, N, 3) N or None.
        sag_offset: (..., S, N, 3) m, the world sag-free offset of the ghosts from the particles'
            rest anchors (read by the non-Hookean law only; None = zero).
    Returns:
        blocks: (..., S, N, 4, 3, 3) lower band, ``blocks[..., i, k] = A[i, i-k]``, kg.
        rhs: (..., S, N, 3), kg·m/s.
    """
    with record_function("ams_torch.assembly"):
        m = coeffs.mass
        eye = torch.eye(3, dtype=x.dtype, device=x.device)
        force = forces.gravity_force(m, model.gravity).expand_as(x)
        if external_force is not None:
            force = force + external_force
        # (m + Δt'γ) I, one block per particle (and scene), added to in place below
        diag = x.new_zeros(x.shape + (3,))
        diag.diagonal(dim1=-2, dim2=-1).copy_((m + forces.drag_diagonal(coeffs.drag, h))[..., None])
        offdiag = []
        with record_function("ams_torch.springs"):
            for k, kappa in zip((1, 2, 3), (coeffs.edge, coeffs.bend, coeffs.torsion)):
                f, stiff = forces.spring_forces(x, model.rest_lengths[k - 1], kappa, k, config.geometric_stiffness)
                force = force + f
                hk = (h * h) * stiff  # (..., S, N-k, 3, 3)
                _add_pair(diag, hk, k)
                offdiag.append(-hk)  # A[i, i−k] for i ≥ k (rows below k are zero)
        rhs = m[..., None] * v
        with record_function("ams_torch.biphasic"):
            force, diag, rhs = _integrity_terms(model, coeffs, config, x, ghost, ghost_velocity, h, sag_offset,
                                                eye, force, diag, rhs)
            if config.angular:
                force, diag, offdiag, rhs = _angular_terms(coeffs, config, x, v, ghost, ghost_velocity, h, force,
                                                           diag, offdiag, rhs)
        return _pinned_rows(model, m, x, pin_velocity, h, eye, force, diag, offdiag, rhs)


def _integrity_terms(model: Model, coeffs: Coefficients, config: Config, x, ghost, ghost_velocity, h, sag_offset,
                     eye, force, diag, rhs):
    """The integrity spring (SPEC §3, §7): force, its tangent on the diagonal, and the
    ghost-velocity term; unchanged when the scene has no integrity coupling."""
    if config.integrity_model == "nonhookean":
        kappa = coeffs.integrity
        offset = sag_offset if sag_offset is not None else torch.zeros_like(x)
        f, tangent, _ = forces.integrity_force_nonhookean(
            x, ghost - offset, kappa[..., None] * offset, kappa, model.segment_length,
            coeffs.transition, coeffs.breaking, coeffs.soft_ratio)
        ht = (h * h) * tangent
        return force + f, diag + ht, rhs + forces.integrity_ghost_velocity_term(ht, ghost_velocity)
    if config.integrity_model == "hookean":
        kappa = coeffs.integrity
        hk = (h * h) * kappa
        diag.diagonal(dim1=-2, dim2=-1).add_(hk[..., None])  # + κ_I Δt'² I, in place (diag is the assembly's)
        return (force + forces.integrity_force(x, ghost, kappa), diag,
                rhs + forces.integrity_ghost_velocity_term(hk, ghost_velocity))
    return force, diag, rhs


def _angular_terms(coeffs: Coefficients, config: Config, x, v, ghost, ghost_velocity, h, force, diag, offdiag, rhs):
    """The angular spring (SPEC §3): force and, when implicit, its tangent (a couple on
    (i, i+1): the band structure of an edge spring with D → I − êêᵀ; or, in the one-particle
    form, on the diagonal of i+1 only) and its ghost-velocity term."""
    f, tangent = forces.angular_force(x, ghost, coeffs.angular, config.angular_reaction)
    force = force + f
    if config.implicit_angular:
        ht = (h * h) * tangent
        if config.angular_reaction:
            _add_pair(diag, ht, 1)
            offdiag = [offdiag[0] - ht] + offdiag[1:]
        else:
            diag = diag + _pad_n(ht, 1, 0)
        rhs = rhs + forces.angular_ghost_velocity_term(ht, ghost_velocity, v, config.angular_reaction)
    return force, diag, offdiag, rhs


def _pinned_rows(model: Model, m, x, pin_velocity, h, eye, force, diag, offdiag, rhs):
    """Add the forces to the right-hand side, stack the band and impose the pinned rows."""
    rhs = rhs + h * force
    # the band: blocks[..., i, 0] = diag, blocks[..., i, k] = offdiag[k − 1][..., i − k] for i ≥ k, else 0
    blocks = diag.new_zeros(diag.shape[:-2] + (4, 3, 3))
    blocks[..., 0, :, :] = diag
    for k, o in enumerate(offdiag, 1):
        blocks[..., k:, k, :, :] = o
    if not model.has_pinned:
        return blocks, rhs
    pinned = model.pinned  # (S, N)
    # Pinned rows become m_i I v_i = m_i v_pin; their coupling to free particles moves to the
    # right-hand side, so the matrix stays symmetric positive definite (SPEC §4).
    vp = pin_velocity * pinned[..., None].to(x.dtype)
    rhs = rhs - banded_matvec(blocks, vp)
    free = ~pinned
    keep = [free]
    for k in (1, 2, 3):
        shifted = F.pad(free, (k, 0), value=False)[..., :-k]
        keep.append(free & shifted)
    keep = torch.stack(keep, -1)[..., None, None].to(x.dtype)  # (S, N, 4, 1, 1)
    blocks = blocks * keep
    blocks[..., 0, :, :] += (m[..., None, None] * eye) * pinned[..., None, None].to(x.dtype)  # m I on pinned rows
    rhs = torch.where(pinned[..., None], m[..., None] * pin_velocity, rhs)
    return blocks, rhs
