"""The native adjoint of the fused dynamics frame (``csrc/frame/frame_adjoint.h``, the op
``ams_torch::frame_dynamics_diff``): its gradients against the torch definition's autograd.

* float64 rollouts with every input a leaf (x₀, v₀, ghost_rest, the external force, a shift of the
  head poses, every learnable material field incl. per-strand ones): native gradients equal the
  torch path's to ≤ 1e-8 relative (measured ~1e-13), over the Config variants the adjoint covers;
* batched scenes (per-scene and shared head poses), pinned prefixes of different lengths;
* ``torch.autograd.gradcheck`` of the op itself on a tiny input, and ``torch.library.opcheck``;
* what is not native falls back to the torch definition (the non-Hookean law), still exact.
"""
from __future__ import annotations

import pytest
import torch
from helpers import built_native

import ams_torch as at
from ams_torch.geometry.pose import Pose
from ams_torch.sim import native_grad
from ams_torch.apps.motion import Shake

from ams_torch.testing import sphere_groom

F64 = torch.float64
MATERIAL = ("linear_density", "drag", "stretch_rigidity", "bend_rigidity", "torsion_rigidity", "integrity_rate",
            "angular_rigidity")


@pytest.fixture(scope="module", autouse=True)
def adjoint_cpu():
    return built_native("cpu")


def _gradients(backend: str, params: at.Params, learnable=MATERIAL, frames: int = 2, scenes: int = 0,
               shared_pose: bool = True, strands: int = 5, pinned=None, dtype=F64, every_stage: bool = False,
               h: float = 0.0, velocities: bool = True):
    """Gradients of a scalar of a short rollout with respect to every leaf, for one backend (with
    ``every_stage``: a head collider and the hair–hair grid too). With h > 0 also the central
    difference of the loss along a random direction of the leaves: returns (grads, (autograd, fd))."""
    rest = sphere_groom(strands, 8, length=0.12, seed=1, dtype=dtype)
    stages = dict(colliders=[at.stages.SphereCollider(radius=0.1, follow_head=True)],
                  hair_hair=at.HairHair(resolution=8, pressure_iterations=10)) if every_stage else {}
    sim = at.Simulator(rest, params, dtype=dtype, learnable=learnable, backend=backend, **stages)
    if pinned is not None:  # a different pinned prefix per strand
        sim.model.set_pinned(pinned)
    g = torch.Generator().manual_seed(3)
    batch = (scenes,) if scenes else ()
    shape = batch + rest.shape
    leaf = lambda scale: (scale * torch.randn(shape, generator=g, dtype=dtype)).requires_grad_()  # noqa: E731
    dx, dv, dg, ext = leaf(1e-3), leaf(1e-2), leaf(1e-4), leaf(1e-6)
    shift = torch.zeros(batch + (3,) if (scenes and not shared_pose) else (3,), dtype=dtype, requires_grad=True)
    w = torch.randn(shape, generator=g, dtype=dtype)
    base = Shake(amplitude=0.8, frequency=2.0, translation=(0.02, 0.01, 0.0)).poses(frames, 1 / 60, dtype=dtype)
    init = None
    if scenes:
        angles = torch.linspace(0.0, 0.5, scenes, dtype=dtype)
        rot = at.geometry.pose.axis_angle_to_matrix(torch.stack([angles * 0, angles, angles * 0], -1))
        init = Pose(rot, torch.zeros(scenes, 3, dtype=dtype))
    def loss_fn():
        s = sim.initial_state(init)
        s = s.replace(x=s.x + dx, v=s.v + dv, ghost_rest=s.ghost_rest + dg)
        for p in base:
            r, t, lin, ang = p.rotation, p.translation, p.linear_velocity, p.angular_velocity
            if scenes and not shared_pose:
                r, t = r.expand(scenes, 3, 3), t.expand(scenes, 3)
                lin, ang = lin.expand(scenes, 3), ang.expand(scenes, 3)
            pose = Pose(r, t + shift, lin, ang, check=False) if velocities else Pose(r, t + shift, check=False)
            s = sim.step(s, pose, external_force=ext)
        return (w * s.x).sum() + 0.01 * (w * s.v).sum()

    names = ["x0", "v0", "ghost_rest", "external_force", "head shift"] + [n for n, _ in sim.named_parameters()]
    leaves = [dx, dv, dg, ext, shift] + list(sim.parameters())
    grads = torch.autograd.grad(loss_fn(), leaves, allow_unused=True)
    out = {n: g for n, g in zip(names, grads) if g is not None}  # ghost_rest is unused without couplings
    if not h:
        return out
    d = [torch.randn(t.shape, generator=g, dtype=dtype) * (t.detach().abs() + 1e-3 * float(t.detach().abs().max()))
         for t in leaves]
    ad = sum(float((a * b).sum()) for a, b in zip(grads, d) if a is not None)
    vals = []
    with torch.no_grad():
        for sign in (1.0, -1.0):
            for t, dt in zip(leaves, d):
                t.add_(sign * h * dt)
            vals.append(float(loss_fn()))
            for t, dt in zip(leaves, d):
                t.sub_(sign * h * dt)
    return out, (ad, (vals[0] - vals[1]) / (2 * h))


