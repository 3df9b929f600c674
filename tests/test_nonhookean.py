"""Non-Hookean integrity tension (SPEC §7): the curve, its tangent, the plastic yield, and the
roller-coaster ride that scrambles the hair for good (Hookean hair relaxes back)."""
import pytest
import torch

import ams_torch as at
from ams_torch.sim import forces
from ams_torch.apps.motion import RollerCoaster, Shake
from ams_torch.testing import shake_poses, shape_deviation, sphere_groom


def test_curve_continuous_monotone_and_matches_hookean_below_transition():
    e = torch.linspace(0, 3, 3001, dtype=torch.float64)
    phi, slope = forces.integrity_elongation_law(e, 0.5, 1.0, 0.25)
    assert torch.allclose(phi[e <= 0.5], e[e <= 0.5])
    assert (torch.diff(phi) >= -1e-15).all() and (slope >= 0).all()
    assert (phi[e > 1.0] == phi[e > 1.0][0]).all()  # yield plateau
    # the slope is the derivative (C¹ at the transition; a kink into the yield plateau)
    num = torch.diff(phi) / torch.diff(e)
    mid = 0.5 * (e[1:] + e[:-1])
    away = (mid - 1.0).abs() > 2e-3
    assert torch.allclose(num[away], forces.integrity_elongation_law(mid, 0.5, 1.0, 0.25)[1][away], atol=1e-6)
    assert slope[(e > 0.5) & (e < 1.0)].min() >= 0.25 - 1e-12


def test_tangent_is_psd_and_is_the_jacobian():
    torch.manual_seed(0)
    x = torch.nn.functional.normalize(torch.randn(2, 5, 3, dtype=torch.float64), dim=-1)
    x = x * torch.linspace(0.002, 0.03, 10, dtype=torch.float64).reshape(2, 5, 1)  # e from 0.1 to 1.5
    anchor = torch.zeros_like(x)
    preload = torch.randn_like(x) * 1e-6
    seg = torch.full((2, 5), 0.02, dtype=torch.float64)
    f, tangent, e = forces.integrity_force_nonhookean(x, anchor, preload, 1e-4, seg)
    assert (e < 0.5).any() and ((e > 0.5) & (e < 1.0)).any() and (e > 1.0).any()
    assert (torch.linalg.eigvalsh(tangent) >= -1e-18).all()
    # −∂f/∂x per particle (the force is local to each particle)
    for s in range(2):
        for i in range(5):
            j = torch.autograd.functional.jacobian(
                lambda p: forces.integrity_force_nonhookean(p[None, None], anchor[s, i][None, None],
                                                            preload[s, i][None, None], 1e-4,
                                                            seg[s, i][None, None])[0][0, 0], x[s, i])
            assert torch.allclose(-j, tangent[s, i], atol=1e-12)


def test_nonhookean_equals_hookean_below_transition():
    rest = sphere_groom(20, 12, radius=0.1, length=0.15)
    out = {}
    for model in ("hookean", "nonhookean"):
        p = at.Params(integrity_model=model, integrity_transition=50.0, integrity_break=100.0)
        sim = at.Simulator(rest, p, dtype=torch.float64)
        st = sim.initial_state()
        for pose in shake_poses(10, p.dt, dtype=torch.float64):
            st = sim.step(st, pose)
        out[model] = st
    assert torch.allclose(out["hookean"].x, out["nonhookean"].x, atol=1e-12)
    assert torch.equal(out["nonhookean"].ghost_rest, out["hookean"].ghost_rest)  # no yield


def test_yield_keeps_elongation_at_breaking_point():
    x = torch.tensor([[[0.0, 0.0, 0.0], [0.0, 0.0, 0.05], [0.0, 0.0, 0.011]]])
    anchor = torch.zeros_like(x)
    seg = torch.full((1, 3), 0.01)
    free = torch.tensor([False, True, True])
    new = forces.integrity_yield(x, anchor, seg, 1.0, free)
    assert torch.equal(new[0, 0], anchor[0, 0])
    assert torch.allclose((new[0, 1] - x[0, 1]).norm(), torch.tensor(0.01))
    assert torch.allclose((new[0, 2] - x[0, 2]).norm(), torch.tensor(0.01))


@pytest.mark.parametrize("name,value", [("integrity_model", "plastic"), ("integrity_transition", -0.1),
                                        ("integrity_break", 0.4), ("integrity_soft_ratio", 0.0)])
def test_params_validation_names_field(name, value):
    with pytest.raises(ValueError, match=name):
        at.Params(**{name: value})


def _ride(model, motion, frames_ride, frames_rest, rest):
    p = at.Params(integrity_model=model)
    sim = at.Simulator(rest, p)
    st = sim.initial_state()
    devs = []
    for i, pose in enumerate(motion.poses(frames_ride + frames_rest, p.dt)):
        st = sim.step(st, pose)
        if i + 1 in (frames_ride, frames_ride + frames_rest):
            devs.append(float(shape_deviation(st.pose.to_local(st.x), sim.model.rest_positions).mean()))
    return devs, st, sim


def test_roller_coaster_scrambles_nonhookean_hair_for_good_and_hookean_relaxes():
    rest = sphere_groom(24, 12, radius=0.1, length=0.15)
    ride = RollerCoaster(radius=0.5, peak_g=4.0)
    n_ride = int(round(ride.duration * 60)) + 1
    n_rest = 90
    shake = Shake(amplitude=0.2, frequency=0.5)
    (nh_after, nh_later), st, sim = _ride("nonhookean", ride, n_ride, n_rest, rest)
    (sh_after, _), _, _ = _ride("nonhookean", shake, n_ride, n_rest, rest)
    (h_after, h_later), _, _ = _ride("hookean", ride, n_ride, n_rest, rest)
    print(f"\nmean deviation from rest (m): non-Hookean ride {nh_after:.4f} -> {nh_later:.4f} after "
          f"{n_rest} still frames; gentle shake {sh_after:.4f}; Hookean ride {h_after:.4f} -> {h_later:.4f}")
    assert nh_after > 5 * sh_after
    assert nh_later > 0.8 * nh_after and nh_later > 5 * sh_after  # plastic: persists at rest
    assert not torch.equal(st.ghost_rest, sim.initial_state().ghost_rest)  # ghosts moved
    assert h_later < 0.25 * h_after and h_later < 0.2 * nh_later  # Hookean relaxes back
