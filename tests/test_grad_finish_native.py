"""The native adjoints of the frame's end and of the plastic yield (``csrc/frame/finish_adjoint.h``:
ops ``finish_adjoint``, ``yield_adjoint``) against autograd on their torch definitions
(``sim/finish.py::pin_and_speed``, ``sim/forces.py::integrity_yield``), float64 to 1e-12 and float32
by its rounding; per-scene and shared head poses, the speed's adjoint given or not, particles at and
past the breaking point; and a gradient frame of a native simulator runs them. The whole-rollout
parity (native gradients = the torch path's, every stage, the non-Hookean law) is
``tests/test_grad_native.py``.
"""
from __future__ import annotations

import pytest
import torch
from helpers import built_native, rel

import ams_torch as at
from ams_torch.apps.motion import Shake
from ams_torch.geometry.pose import Pose
from ams_torch.sim import finish as finish_mod
from ams_torch.sim.finish import _finish_torch, finish_op
from ams_torch.sim.forces import integrity_yield
from ams_torch.testing import sphere_groom

F64 = torch.float64


@pytest.fixture(scope="module")
def ns():
    return built_native("cpu")


def _finish_case(dtype, scenes, per_scene_pose):
    g = torch.Generator().manual_seed(1)
    x = torch.randn(scenes, 7, 9, 3, generator=g, dtype=dtype)
    v = torch.randn(x.shape, generator=g, dtype=dtype)
    num_pinned = torch.tensor([0, 1, 2, 3, 9, 2, 1])
    p = (scenes,) if per_scene_pose else ()
    pose = [torch.randn(p + (3,), generator=g, dtype=dtype) for _ in range(3)]
    return x, v, num_pinned, pose


@pytest.mark.parametrize("dtype", [F64, torch.float32])
@pytest.mark.parametrize("per_scene_pose", [False, True])
@pytest.mark.parametrize("with_speed", [False, True])
def test_finish_adjoint_equals_autograd(ns, dtype, per_scene_pose, with_speed):
    x, v, num_pinned, pose = _finish_case(dtype, 3, per_scene_pose)
    leaves = [t.clone().requires_grad_() for t in (x, v, *pose)]
    out, speed = _finish_torch(leaves[0], leaves[1], num_pinned, leaves[2:])
    g = torch.Generator().manual_seed(2)
    g_v = torch.randn(out.shape, generator=g, dtype=dtype)
    g_s = torch.randn(speed.shape, generator=g, dtype=dtype) if with_speed else None
    pairs = [(out, g_v)] + ([(speed, g_s)] if with_speed else [])
    ref = torch.autograd.grad([o for o, _ in pairs], leaves, [gg for _, gg in pairs])
    # the registered op's backward (the native kernel)
    leaves2 = [t.clone().requires_grad_() for t in (x, v, *pose)]
    out2, speed2 = finish_op(leaves2[0], leaves2[1], num_pinned, leaves2[2:])
    assert rel(out2.detach(), out.detach()) <= 8 * torch.finfo(dtype).eps  # the native forward: the same to rounding
    pairs2 = [(out2, g_v)] + ([(speed2, g_s)] if with_speed else [])
    got = torch.autograd.grad([o for o, _ in pairs2], leaves2, [gg for _, gg in pairs2])
    tol = 1e-12 if dtype == F64 else 1e-5
    for name, a, b in zip(("x", "v", "t", "lin", "ang"), got, ref):
        assert float(b.abs().max()) > 0, name
        assert rel(a, b) <= tol, (name, rel(a, b))


@pytest.mark.parametrize("dtype", [F64, torch.float32])
def test_yield_adjoint_equals_autograd(ns, dtype):
    """Anchors at, inside and past the breaking point; pinned particles never yield."""
    g = torch.Generator().manual_seed(4)
    x = torch.randn(2, 6, 8, 3, generator=g, dtype=dtype)
    seg = 0.01 + 0.01 * torch.rand(6, 8, generator=g, dtype=dtype)
    breaking = torch.tensor(0.05, dtype=dtype)
    d = torch.randn(x.shape, generator=g, dtype=dtype)
    d = d / d.norm(dim=-1, keepdim=True) * (breaking * seg)[..., None] * (0.5 + 1.5 * torch.rand(x.shape[:-1] + (1,),
                                                                                               generator=g, dtype=dtype))
    anchor = x + d
    free = torch.ones(6, 8, dtype=torch.bool)
    free[:, :2] = False
    leaves = [t.clone().requires_grad_() for t in (x, anchor, breaking)]
    new = integrity_yield(leaves[0], leaves[1], seg, leaves[2], free)
    g_new = torch.randn(new.shape, generator=g, dtype=dtype)
    ref = torch.autograd.grad(new, leaves, g_new)
    leaves2 = [t.clone().requires_grad_() for t in (x, anchor, breaking)]
    new2 = finish_mod.native_yield_diff(leaves2[0], leaves2[1], seg, leaves2[2], free)
    assert torch.equal(new2.detach(), new.detach())
    got = torch.autograd.grad(new2, leaves2, g_new)
    tol = 1e-12 if dtype == F64 else 1e-5
    for name, a, b in zip(("x", "anchor", "breaking"), got, ref):
        assert float(b.abs().max()) > 0, name
        assert rel(a, b) <= tol, (name, rel(a, b))


def test_a_native_gradient_frame_runs_the_finish_and_yield_adjoints(ns, monkeypatch):
    """A non-Hookean rollout with gradients on a native simulator calls finish_adjoint and
    yield_adjoint once per frame (and no torch finish)."""
    calls = []
    real = finish_mod.native_namespace

    class Counting:
        def __init__(self, inner):
            self.inner = inner

        def __getattr__(self, name):
            fn = getattr(self.inner, name)
            return (lambda *a: calls.append(name) or fn(*a)) if name.endswith("_adjoint") else fn

    monkeypatch.setattr(finish_mod, "native_namespace",
                        lambda group, *a, **k: (Counting(real(group, *a, **k)) if group == "finish_adjoint"
                                                else real(group, *a, **k)))
    monkeypatch.setattr(finish_mod, "pin_and_speed", None)  # must not be called in these frames
    rest = sphere_groom(4, 8, length=0.12, seed=1, dtype=F64)
    params = at.Params(integrity_model="nonhookean", integrity_rate=1000.0, integrity_transition=0.02,
                       integrity_break=0.05)
    sim = at.Simulator(rest, params, dtype=F64, learnable=("drag", "integrity_break"), backend="native")
    s = sim.initial_state()
    s = s.replace(x=s.x.detach().requires_grad_())
    poses = Shake(amplitude=0.8, frequency=2.0).poses(3, 1 / 60, dtype=F64)
    for p in poses:
        s = sim.step(s, Pose(p.rotation, p.translation, p.linear_velocity, p.angular_velocity, check=False))
    (s.x.sum() + s.v.sum() + s.ghost_rest.sum()).backward()
    assert calls.count("finish_adjoint") == 3 and calls.count("yield_adjoint") == 3, calls