def _assert_parity(params, tol: float = 1e-8, **kw):
    ref = _gradients("torch", params, **kw)
    nat = _gradients("native", params, **kw)
    for name in set(nat) - set(ref):  # unused by the torch graph: the native gradient is zero
        assert float(nat[name].abs().max()) == 0, name
    for name, a in ref.items():
        b = nat[name]
        assert float(a.abs().max()) > 0, name
        err = float((a - b).norm() / a.norm())
        assert err <= tol, (name, err)


@pytest.mark.parametrize("params", [
    at.Params(),
    at.Params(substeps=3),
    at.Params(geometric_stiffness=True),
    at.Params(implicit_angular=False),
    at.Params(inextensibility=False),
    at.Params(root_length=0.03, ftl_damping=0.5),
], ids=["default", "substeps3", "geometric", "explicit_angular", "no_ftl", "root_length"])
def test_native_gradients_equal_the_torch_path(params):
    _assert_parity(params)


def test_native_gradients_with_poses_without_velocities():
    """Head poses given without velocities: linear translation between substeps, velocities from the
    change of pose (their gradients reach the poses through that difference)."""
    _assert_parity(at.Params(substeps=3), velocities=False, frames=3)


def test_native_gradients_without_integrity_or_angular_springs():
    _assert_parity(at.Params(integrity_rate=0.0, sag_free=False, angular_rigidity=0.0),
                   learnable=("linear_density", "drag", "stretch_rigidity", "bend_rigidity"))


def test_native_gradients_of_per_strand_fields_and_per_particle_material():
    s = 5
    per_strand = at.Params(drag=torch.linspace(1.0, 2.0, s, dtype=F64)[:, None],
                           integrity_rate=torch.linspace(80.0, 120.0, s, dtype=F64)[:, None])
    _assert_parity(per_strand, learnable=("drag", "integrity_rate", "stretch_rigidity"))
    paper = at.Params.paper().replace(integrity_stiffness=1e2, angular_stiffness=1e1, drag=0.5)
    _assert_parity(paper, learnable=("particle_mass", "stretch_stiffness", "bend_scale", "integrity_stiffness",
                                     "angular_stiffness", "drag"))


def test_native_gradients_of_batched_scenes_and_mixed_pinned_prefixes():
    _assert_parity(at.Params(), scenes=3, shared_pose=True)
    _assert_parity(at.Params(substeps=2), scenes=2, shared_pose=False)
    _assert_parity(at.Params(), pinned=[1, 2, 3, 0, 2])


def test_every_stage_native_gradients_equal_the_torch_path_and_central_differences():
    """Head contact and the hair–hair grid on: the dynamics run native (forward and adjoint), the
    other stages the torch definition; the whole rollout's gradients equal the all-torch path's, and
    a directional derivative equals the central difference of the native forward."""
    _assert_parity(at.Params(), every_stage=True, frames=3)
    _, (ad, fd) = _gradients("native", at.Params(), every_stage=True, frames=3, h=1e-6)
    assert abs(ad) > 1e-3 and abs(ad - fd) <= 1e-6 * abs(ad), (ad, fd)


def test_float32_native_gradients_agree_with_the_torch_path():
    ref = _gradients("torch", at.Params(), dtype=torch.float32)
    nat = _gradients("native", at.Params(), dtype=torch.float32)
    for name, a in ref.items():
        err = float((a - nat[name]).norm() / a.norm())
        assert err <= 1e-3, (name, err)


