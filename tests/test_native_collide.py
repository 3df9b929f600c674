"""Fused native collision stage (SPEC §8, §15): torch definition vs native CPU (vs CUDA).

The torch definition is ``ams_torch.sim.stepping.collisions`` (the contact response of every collider
in order, then follow-the-leader and push-out rounds); the native kernel is
``ams_torch/native/csrc/collide``, built once per session. Tolerance: float64 1e-10 relative
(measured: ~1e-16). The kernel computes σ, the normals and the response with the torch code's
formulas in its operation order, without fused multiply-adds, and the mesh grid's trilinear
sample corner by corner as ``grid_sample`` sums it (bit-identical on CPU); what remains is the
last-ulp rounding of torch's vector norms (its reduction kernel) and, with B > 1 scenes, of the
batched matrix products. Those differences only matter where they flip a contact decision
σ < 0, i.e. for particles at |σ| ≈ 1e-17 m; a flipped particle has just been pushed onto the
surface with no approaching velocity, so the response it gains or loses is itself of rounding
size (the 60-frame test keeps strands in contact on every frame to check this).

The AMS_TORCH_NATIVE=0 fallback of both fused ops is tested in one subprocess, in
tests/test_native_frame.py::test_fallback_without_native.
"""
from __future__ import annotations

from pathlib import Path

import pytest
import torch
from helpers import rel
from native_cases import F32, F64, KINDS, make_case

from ams_torch.apps.motion import Shake
import ams_torch
from ams_torch import testing
from ams_torch.geometry.pose import Pose
from ams_torch.sim import native
from ams_torch.sim.dynamics import frame_dynamics
from ams_torch.sim.model import coefficients
from ams_torch.sim.stepping import collisions
from ams_torch.native import build as _native
from ams_torch.stages.collide import (
    CapsuleCollider,
    PlaneCollider,
    SphereCollider,
    resolve_world_poses,
)

REPO = Path(__file__).resolve().parents[1]
EPS32 = torch.finfo(F32).eps


def run_both(ns, sim, x, v, head, collider_poses=()):
    """(torch definition, native kernel) results of the stage."""
    ref = collisions(sim.model, sim.config, x, v, head, collider_poses)
    world = resolve_world_poses(sim.colliders, head, list(collider_poses) or None)
    args = native.collision_arguments(sim.model, sim.config, x, v, head, world)
    nat = ns.collide(*args)
    return ref, nat, world


def contact_share(sim, x, world) -> float:
    """Share of particles inside some collider."""
    inside = torch.zeros(x.shape[:-1], dtype=torch.bool)
    for col, pose in zip(sim.colliders, world):
        inside |= col.distance(pose.to_local(x)) < 0
    return inside.double().mean().item()


# ---------------------------------------------------------------------------------------
# each collider alone and all together
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", KINDS)
def test_each_collider_float64(cpu_ops, kind):
    sim, x, v, head, poses = make_case(kind)
    (xr, vr), (xn, vn), world = run_both(cpu_ops, sim, x, v, head, poses)
    assert contact_share(sim, x, world) > 0.02, "the case has too few contacts"
    assert rel(xn, xr) <= 1e-10 and rel(vn, vr) <= 1e-10, (rel(xn, xr), rel(vn, vr))
    assert rel(xn, x) > 1e-6  # the stage did something


@pytest.mark.parametrize("rounds,inext", [(0, True), (2, True), (1, False)])
def test_rounds_and_inextensibility(cpu_ops, rounds, inext):
    sim, x, v, head, poses = make_case("all", rounds=rounds, inextensibility=inext)
    (xr, vr), (xn, vn), _ = run_both(cpu_ops, sim, x, v, head, poses)
    assert rel(xn, xr) <= 1e-10 and rel(vn, vr) <= 1e-10


def test_pinned_particles_untouched(cpu_ops):
    sim, x, v, head, poses = make_case("all")
    (_, _), (xn, vn), _ = run_both(cpu_ops, sim, x, v, head, poses)
    pinned = sim.model.pinned
    assert pinned.any()
    assert torch.equal(xn[pinned], x[pinned]) and torch.equal(vn[pinned], v[pinned])


