"""The per-length material (SPEC §13): its conversions, N-independence of its stiffness, and
convergence in N at fixed dt and M (errors at material points)."""
import math
import sys
from pathlib import Path

import pytest
import torch

import ams_torch as at
from ams_torch.sim.model import coefficients

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
import convergence_n  # noqa: E402

F64 = torch.float64


def _arc(n: int, length: float, curvature: float) -> torch.Tensor:
    """(1, n, 3) m: a planar arc of the given curvature (1/m) and arc length, uniform edges."""
    s = torch.linspace(0, length, n, dtype=F64)
    phi = curvature * s
    return torch.stack((torch.sin(phi) / curvature, (1 - torch.cos(phi)) / curvature, torch.zeros_like(s)), -1)[None]


def _spring_energy(model, x, k: int) -> float:
    kappa = coefficients(model)[1 + k]  # edge, bend, torsion: fields 2, 3, 4 of Coefficients
    d = (x[:, k:] - x[:, :-k]).norm(dim=-1)
    return float(0.5 * (kappa * (d - model.rest_lengths[k - 1]) ** 2).sum())


@pytest.mark.parametrize("k,factor", [(2, (8 / 12) ** 2), (3, (27 / 12) ** 2)])
def test_curved_strand_bending_stiffness_per_length_is_independent_of_n(k, factor):
    """A uniform change δc of a rest arc's curvature c, edges kept: the span-k springs' energy per
    unit length is ½ B δc² with B = (k³/12)² c² B_proxy at every N (docs/material.md)."""
    length, c, dc = 0.2, 20.0, 0.2
    stiffness = {}
    for n in (16, 32, 64, 128):
        p = at.Params(bend_rigidity=3e-11, torsion_rigidity=3e-11)
        sim = at.Simulator(_arc(n, length, c), p, dtype=F64)
        bent = _arc(n, length, c + dc)
        stiffness[n] = 2 * _spring_energy(sim.model, bent, k) / (length * dc * dc)
    expected = factor * c * c * 3e-11
    assert abs(stiffness[128] / expected - 1) < 0.01
    # N-independent up to the strand's ends (N − k springs on N − 1 edges) and O((c l)²) terms
    spread = [abs(stiffness[n] / stiffness[128] - 1) for n in (16, 32, 64)]
    assert max(spread) < 0.05
    # the per-particle springs would change it by 2⁵ per doubling of N
    p = at.Params(material="per_particle")
    per = [2 * _spring_energy(at.Simulator(_arc(n, length, c), p, dtype=F64).model, _arc(n, length, c + dc), k)
           / (length * dc * dc) for n in (16, 32)]
    assert 25 < per[0] / per[1] < 40


def test_conversion_both_ways_gives_the_same_coefficients():
    rest = _arc(33, 0.256, 8.0)  # edges of 8 mm
    ell = float((rest[0, 1] - rest[0, 0]).norm())
    pp = at.Params(material="per_particle", particle_mass=2e-6, stretch_stiffness=3.0, integrity_stiffness=5e-4,
                   angular_stiffness=7e-5, bend_scale=0.5)
    pl = pp.to_per_length(ell)
    a = coefficients(at.Simulator(rest, pp, dtype=F64).model)
    b = coefficients(at.Simulator(rest, pl, dtype=F64).model)
    interior = slice(1, -1)  # the ends carry half an edge of mass in the per-length material
    for name in ("mass", "drag", "integrity"):
        torch.testing.assert_close(getattr(b, name)[:, interior], getattr(a, name)[:, interior], rtol=1e-9, atol=0)
    torch.testing.assert_close(b.edge, a.edge, rtol=1e-9, atol=0)
    torch.testing.assert_close(b.angular, a.angular, rtol=1e-12, atol=0)
    torch.testing.assert_close(b.bend, a.bend, rtol=5e-3, atol=0)  # ℓ is the half chord: l (1 − (c l)²/8)
    back = pl.to_per_particle(ell)
    for f in ("particle_mass", "stretch_stiffness", "integrity_stiffness", "angular_stiffness", "bend_scale"):
        assert math.isclose(getattr(back, f), getattr(pp, f), rel_tol=1e-12), f
    assert back.num_pinned == pp.num_pinned


def test_root_length_pins_a_fixed_arc_length():
    rest = _arc(65, 0.25, 4.0)
    p = at.Params(root_length=0.02)
    model = at.Simulator(rest, p, dtype=F64).model
    edge = 0.25 / 64
    assert int(model.num_pinned[0]) == 1 + math.floor(0.02 / edge + 1e-9)
    assert int(at.Simulator(_arc(8, 0.25, 4.0), p, dtype=F64).model.num_pinned[0]) == 2  # at least root + direction


@pytest.mark.parametrize("case", ["wisp", "head"])
def test_error_falls_monotonically_in_n_under_the_per_length_material(case, capsys):
    """Errors of N = 8, 16, 32, 64 against N = 128 at fixed dt and M fall monotonically, at about
    first order (the full measurement, with the per-particle material beside it, is
    docs/material_convergence.md)."""
    c = convergence_n.wisp_case(3, 20) if case == "wisp" else convergence_n.head_case(4, 12)
    r = convergence_n.convergence(c, "per_length", substeps=8)
    with capsys.disabled():
        print(f"\n[convergence in N] {case}: " + ", ".join(f"N={n}: {e:.3g} mm" for n, e in
                                                         zip(r["particles"], r["rms_error_mm"]))
              + f"; order {r['order']:.2f}; time error {r['time_error_mm']:.2g} mm")
    assert r["monotone"], r["rms_error_mm"]
    assert r["order"] > 0.6
    assert r["time_error_mm"] < r["rms_error_mm"][1]  # below the errors being compared (same M for every N)
