"""The native adjoint of the collision stage (``csrc/collide/collide_adjoint.h``, op
``ams_torch::collisions_adjoint``, the backward of ``ams_torch::collisions``): its gradients against
the torch definition's autograd.

* per collider kind (sphere, capsule, plane, mesh, several together), moving colliders with
  friction, 0–2 rounds of follow-the-leader and push-out, batched scenes with per-scene poses: the
  native x̄, v̄, pose, velocity, friction and head-rotation adjoints equal the torch definition's to
  ≤ 1e-10 relative in float64;
* a gradient frame of a native simulator runs the native adjoint (the kernel is called), for the
  collision stage and for the substep contact; a hollow sphere keeps the torch definition, still exact;
* ``torch.autograd.gradcheck`` of the op on a small input, and ``torch.library.opcheck``.
"""
from __future__ import annotations

import pytest
import torch
from helpers import built_native, rel
from native_cases import make_case, without_hollow

import ams_torch as at
from ams_torch.sim import native
from ams_torch.sim import native_collide_grad as ncg
from ams_torch.stages.collide import resolve_world_poses

F64 = torch.float64


@pytest.fixture(scope="module", autouse=True)
def cpu_lib():
    return built_native("cpu")


def _arguments(sim, x, v, head, grad=True):
    """The op's arguments with x, v and the colliders' world poses as leaves (requires_grad)."""
    world = resolve_world_poses(sim.colliders, head, None)
    args = list(native.collision_arguments(sim.model, sim.config, x, v, head, world))
    if grad:
        args[0], args[1] = (t.detach().clone().requires_grad_() for t in args[:2])
        args[4] = [t.detach().clone().requires_grad_() if i % 4 == 0 else t for i, t in enumerate(args[4])]
        args[5] = [t.detach().clone().requires_grad_() for t in args[5]]
        args[3] = args[3].detach().clone().requires_grad_()
    return args


def _both(args, seed=0):
    g = torch.Generator().manual_seed(seed)
    gx = torch.randn(args[0].shape, generator=g, dtype=args[0].dtype)
    gv = torch.randn(args[0].shape, generator=g, dtype=args[0].dtype)
    nat = ncg._collisions_adjoint_kernel(*args, gx, gv)
    ref = ncg._collisions_vjp(*args[:8], tuple(args[8:12]), gx, gv)
    return nat, ref


@pytest.mark.parametrize("kind", ["sphere", "capsule", "plane", "mesh", "all_but_hollow"])
@pytest.mark.parametrize("rounds", [0, 1, 2])
def test_native_adjoint_equals_the_torch_definition(kind, rounds):
    scene = "all" if kind == "all_but_hollow" else kind
    sim, x, v, head, _ = make_case(scene, scenes=2, strands=15, rounds=rounds)
    args = without_hollow(_arguments(sim, x, v, head))
    assert len(args[6]) == 3 * (4 if kind == "all_but_hollow" else 1)
    nat, ref = _both(args)
    assert len(nat) == len(ref)
    inside = int((native._collisions_torch(*[a.detach() if isinstance(a, torch.Tensor) else a for a in args])[1]
                  != args[1].detach()).any(-1).sum())
    assert inside > 0, "no particle in contact: the case tests nothing"
    for i, (a, b) in enumerate(zip(nat, ref)):
        a, b = a.detach(), b.detach()
        scale = float(b.abs().max())
        assert float((a - b).abs().max()) <= 1e-10 * max(scale, 1e-12), (kind, rounds, i, float((a - b).abs().max()),
                                                                        scale)
    assert float(ref[0].abs().max()) > 0 and any(float(g.abs().max()) > 0 for g in ref[3:])


def test_head_rotation_adjoint_through_collapsed_edges():
    """Follow-the-leader's fallback direction (an edge collapsed to zero length) carries the head
    rotation: its adjoint equals the torch definition's."""
    sim, x, v, head, _ = make_case("capsule", scenes=None, strands=15, rounds=2)
    pinned = int(sim.model.num_pinned.min())
    assert pinned >= 1
    x = x.clone()
    x[:, pinned] = x[:, pinned - 1]  # the first free edge collapsed onto the last pinned particle
    args = _arguments(sim, x, v, head)
    nat, ref = _both(args, seed=1)
    assert float(ref[2].abs().max()) > 0
    assert rel(nat[2], ref[2]) <= 1e-10
    for a, b in zip(nat, ref):
        a, b = a.detach(), b.detach()
        assert float((a - b).abs().max()) <= 1e-10 * max(float(b.abs().max()), 1e-12)