def test_scenes_with_their_own_poses(cpu_ops):
    """B > 1 scenes: per-scene head poses, a follow-head sphere, a world capsule with one pose per
    scene and a moving plane (velocities), a mesh with a shared pose."""
    sim, x, v, head, _ = make_case("all", scenes=3)
    b = 3
    rot = Pose.stack([Pose.from_rotvec((0.0, 0.1 * k, 0.05), (0.01 * k, 0.0, 0.0), (0.1 * k, 0.0, 0.0),
                                       (0.0, 0.5, 0.2 * k), dtype=F64) for k in range(b)])
    plane_pose = Pose.from_rotvec((0.05, 0.0, 0.0), (0.0, 0.01, 0.0), (0.0, 0.3, 0.0), (0.2, 0.0, 0.0), dtype=F64)
    poses = (None, rot, plane_pose, None, None)
    (xr, vr), (xn, vn), world = run_both(cpu_ops, sim, x, v, head, poses)
    assert world[1].rotation.shape == (3, 3, 3) and world[2].has_velocity
    assert rel(xn, xr) <= 1e-10 and rel(vn, vr) <= 1e-10
    for k in range(b):
        assert rel(xn[k], xr[k]) <= 1e-10 and rel(vn[k], vr[k]) <= 1e-10


def test_entry_point_and_unsupported_collider(cpu_ops):
    sim, x, v, head, _ = make_case("all")
    world = resolve_world_poses(sim.colliders, head, None)
    assert native.native_collisions_available("cpu", F64)
    assert native.native_collisions_supported(sim.model, x, v, head, world)
    xn, vn = native.native_collisions(sim.model, sim.config, x, v, head, world)
    direct = cpu_ops.collide(*native.collision_arguments(sim.model, sim.config, x, v, head, world))
    assert torch.equal(xn, direct[0]) and torch.equal(vn, direct[1])

    class Shifted(SphereCollider):  # a subclass may compute its own distance: torch path
        pass

    sim2 = ams_torch.Simulator(sim.model.rest_positions, sim.params, dtype=F64,
                               colliders=[Shifted((0.0, 0.0, 0.0), 0.106)])
    world2 = resolve_world_poses(sim2.colliders, head, None)
    assert not native.native_collisions_supported(sim2.model, x, v, head, world2)
    got = native.native_collisions(sim2.model, sim2.config, x, v, head, world2)
    want = collisions(sim2.model, sim2.config, x, v, head, ())
    assert torch.equal(got[0], want[0]) and torch.equal(got[1], want[1])
    # a gradient to keep: the torch path, differentiable
    vg = v.clone().requires_grad_()
    assert not native.native_collisions_supported(sim.model, x, vg, head, world)
    xg, _ = native.native_collisions(sim.model, sim.config, x, vg, head, world)
    xg.sum().backward()
    assert vg.grad is not None


def test_op_default_is_the_torch_definition():
    sim, x, v, head, _ = make_case("all", scenes=2)
    world = resolve_world_poses(sim.colliders, head, None)
    args = native.collision_arguments(sim.model, sim.config, x, v, head, world)
    got = native._collisions_torch(*args)
    want = collisions(sim.model, sim.config, x, v, head, ())
    assert torch.equal(got[0], want[0]) and torch.equal(got[1], want[1])


def test_float32(cpu_ops):
    """float32: as close to the float64 stage as the torch float32 stage is (twice, plus 8 ulps)."""
    out = {}
    for dtype in (F32, F64):
        sim, x, v, head, poses = make_case("all", dtype=dtype)
        out[dtype] = run_both(cpu_ops, sim, x, v, head, poses)[:2]
    (x64, v64), _ = out[F64]
    (xt, vt), (xn, vn) = out[F32]
    assert xn.dtype == F32
    for nat, tor, ref in ((xn, xt, x64), (vn, vt, v64)):
        assert rel(nat, ref) <= 2 * rel(tor, ref) + 8 * EPS32, (rel(nat, ref), rel(tor, ref))


