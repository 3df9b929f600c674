"""Head motions (exact velocities) and wind (downwind motion, zero wind == no wind)."""
import numpy as np
import pytest
import torch

import ams_torch as at
from ams_torch.apps.motion import Keyframes, RollerCoaster, make_motion, recorded
from ams_torch.geometry.pose import axis_angle_to_matrix
from ams_torch.testing import sphere_groom
from ams_torch.stages.wind import Wind

MOTIONS = [{"type": "static"}, {"type": "shake"}, {"type": "nod"}, {"type": "spin", "rate": 4.0},
           {"type": "roller_coaster"},
           {"type": "keyframes", "times": [0.0, 0.4, 1.0], "rotvecs": [[0, 0, 0], [0, 0.6, 0], [0.3, 0, 0]],
            "translations": [[0, 0, 0], [0.1, 0, 0], [0, 0.2, 0]]}]


@pytest.mark.parametrize("spec", MOTIONS, ids=lambda s: s["type"])
def test_motion_velocities_are_derivatives(spec):
    m = make_motion(spec)
    eps = 1e-5
    for t in (0.13, 0.37, 0.71, 1.23):
        a, b, c = (m(t + d, dtype=torch.float64) for d in (-eps, eps, 0.0))
        assert torch.allclose((b.translation - a.translation) / (2 * eps), c.linear_velocity, atol=1e-6)
        assert torch.allclose(a.relative_rotvec(b) / (2 * eps), c.angular_velocity, atol=1e-6)


def test_roller_coaster_reaches_several_g_and_stops_upright():
    rc = RollerCoaster(radius=0.5, peak_g=4.0)
    ts = np.linspace(0, rc.duration, 400)
    acc = [np.linalg.norm(rc.state(t + 1e-4)[2] - rc.state(t - 1e-4)[2]) / 2e-4 for t in ts]
    assert 3.5 * 9.81 < max(acc) < 4.5 * 9.81
    end = rc(rc.duration + 1.0, dtype=torch.float64)
    assert torch.allclose(end.rotation, torch.eye(3, dtype=torch.float64), atol=1e-9)
    assert end.linear_velocity.abs().max() == 0 and end.angular_velocity.abs().max() == 0


def test_recorded_motion_from_npz(tmp_path):
    f = tmp_path / "rec.npz"
    rv = np.stack([np.array([0.0, 0.1 * k, 0.0]) for k in range(5)])
    np.savez(f, rotvecs=rv, translations=np.zeros((5, 3)), dt=0.1)
    m = recorded(str(f))
    p = m(0.25, dtype=torch.float64)
    assert torch.allclose(p.angular_velocity, torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))
    with pytest.raises(ValueError, match="translations"):
        np.savez(tmp_path / "bad.npz", rotvecs=rv, dt=0.1)
        recorded(str(tmp_path / "bad.npz"))
    with pytest.raises(FileNotFoundError):
        recorded(str(tmp_path / "missing.npz"))
    assert isinstance(make_motion({"type": "recorded", "path": str(f)}), Keyframes)


def test_bad_motion_names_the_problem():
    with pytest.raises(ValueError, match="motion.type"):
        make_motion({"type": "wobble"})
    with pytest.raises(ValueError, match="frequncy"):
        make_motion({"type": "shake", "frequncy": 2.0})


def test_curl_noise_is_divergence_free():
    w = Wind(turbulence=1.0, noise_scale=0.3, modes=6)
    x = torch.randn(50, 3, dtype=torch.float64, requires_grad=True)
    u = w.velocity(x, 0.7)
    div = sum(torch.autograd.grad(u[:, i].sum(), x, retain_graph=True)[0][:, i] for i in range(3))
    assert div.abs().max() < 1e-10
    assert u.norm(dim=-1).mean() > 0.1


def _run(external, frames=20, backend="auto"):
    rest = sphere_groom(30, 12, radius=0.1, length=0.15)
    sim = at.Simulator(rest, at.Params(), backend=backend)
    st = sim.initial_state()
    force = external.bind(sim) if external is not None else None
    for _ in range(frames):
        st = sim.step(st, None, external_force=force)
    return st.x


def test_zero_wind_equals_no_wind_exactly():
    # on one path: a wind callable keeps a frame on the torch definition (the native kernel takes
    # forces held over the frame), which agrees with the native path to ~1e-14, not bit for bit
    assert torch.equal(_run(None, backend="torch"), _run(Wind(speed=0.0, gust=0.5, turbulence=0.0), backend="torch"))


def test_hair_moves_downwind():
    still = _run(None)
    windy = _run(Wind(direction=(1.0, 0.0, 0.0), speed=8.0, gust=0.3, turbulence=1.0))
    shift = (windy - still)[:, 2:, :].mean(dim=(0, 1))
    assert shift[0] > 5e-3 and shift[0] > 3 * shift[1:].abs().max()


@pytest.mark.parametrize("rotations,match", [
    (np.zeros((4, 4, 4)), r"rotations must have shape \(4, 3, 3\); got \(4, 4, 4\) \(homogeneous"),
    (np.tile(3 * np.eye(3), (4, 1, 1)), r"not a rotation at frame \(0,\).*det = 27"),
    (np.tile(np.array([[1.0, 0.25, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]), (4, 1, 1)), r"not a rotation at frame"),
])
def test_recorded_motion_refuses_matrices_that_are_not_rotations(tmp_path, rotations, match):
    """Before: (F, 4, 4) zeros and 3·I came back as the identity, a shear as a 14° rotation."""
    path = tmp_path / "bad.npz"
    np.savez(path, rotations=rotations, translations=np.zeros((4, 3)), dt=0.1)
    with pytest.raises(ValueError, match=match):
        recorded(str(path))


def test_recorded_float32_rotations_pass_at_their_precision(tmp_path):
    rv = np.random.default_rng(0).normal(size=(6, 3))
    rot = axis_angle_to_matrix(torch.as_tensor(rv)).numpy().astype(np.float32)
    np.savez(tmp_path / "ok.npz", rotations=rot, translations=np.zeros((6, 3)), dt=0.1)
    m = recorded(str(tmp_path / "ok.npz"))
    assert torch.allclose(m(0.2, dtype=torch.float64).rotation, torch.as_tensor(rot[2], dtype=torch.float64), atol=1e-6)