def test_hollow_sphere_keeps_the_torch_definition(monkeypatch):
    sim, x, v, head, _ = make_case("hollow", scenes=None, strands=7)
    args = _arguments(sim, x, v, head)
    called = []
    monkeypatch.setattr(ncg, "native_namespace", lambda *a, **k: called.append(a) or None)
    nat, ref = _both(args)
    assert not called or all(a[0] != "collide_adjoint" for a in called)
    for a, b in zip(nat, ref):
        assert torch.equal(a, b)
    assert not ncg.native_collisions_diff_supported(sim.model, x, sim.config)


def _spy(monkeypatch):
    calls = []
    real = ncg._collisions_adjoint_kernel

    def spy(*a):
        calls.append(a[8])  # dt: the frame's, or the substep's
        return real(*a)
    monkeypatch.setattr(ncg, "_collisions_adjoint_kernel", spy)
    ncg.collisions_adjoint_op.register_kernel("cpu")(spy)
    return calls, real


@pytest.mark.parametrize("contact", ["frame", "substep"])
def test_gradient_frames_run_the_native_adjoint(monkeypatch, contact):
    """A rollout's gradient through a mesh head collider (and a moving sphere) runs the native
    adjoints in every frame (the dynamics, the collision stage, and with substep contact the
    dynamics substep by substep and the contact after each), and equals the torch path's."""
    head = at.default_head(2)
    grid = at.geometry.sdf.SDFGrid.from_mesh(head, resolution=24, cache=False)
    rest = at.grooms.head.hanging_groom(head, 12, 8, 0.08, sdf=grid, seed=2)
    grads = {}
    calls, real = _spy(monkeypatch)
    from ams_torch.sim import native_grad
    frame_ops = []
    op = native_grad.frame_dynamics_diff_op
    monkeypatch.setattr(native_grad, "frame_dynamics_diff_op", lambda *a: frame_ops.append(a[-1]) or op(*a))
    try:
        for backend in ("native", "torch"):
            cols = [at.MeshCollider(grid), at.stages.SphereCollider((0.0, -0.05, 0.06), 0.04, friction=0.4)]
            sim = at.Simulator(rest, at.Params(contact=contact, substeps=2), dtype=F64, backend=backend,
                               colliders=cols, learnable=("drag",))
            poses = at.apps.motion.Shake(amplitude=0.9, frequency=2.0).poses(3, 1 / 60, dtype=F64)
            s = sim.initial_state()
            x0 = s.x.clone().requires_grad_()
            s = s.replace(x=x0)
            for p in poses:
                s = sim.step(s, p)
            w = torch.linspace(-1, 1, s.x.numel(), dtype=F64).reshape(s.x.shape)
            loss = (w * s.x).sum() + 0.1 * (w * s.v).sum()
            grads[backend] = torch.autograd.grad(loss, [x0] + list(sim.parameters()))
            if backend == "native":
                native_calls = list(calls)
    finally:
        ncg.collisions_adjoint_op.register_kernel("cpu")(real)
    frames = len(poses)
    # a frame: the collision stage; with substep contact also the contact after each of the 2 substeps and
    # follow-the-leader at the frame's end (the collision op without colliders)
    expect = frames * (1 + (3 if contact == "substep" else 0))
    assert len(native_calls) == expect, native_calls
    # the dynamics' native forward and adjoint: once a frame, or once a substep (without follow-the-leader)
    assert len(frame_ops) == frames * (2 if contact == "substep" else 1)
    assert all(inext is (contact != "substep") for inext in frame_ops)
    for a, b in zip(grads["native"], grads["torch"]):
        assert float(b.abs().max()) > 0
        assert rel(a, b) <= 1e-9, rel(a, b)


def test_gradcheck_of_the_op():
    sim, x, v, head, _ = make_case("all", scenes=None, strands=4, particles=6, rounds=1)
    args = without_hollow(_arguments(sim, x, v, head))

    def fn(x, v, r, t):
        a = list(args)
        a[0], a[1] = x, v
        poses = list(a[5])
        poses[0], poses[1] = r, t
        a[5] = poses
        return native.collisions_op(*a)

    assert torch.autograd.gradcheck(fn, (args[0], args[1], args[5][0], args[5][1]), eps=1e-7, atol=1e-6, rtol=1e-5)


def test_opcheck_of_the_op():
    sim, x, v, head, _ = make_case("sphere", scenes=2, strands=3, particles=5)
    args = _arguments(sim, x, v, head)
    torch.library.opcheck(native.collisions_op, tuple(args),
                          test_utils=("test_schema", "test_autograd_registration", "test_faketensor"))
