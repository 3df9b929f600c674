"""Contact at the substep rate (``Params(contact="substep")``): the torch definition (``frame_dynamics``
with :func:`ams_torch.sim.contact.substep_contact` after every substep) against the fused native
frame (op ``ams_torch::frame_contact``, ``frame.h`` + ``collide.h``), collider by collider and frame
by frame, and what the option does to a contact.

Tolerance: float64 1e-10 relative, as the collision stage's parity (measured ~1e-15): the kernel runs
the collision stage's per-particle response (its parity is tests/test_native_collide.py) inside the
frame kernel's substeps (tests/test_native_frame.py).
"""
from __future__ import annotations

from functools import partial

import pytest
import torch
from helpers import rel
from native_cases import KINDS, make_colliders

from ams_torch.apps.motion import Shake
import ams_torch
from ams_torch import testing
from ams_torch.geometry.pose import Pose
from ams_torch.sim.contact import substep_contact
from ams_torch.sim.dynamics import frame_dynamics
from ams_torch.sim.model import coefficients
from ams_torch.sim.native import op_arguments
from ams_torch.sim.native_contact import (_contact_arguments, _contact_torch, frame_contact_op, native_frame_contact,
                                          native_frame_contact_supported, substep_world_poses)
from ams_torch.sim.stepping import resolve_pose
from ams_torch.stages.collide import collider_distances, resolve_world_poses

F64 = torch.float64


def make_frame(kind: str, scenes=None, substeps=3, strands=15, particles=10, seed=0, dtype=F64):
    """A simulator with substep contact and colliders across a sphere groom, a state pushed into
    them (with velocities), and the frame's two head poses. Returns (sim, x, v, pose0, pose1)."""
    rest = testing.sphere_groom(strands, particles, dtype=F64, seed=seed)
    sim = ams_torch.Simulator(rest, ams_torch.Params(substeps=substeps, contact="substep"), dtype=dtype,
                              colliders=make_colliders(kind, rest))
    dt = sim.config.dt

    def motion(b):
        return Shake(amplitude=0.4 + 0.3 * b, translation=(0.03, 0.02 * b, 0.0)).poses(3, dt, dtype=dtype)[:2]

    if scenes is None:
        pose0, pose1 = motion(0)
    else:
        pairs = [motion(b) for b in range(scenes)]
        pose0, pose1 = Pose.stack([p[0] for p in pairs]), Pose.stack([p[1] for p in pairs])
    state = sim.initial_state(pose0)
    g = torch.Generator().manual_seed(seed + 1)
    noise = lambda scale: (scale * torch.randn(state.x.shape, generator=g, dtype=F64)).to(dtype)  # noqa: E731
    return sim, state.x + noise(8e-3), state.v + noise(0.4), state, pose0, pose1


def both(ns, sim, x, v, state, pose0, pose1, collider_poses=()):
    """(torch definition, native kernel) of one frame with substep contact."""
    coeffs = coefficients(sim.model)
    contact = partial(substep_contact, sim.model, sim.config, collider_poses=collider_poses)
    ref = frame_dynamics(sim.model, coeffs, sim.config, x, v, state.ghost_rest, state.sag_offset, pose0, pose1, True,
                         state.time, None, contact=contact)
    args = op_arguments(sim.model, coeffs, sim.config, x, v, state.ghost_rest, state.sag_offset, pose0, pose1, True)
    world = substep_world_poses(sim.model, pose0, pose1, True, sim.config, collider_poses)
    nat = ns.frame_contact(*args, *_contact_arguments(sim.model, sim.config, x, world))
    return ref, nat


@pytest.mark.parametrize("kind", KINDS)
def test_each_collider_float64(cpu_ops, kind):
    """Collider by collider (and all five together): one frame of M = 3 substeps, each followed by
    the contact response; the particles start inside the colliders."""
    sim, x, v, state, pose0, pose1 = make_frame(kind)
    (xr, vr), (xn, vn) = both(cpu_ops, sim, x, v, state, pose0, pose1)
    assert rel(xn, xr) <= 1e-10 and rel(vn, vr) <= 1e-10, (rel(xn, xr), rel(vn, vr))
    coeffs = coefficients(sim.model)
    plain = frame_dynamics(sim.model, coeffs, sim.config, x, v, state.ghost_rest, state.sag_offset, pose0, pose1,
                           True, state.time)
    assert rel(xr, plain[0]) > 1e-6, "the substep contact changed nothing"


def test_scenes_with_their_own_poses(cpu_ops):
    """B = 3 scenes with their own head motions, a world capsule with one pose per scene and a
    moving plane (with velocities)."""
    sim, x, v, state, pose0, pose1 = make_frame("all", scenes=3)
    rot = Pose.stack([Pose.from_rotvec((0.0, 0.1 * k, 0.05), (0.01 * k, 0.0, 0.0), (0.1 * k, 0.0, 0.0),
                                       (0.0, 0.5, 0.2 * k), dtype=F64) for k in range(3)])
    plane = Pose.from_rotvec((0.05, 0.0, 0.0), (0.0, 0.01, 0.0), (0.0, 0.3, 0.0), (0.2, 0.0, 0.0), dtype=F64)
    poses = (None, rot, plane, None, None)
    (xr, vr), (xn, vn) = both(cpu_ops, sim, x, v, state, pose0, pose1, poses)
    for k in range(3):
        assert rel(xn[k], xr[k]) <= 1e-10 and rel(vn[k], vr[k]) <= 1e-10


