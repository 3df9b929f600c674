"""Parameter identification through rollouts (:mod:`ams_torch.apps.identify`, driven by
``scripts/identify.py``): the fits recover two material fields of a tiny groom and a per-strand
field, and the gradient of a rollout loss matches finite differences, with and without
checkpointing."""
import time

import pytest
import torch
from helpers import load_script

import ams_torch as at
from ams_torch.testing import sphere_groom

F64 = torch.float64


@pytest.fixture(scope="module")
def identify():
    return load_script("identify")


def tiny_case(identify, frames: int):
    """3 strands of 8 particles, a shake of ``frames`` frames, one substep; target at the same
    resolution with ω_I² = 150 s⁻², drag 2 s⁻¹."""
    rest = sphere_groom(3, 8, seed=1, dtype=F64)
    poses = identify.shake_motion(frames)
    true = {"integrity_rate": 150.0, "drag": 2.0}
    target = identify.make_target(rest, 8, 1, at.Params(**true), poses)
    return rest, poses, true, target


def test_recovers_integrity_rate_and_drag_within_5_percent(identify, capsys):
    t0 = time.perf_counter()
    rest, poses, true, target = tiny_case(identify, 12)
    start = {"integrity_rate": 75.0, "drag": 4.0}  # a factor 2 off, on either side
    sim = identify.fit_simulator(rest, at.Params(substeps=1, **start), {k: identify.Log() for k in true})
    assert {n for n, _ in sim.named_parameters()} == {f"model.parametrizations.{k}.original" for k in true}
    assert identify.values(sim) == pytest.approx(start)
    hist = identify.fit(sim, poses, target, iterations=12, optimizer="lbfgs", log=None)
    wall = time.perf_counter() - t0
    fitted = hist["final_values"]
    with capsys.disabled():
        print(f"\n[identify] {hist['iterations']} evaluations, {wall:.1f} s: " +
              ", ".join(f"{k} {fitted[k]:.4g} (true {true[k]:g})" for k in true) +
              f"; loss {hist['loss'][0]:.3g} -> {hist['final_loss']:.3g} mm²")
    for k, v in true.items():
        assert abs(fitted[k] / v - 1) < 0.05, (k, fitted[k], v)
    assert hist["final_loss"] < 1e-3 * hist["loss"][0]
    assert wall < 30.0


def test_rollout_gradient_matches_finite_differences(identify):
    """Float64, 10 frames, three random directions of the log-values: autograd through the
    checkpointed rollout against central differences; no checkpointing, every frame and segments of
    4 frames agree to rounding."""
    rest, poses, true, target = tiny_case(identify, 10)
    sim = identify.fit_simulator(rest, at.Params(substeps=1, integrity_rate=75.0, drag=4.0),
                                 {k: identify.Log() for k in true})
    check = identify.fd_check(sim, poses, target, directions=3, steps=(1e-4,))
    for row in check["directions"]:
        assert row["rel"]["0.0001"] < 1e-6, row
        assert abs(row["autograd"]) > 1e-3  # not a vacuous check
    assert identify.values(sim) == pytest.approx({"integrity_rate": 75.0, "drag": 4.0})  # restored
    grads = [identify.loss_and_grad(sim, poses, target, k) for k in (0, 1, 4)]
    for g in grads[1:]:
        assert g[0] == pytest.approx(grads[0][0], rel=1e-13)
        assert g[1] == pytest.approx(grads[0][1], rel=1e-10)


def test_recovers_a_per_strand_drag(identify):
    """A per-strand field, (S, 1): three strands with drag 1, 2 and 4 s⁻¹, recovered from one start."""
    rest = sphere_groom(3, 8, seed=1, dtype=F64)
    poses = identify.shake_motion(12)
    true = torch.tensor([[1.0], [2.0], [4.0]], dtype=F64)
    target = identify.make_target(rest, 8, 1, at.Params(drag=true), poses)
    sim = identify.fit_simulator(rest, at.Params(substeps=1, drag=torch.full((3, 1), 2.5, dtype=F64)),
                                 {"drag": identify.Log()})
    assert identify.unconstrained(sim)["drag"].shape == (3, 1)
    hist = identify.fit(sim, poses, target, iterations=15, optimizer="lbfgs", log=None)
    fitted = torch.tensor(hist["final_values"]["drag"], dtype=F64)
    assert float((fitted / true - 1).abs().max()) < 0.05, fitted


def test_transition_parametrisation_stays_below_the_breaking_point(identify):
    rest = sphere_groom(2, 6, seed=2, dtype=F64)
    params = at.Params(integrity_model="nonhookean", integrity_break=1.0, integrity_transition=0.25)
    sim = identify.fit_simulator(rest, params, {"integrity_transition": identify.Fraction(1.0)})
    assert identify.values(sim)["integrity_transition"] == pytest.approx(0.25)
    z = identify.unconstrained(sim)["integrity_transition"]
    with torch.no_grad():
        z.fill_(50.0)
    assert 0.0 < identify.values(sim)["integrity_transition"] <= 1.0
