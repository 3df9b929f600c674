"""The per-length material's spring algebra (SPEC §13, docs/material.md): the small-deflection
bending stiffness that bend and torsion springs give a curved strand whose edges stretch, and the
factor by which the springs are scaled so that it does not depend on N. Pure functions of the
stiffnesses, shared by :class:`~ams_torch.sim.params.Params` (conversions between materials) and
:class:`~ams_torch.sim.model.Model` (the coefficients)."""
from __future__ import annotations

import torch

__all__ = ["coupled_bending", "stretch_coupling_factor"]

_UNBOUNDED = 1e20  # the factor where no finite one exists (the cap binds there)


def coupled_bending(bend, torsion, edge):
    """Small-deflection bending stiffness that bend and torsion springs give a curved strand whose
    edges stretch (docs/material.md): per unit length and per c² (c the rest curvature), divided by
    ℓ⁵, on a uniform planar arc of edge length ℓ: ``κ_b/4 + 4 κ_t − (κ_b + 6 κ_t)² / (κ_L + 4 κ_b + 9 κ_t)``.

    bend, torsion, edge: stiffnesses κ_b, κ_t, κ_L of the springs (i, i+2), (i, i+3), (i, i+1),
    N/m, broadcastable tensors or floats. The first two terms are the inextensible-edge stiffness
    (a uniform curvature change δc moves the chords by −c ℓ³ δc / 2 and −2 c ℓ³ δc); the last is
    what the strand saves by stretching its edges instead (the chords also resist stretch:
    2 ℓ ε and 3 ℓ ε for a strain ε). Returns N/m, the shape of the broadcast."""
    return bend / 4 + 4 * torsion - (bend + 6 * torsion) ** 2 / (edge + 4 * bend + 9 * torsion)


def stretch_coupling_factor(ell, stretch_rigidity, bend_rigidity, torsion_rigidity):
    """The factor s ≥ 1 by which the per-length material multiplies both spring kinds,
    κ_b = s B_b / ℓ⁵ and κ_t = s B_t / ℓ⁵, so that :func:`coupled_bending` with edges
    κ_L = EA / ℓ equals the inextensible-edge value of B_b / ℓ⁵, B_t / ℓ⁵: the curved strand's
    small-deflection bending stiffness is then ``c² (B_b / 4 + 4 B_t)`` at every N, whatever the
    ratio of the springs to the edges (docs/material.md).

    With b = B_b/ℓ⁵, t = B_t/ℓ⁵, P = b/4 + 4t, R = 4b + 9t it is the positive root of
    ``6.25 b t s² + P (κ_L − R) s − P κ_L = 0``: 1 for edges much stiffer than the springs, at most
    2PR / (6.25 b t) (8.84 for B_b = B_t) for edges much softer. With B_t = 0 and springs stiffer than
    a quarter of the edges the root is infinite (bend springs alone cannot stop the strand from
    bending by stretching): the stiffness cap then binds. ell: (S, K) m, the springs' rest lengths
    over their span; rigidities: EA (N) and B (N·m⁴), tensors or floats. Returns (S, K) in ell's
    dtype (computed in float64: b² and κ_L² overflow float32 on short segments)."""
    f64 = torch.float64
    ell64 = ell.to(f64)
    b, t, ea = (v.to(f64) if isinstance(v, torch.Tensor) else torch.tensor(float(v), dtype=f64, device=ell.device)
                for v in (bend_rigidity, torsion_rigidity, stretch_rigidity))
    b = b * ell64 ** -5
    t = t * ell64 ** -5
    kl = ea / ell64
    p = b / 4 + 4 * t
    lin = p * (kl - 4 * b - 9 * t)
    none = p <= 0  # no springs: any factor (1)
    sq = lin * lin + 25 * b * t * p * kl
    disc = torch.sqrt(torch.where(none, torch.ones_like(sq), sq))
    # the positive root without cancellation: 2 P κ_L / (lin + √disc) for lin ≥ 0, (√disc − lin) / (12.5 b t) else
    a2 = 12.5 * b * t
    positive = lin >= 0
    bounded = ~none & (positive | (a2 > 0))
    den = torch.where(positive, lin + disc, a2)
    s = torch.where(positive, 2 * p * kl, disc - lin) / torch.where(bounded, den, torch.ones_like(den))
    return torch.where(bounded, s, torch.where(none, torch.ones_like(s), torch.full_like(s, _UNBOUNDED))).to(ell.dtype)
