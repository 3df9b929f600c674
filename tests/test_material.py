"""The per-length material (SPEC §13): its conversions, N-independence of its stiffness, and
convergence in N at fixed dt and M (errors at material points)."""
import math
import sys
from pathlib import Path

import pytest
import torch

import ams_torch as at
from ams_torch.sim.material import coupled_bending, stretch_coupling_factor
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


def _chain(n: int, edge: float, turn: float) -> torch.Tensor:
    """(1, n, 3) m: a planar chain of equal edges turning by ``turn`` rad at every vertex."""
    angles = torch.arange(n - 1, dtype=F64) * turn
    steps = edge * torch.stack((torch.cos(angles), torch.sin(angles), torch.zeros_like(angles)), -1)
    return torch.cat([torch.zeros(1, 3, dtype=F64), steps.cumsum(0)])[None]


@pytest.mark.parametrize("k,factor", [(2, 1 / 4), (3, 4.0)])
def test_fixed_edge_bending_factors_are_a_quarter_and_four(k, factor):
    """docs/material.md: a uniform change δc of the rest curvature c with the edges held moves the
    chords of the span-k springs by −c ℓ³ δc / 2 (k = 2) and −2 c ℓ³ δc (k = 3), so the springs'
    energy per unit length is ½ (factor) c² κ ℓ⁵ δc²: 1/4 and 4 (the page once said 1/9)."""
    length, c, dc = 0.2, 20.0, 0.02
    for n in (64, 256):
        edge = length / (n - 1)
        p = at.Params(bend_rigidity=3e-11, torsion_rigidity=3e-11, stretch_rigidity=1e9, stiffness_cap=1e12)
        model = at.Simulator(_chain(n, edge, c * edge), p, dtype=F64).model
        kappa = coefficients(model)[1 + k]
        ell = model.rest_lengths[k - 1] / k
        energy = _spring_energy(model, _chain(n, edge, (c + dc) * edge), k)
        measured = 2 * energy / (length * dc * dc) / (c * c * float((kappa * ell ** 5).mean()))
        assert abs(measured / factor - 1) < 0.03 + 16 / n, (n, measured)


def test_coupled_bending_stiffness_is_the_target_at_every_n_and_stretch_rigidity():
    """The per-length springs' small-deflection bending stiffness with their stretch coupling,
    :func:`coupled_bending`, equals c² (B_b/4 + 4 B_t) at every N and EA (docs/material.md)."""
    bb, bt = 3e-11, 1e-11
    for ea in (8e-3, 1.0, 20.0):
        for n in (16, 64, 256):
            p = at.Params(bend_rigidity=bb, torsion_rigidity=bt, stretch_rigidity=ea, stiffness_cap=1e12)
            model = at.Simulator(_arc(n, 0.25, 8.0), p, dtype=F64).model
            co = coefficients(model)
            ell = model.bend_rest_length[:, 1:-1] / 2
            kb, kt, kl = co.bend[:, 1:-1], co.torsion[:, 1:], co.edge[:, 1:-2]
            got = coupled_bending(kb, kt, kl) * ell ** 5 / (bb / 4 + 4 * bt)
            torch.testing.assert_close(got, torch.ones_like(got), rtol=2e-2, atol=0)
    s = stretch_coupling_factor(torch.tensor([1e-3, 1e-2], dtype=F64), 8e-3, 3e-11, 3e-11)
    assert 1 <= float(s.min()) and float(s.max()) <= 8.85  # bounded: 1 (stiff edges) … 2PR/(6.25 b t)


def test_cantilever_deflection_converges_to_euler_bernoulli():
    """A clamped circular arc with bend and torsion springs only (soft default edges) under a small
    in-plane load: the static tip deflection over the Euler–Bernoulli curved beam of stiffness
    c² (B_b/4 + 4 B_t) tends to 1 at first order; without the stretch coupling it does not (the
    springs outgrow the edges and the strand bends by stretching)."""
    study = convergence_n.cantilever_study(ns=(16, 32, 64))
    errors = study["relative_error"]
    assert study["monotone"] and study["order"] >= 0.9, errors
    assert errors[-1] < 0.06
    old = [convergence_n.cantilever_deflection(n, coupling=False)["ratio"] for n in (16, 64)]
    assert old[1] > 5 and old[1] > old[0]  # the uncoupled conversion: 5.7 at N = 16, 8.4 at N = 64, growing


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


@pytest.mark.parametrize("name", ["wavy", "curly"])
def test_error_falls_at_first_order_in_n_against_a_finer_reference(name, capsys):
    """A small version of scripts/convergence_n.py: 3 strands of a preset, 40 frames of a shake, M = 4;
    N = 16 and 32 against N = 128 (four times finer than the finest N judged), whose own error
    against N = 256 is at most 1/5 of the errors judged (the full study: docs/material_convergence.md)."""
    case = convergence_n.preset_case(name, 3, 40)
    r = convergence_n.convergence(case, "per_length", substeps=4, ns=(16, 32), ref_n=128, check_n=256, shown=(),
                                  time_check=False)
    with capsys.disabled():
        print(f"\n[convergence in N] {name}: " + ", ".join(f"N={n}: {e:.3g} mm" for n, e in
                                                         zip(r["particles"], r["rms_error_mm"]))
              + f"; order {r['order']:.2f}; N = 128 vs 256: {r['reference_check']['rms_error_mm']:.2g} mm")
    assert r["monotone"] and r["order"] >= 0.9, r["rms_error_mm"]
    assert r["reference_check"]["over_smallest"] <= 0.2