def test_frame_by_frame_through_the_simulator(cpu_ops):
    """30 frames of a shaken head with every collider, through ``Simulator.step``: the native
    backend and the torch backend stay within 1e-9 relative, frame by frame."""
    rest = testing.sphere_groom(12, 10, dtype=F64, seed=3)
    sims = {b: ams_torch.Simulator(rest, ams_torch.Params(substeps=2, contact="substep"), dtype=F64,
                                   colliders=make_colliders("all", rest), backend=b) for b in ("torch", "native")}
    states = {b: s.initial_state() for b, s in sims.items()}
    inside = 0
    for k, pose in enumerate(Shake(amplitude=0.8, translation=(0.04, 0.03, 0.0)).poses(30, 1 / 60, dtype=F64)):
        states = {b: sims[b].step(states[b], pose) for b in sims}
        assert rel(states["native"].x, states["torch"].x) <= 1e-9, k
        assert rel(states["native"].v, states["torch"].v) <= 1e-8, k
        world = resolve_world_poses(sims["torch"].colliders, states["torch"].pose, None)
        inside += int((collider_distances(states["torch"].x, sims["torch"].colliders, world) < 1e-4).sum())
    assert inside > 50, "the strands never touched the colliders"


def test_entry_point_support_and_the_op_default():
    """native_frame_contact: the native op when supported; a gradient to keep, or a collider class
    of the user's, takes the torch definition (differentiable); the op's default is the torch
    definition."""
    sim, x, v, state, pose0, pose1 = make_frame("all")
    coeffs = coefficients(sim.model)
    args = (sim.model, coeffs, sim.config, x, v, state.ghost_rest, state.sag_offset, pose0, pose1, True, state.time)
    assert native_frame_contact_supported(sim.model, coeffs, x, v, state.ghost_rest, state.sag_offset, pose0, pose1)
    xn, vn = native_frame_contact(*args)
    contact = partial(substep_contact, sim.model, sim.config, collider_poses=())
    xr, vr = frame_dynamics(*args, contact=contact)
    assert rel(xn, xr) <= 1e-10 and rel(vn, vr) <= 1e-10
    vg = v.clone().requires_grad_()
    grad_args = args[:4] + (vg,) + args[5:]
    assert not native_frame_contact_supported(sim.model, coeffs, x, vg, state.ghost_rest, state.sag_offset, pose0,
                                              pose1)
    xg, _ = native_frame_contact(*grad_args)
    xg.sum().backward()
    assert vg.grad is not None and torch.isfinite(vg.grad).all()
    op_args = op_arguments(sim.model, coeffs, sim.config, x, v, state.ghost_rest, state.sag_offset, pose0, pose1, True)
    world = substep_world_poses(sim.model, pose0, pose1, True, sim.config, ())
    default = _contact_torch(*op_args, *_contact_arguments(sim.model, sim.config, x, world))  # the op's default
    assert rel(default[0], xr) <= 1e-12 and rel(default[1], vr) <= 1e-12
    assert torch.equal(frame_contact_op(*op_args, *_contact_arguments(sim.model, sim.config, x, world))[0], xn)


def test_substep_contact_keeps_a_falling_strand_out_of_a_ball():
    """A strand hanging over a ball, the head dropped onto it: with the contact after every substep
    the free particles are never found inside the ball after any substep's response (σ ≥ −1e-12),
    and the frame ends outside it in both modes."""
    rest = testing.wisp(3, 16, length=0.2, dtype=F64)
    ball = ams_torch.stages.SphereCollider((0.1, -0.12, 0.0), 0.08, friction=0.5)
    deepest = {}
    for mode in ("frame", "substep"):
        sim = ams_torch.Simulator(rest, ams_torch.Params(substeps=4, contact=mode), dtype=F64, colliders=[ball],
                                  backend="torch")
        s = sim.initial_state()
        low = 0.0
        seen = []

        def probe(x, v, pose, h, _sim=sim):
            x, v = substep_contact(_sim.model, _sim.config, x, v, pose, h)
            seen.append(float(collider_distances(x, _sim.colliders, resolve_world_poses(_sim.colliders, pose))
                              [:, ~_sim.model.pinned].min()))
            return x, v

        for k in range(30):
            pose = Pose.from_rotvec((0.0, 0.0, 0.0), (0.0, -0.004 * (k + 1), 0.0), dtype=F64)
            if mode == "substep":
                coeffs = coefficients(sim.model)
                frame_dynamics(sim.model, coeffs, sim.config, s.x, s.v, s.ghost_rest, s.sag_offset, s.pose,
                               resolve_pose(s.pose, pose, sim.config.dt)[0], False, s.time,
                               contact=probe)
            s = sim.step(s, pose)
            world = resolve_world_poses(sim.colliders, s.pose)
            low = min(low, float(collider_distances(s.x, sim.colliders, world)[:, ~sim.model.pinned].min()))
        deepest[mode] = low
        if mode == "substep":
            assert min(seen) >= -1e-12 and len(seen) == 30 * 4
            assert min(seen) <= 1e-6, "the strand never reached the ball"
    assert deepest["frame"] >= -1e-9 and deepest["substep"] >= -1e-9