def test_native_gradients_of_the_non_hookean_law():
    """The non-Hookean law (its curve's transition, breaking point and soft ratio learnable, the
    sag-free offset through the learnable integrity rate): 75 % of the particles start frames 2 and 3
    past the transition, 30 % at the breaking point (the plastic yield put them there)."""
    params = at.Params(integrity_model="nonhookean", integrity_rate=1000.0, integrity_transition=0.02,
                       integrity_break=0.05)
    _assert_parity(params, learnable=("drag", "integrity_rate", "integrity_transition", "integrity_break",
                                      "integrity_soft_ratio"), frames=3)
    _assert_parity(params.replace(substeps=2), learnable=("integrity_rate", "integrity_transition"), scenes=2,
                   shared_pose=False)


def test_the_one_particle_angular_form_keeps_the_torch_definition():
    params = at.Params(angular_reaction=False)
    rest = sphere_groom(3, 8, seed=1, dtype=F64)
    sim = at.Simulator(rest, params, dtype=F64, backend="native", learnable=("drag",))
    coeffs = at.sim.coefficients(sim.model)
    assert not native_grad.native_adjoint_supported(sim.model, coeffs, sim.config, rest)
    _assert_parity(params, learnable=("drag", "angular_rigidity"))


def _op_inputs(scenes=0, substeps=2, strands=3, particles=6):
    from ams_torch.sim.native import op_arguments

    rest = sphere_groom(strands, particles, length=0.08, seed=2, dtype=F64)
    sim = at.Simulator(rest, at.Params(substeps=substeps), dtype=F64, backend="native")
    coeffs = at.sim.coefficients(sim.model)
    s = sim.initial_state()
    g = torch.Generator().manual_seed(1)
    x = s.x + 1e-3 * torch.randn(s.x.shape, generator=g, dtype=F64)
    v = 1e-2 * torch.randn(s.x.shape, generator=g, dtype=F64)
    p1 = Shake(amplitude=0.8, translation=(0.02, 0.0, 0.01)).poses(1, 1 / 60, dtype=F64)[0]
    ext = 1e-6 * torch.randn(s.x.shape, generator=g, dtype=F64)
    state, ext, model, _, *settings = op_arguments(sim.model, coeffs, sim.config, x, v, s.ghost_rest, s.sag_offset,
                                                   s.pose, p1, True, ext)
    poses = native_grad.substep_pose_tensor(s.pose, p1, True, substeps, sim.config.dt, x)
    return state, ext, model, poses, settings[:-1]


def test_gradcheck_of_the_op():
    """gradcheck on a tiny input (3 strands of 6 particles, 2 substeps), every differentiable input in
    units of its own size (coefficients as factors, positions in mm, velocities in cm/s, ...)."""
    state, ext, model, poses, settings = _op_inputs()
    scales = [1e-3, 1e-2, 1e-3, 1e-6, 1e-2]  # x, v, ghost_rest (m, m/s, m), external force (N), poses
    base = [state[0], state[1], state[2], ext, poses]
    coef = {1: "mass", 2: "drag", 3: "edge", 6: "integrity", 7: "angular"}
    leaves = [torch.zeros_like(t, requires_grad=True) for t in base] + \
        [torch.ones_like(model[i], requires_grad=True) for i in coef]

    def fn(*u):
        x, v, g, e, p = (b + sc * d for b, sc, d in zip(base, scales, u[:5]))
        mod = list(model)
        for i, f in zip(coef, u[5:]):
            mod[i] = model[i] * f
        return native_grad.frame_dynamics_diff_op([x, v, g, state[3]], e, mod, p, *settings)

    assert torch.autograd.gradcheck(fn, tuple(leaves), eps=1e-6, atol=1e-7, rtol=1e-4)


def test_opcheck_of_the_op():
    state, ext, model, poses, settings = _op_inputs(substeps=1)
    state = [t.detach().clone().requires_grad_(i < 3) for i, t in enumerate(state)]
    model = [t.detach().clone().requires_grad_(i in (1, 2, 3, 4, 5, 6, 7)) for i, t in enumerate(model)]
    torch.library.opcheck(native_grad.frame_dynamics_diff_op,
                          (state, ext.detach().clone().requires_grad_(), model, poses.detach().clone().requires_grad_(),
                           *settings))


def test_native_status_names_the_gradient_stages():
    st = at.native_status()["gradients"]
    assert st["dynamics"].startswith("native")
    assert st["collisions"].startswith("native")
    assert st["hair_hair"].startswith("native forward and adjoint")
    assert st["finish"].startswith("native forward and adjoint")
    assert st["plastic_yield"].startswith("native adjoint")