def test_sixty_frames_in_contact(cpu_ops):
    """60 frames of a shaken groom resting on a head sphere and cut by a plane and a capsule,
    float64: torch frame + torch collisions against native frame + native collisions, each fed its
    own output. Strands are in contact on every frame; report the max difference."""
    rest = testing.sphere_groom(20, 12, dtype=F64)
    cols = [SphereCollider((0.0, 0.0, 0.0), 0.104, friction=0.5, follow_head=True),
            PlaneCollider((0.0, -0.15, 0.0), (0.1, 1.0, 0.0), friction=0.8),
            CapsuleCollider((-0.2, -0.08, 0.06), (0.2, -0.1, 0.06), 0.03, friction=0.3)]
    sim = ams_torch.Simulator(rest, ams_torch.Params(), dtype=F64, colliders=cols)
    poses = Shake(amplitude=0.7, frequency=1.5, translation=(0.04, 0.03, 0)).poses(61, sim.config.dt, dtype=F64)
    state = sim.initial_state(poses[0])
    coeffs = coefficients(sim.model)
    frame_ns = _native.native_ops("cpu")
    paths = {"torch": (state.x, state.v), "native": (state.x, state.v)}
    worst, contacts = 0.0, []
    for f in range(60):
        p0, p1 = poses[f], poses[f + 1]
        world = resolve_world_poses(sim.colliders, p1, None)
        for name in paths:
            x, v = paths[name]
            a = (sim.model, coeffs, sim.config, x, v, state.ghost_rest, state.sag_offset, p0, p1, True, state.time)
            if name == "torch":
                x, v = frame_dynamics(*a)
                contacts.append(contact_share(sim, x, world))
                x, v = collisions(sim.model, sim.config, x, v, p1, ())
            else:
                x, v = frame_ns.frame(*native.op_arguments(*a[:10], None), -1)
                x, v = cpu_ops.collide(*native.collision_arguments(sim.model, sim.config, x, v, p1, world))
            paths[name] = (x, v)
        worst = max(worst, (paths["native"][0] - paths["torch"][0]).abs().max().item())
    print(f"60 frames in contact: max |x_native - x_torch| = {worst:.3g} m; contact share "
          f"{min(contacts):.3f}..{max(contacts):.3f}")
    assert min(contacts) > 0.01
    assert worst <= 1e-10


def test_opcheck_and_compile(cpu_ops):
    for dtype in (F64, F32):
        sim, x, v, head, _ = make_case("all", dtype=dtype, scenes=2, strands=5, particles=6)
        world = resolve_world_poses(sim.colliders, head, None)
        torch.library.opcheck(torch.ops.ams_torch.collisions.default,
                              native.collision_arguments(sim.model, sim.config, x, v, head, world))
    sim, x, v, head, _ = make_case("all", dtype=F32, strands=6, particles=6)
    world = resolve_world_poses(sim.colliders, head, None)

    def stage(x, v):
        xo, vo = native.native_collisions(sim.model, sim.config, x, v, head, world)
        return xo * 1.0, vo + 0.0

    torch._dynamo.reset()
    compiled = torch.compile(stage, fullgraph=True, dynamic=False)
    with torch.no_grad():
        got, want = compiled(x, v), stage(x, v)
    assert torch.equal(got[0], want[0]) and torch.equal(got[1], want[1])


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
@pytest.mark.parametrize("dtype", [F64, F32])
def test_cuda_matches_cpu(cpu_ops, dtype):
    ns = _native.native_ops("cuda")
    if ns is None:
        reason = _native.native_status()["cuda"]["reason"]
        if reason.startswith("no CUDA toolkit"):
            pytest.skip(reason)
        raise AssertionError(reason)
    sim, x, v, head, _ = make_case("all", dtype=dtype, scenes=2, strands=37)
    world = resolve_world_poses(sim.colliders, head, None)
    cpu = cpu_ops.collide(*native.collision_arguments(sim.model, sim.config, x, v, head, world))
    sim_c = sim.to("cuda")
    head_c = head.to(device="cuda")
    world_c = resolve_world_poses(sim_c.colliders, head_c, None)
    gpu = ns.collide(*native.collision_arguments(sim_c.model, sim_c.config, x.cuda(), v.cuda(), head_c, world_c))
    tol = 1e-12 if dtype == F64 else 1e-5
    assert rel(gpu[0].cpu(), cpu[0]) <= tol and rel(gpu[1].cpu(), cpu[1]) <= tol
