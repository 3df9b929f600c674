"""The frame's end (``ams_torch/sim/finish.py``, ``csrc/frame/finish.h``): the fused native op
against its torch definition ``pin_and_speed`` (float64 to rounding, float32 within a few ulps),
NaN/Inf propagation into the divergence flag, op registration (opcheck, fake), and whole frames
of the simulator through both paths."""
import math

import pytest
import torch

import ams_torch as at
from ams_torch.geometry.pose import Pose
from ams_torch.sim import finish
from ams_torch.sim.op_support import pose_tensors
from ams_torch.sim.state import Control
from ams_torch.sim.stepping import SimulationDiverged, check_state, step
from ams_torch.stages.collide import SphereCollider
from helpers import DEVICES, rel
from native_cases import F32, F64, frame_args, make_scene, native_ns

EPS64 = torch.finfo(F64).eps


def _case(device="cpu", dtype=F64, batch=(), pose_batch=None, strands=6, particles=7, seed=0):
    g = torch.Generator().manual_seed(seed)

    def rnd(*shape, scale=1.0):
        return (scale * torch.randn(shape, generator=g, dtype=F64)).to(device=device, dtype=dtype)

    x = rnd(*batch, strands, particles, 3, scale=0.1)
    v = rnd(*batch, strands, particles, 3)
    pb = batch if pose_batch is None else pose_batch
    angle = rnd(*pb, 3)
    rot = torch.linalg.matrix_exp(torch.linalg.cross(
        angle[..., None, :].expand(*pb, 3, 3), torch.eye(3, dtype=dtype, device=device).expand(*pb, 3, 3), dim=-1))
    pose = Pose(rot, rnd(*pb, 3, scale=0.1), rnd(*pb, 3), rnd(*pb, 3, scale=5.0), check=False)
    counts = torch.tensor([(s * 3) % (particles + 1) for s in range(strands)], device=device)
    pinned = torch.arange(particles, device=device)[None, :] < counts[:, None]
    model = type("M", (), {"pinned": pinned, "num_pinned": counts})()
    return model, x, v, pose


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("batch,pose_batch", [((), None), ((3,), None), ((3,), ()), ((2, 2), None)])
def test_native_equals_definition_float64(cpu_ops, device, batch, pose_batch):
    native_ns(device)  # the kernels of this device are built (else the op would take the definition)
    model, x, v, pose = _case(device, F64, batch, pose_batch)
    want_v, want_s = finish.pin_and_speed(x, v, model.pinned, pose)
    got_v, got_s = finish.native_finish(model, x, v, pose)
    assert got_v.shape == x.shape and got_s.shape == x.shape[:-1]
    # free particles keep v exactly; pinned ones take the head's rigid velocity, to rounding (the
    # kernel may fuse the cross product's multiply-adds)
    pinned = model.pinned
    assert torch.equal(got_v[..., ~pinned, :], v[..., ~pinned, :])
    head = pose.velocity_at(x)
    scale = 1.0 + pose.angular_velocity.abs().amax() * (x.abs().amax() + pose.translation.abs().amax())
    assert (got_v[..., pinned, :] - head[..., pinned, :]).abs().max() <= 8 * EPS64 * scale
    assert ((got_s - want_s).abs() / want_s.abs().clamp_min(1e-300))[..., ~pinned].max() <= 1e-14
    assert (got_s[..., pinned] == 0).all() and (got_s[..., ~pinned] > 0).all()


@pytest.mark.parametrize("device", DEVICES)
def test_native_equals_definition_float32(cpu_ops, device):
    """float32: the head's rigid velocity is a few products and sums of O(1) terms, so each
    component is within a few ulps of the norm of the terms (bound 8 eps · scale)."""
    native_ns(device)
    model, x, v, pose = _case(device, F32, (2,))
    want_v, want_s = finish.pin_and_speed(x, v, model.pinned, pose)
    got_v, got_s = finish.native_finish(model, x, v, pose)
    scale = 1.0 + v.abs().amax() + pose.angular_velocity.abs().amax() * (x.abs().amax() + 1.0)
    eps = torch.finfo(F32).eps
    assert (got_v - want_v).abs().max() <= 8 * eps * scale
    assert (got_s - want_s).abs().max() <= 8 * eps * scale


@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_nonfinite_particles_give_nonfinite_speed(cpu_ops, bad):
    model, x, v, pose = _case()
    free = (~model.pinned).nonzero()[0]
    v[free[0], free[1], 1] = bad
    _, speed = finish.native_finish(model, x, v, pose)
    assert not math.isfinite(float(speed[free[0], free[1]]))
    assert not bool(speed.amax() <= 1e9)  # NaN and Inf both fail the divergence comparison
    others = torch.ones_like(speed, dtype=torch.bool)
    others[free[0], free[1]] = False
    assert torch.isfinite(speed[others]).all()


def test_opcheck(cpu_ops):
    for dtype, batch, pose_batch in ((F64, (2,), None), (F32, (), None), (F64, (3,), ())):
        model, x, v, pose = _case("cpu", dtype, batch, pose_batch)
        (_, t, lin, ang), _ = pose_tensors(pose, x)
        torch.library.opcheck(torch.ops.ams_torch.finish.default, (x, v, model.num_pinned, [t, lin, ang]))


def test_op_default_is_the_definition():
    model, x, v, pose = _case(batch=(2,))
    (_, t, lin, ang), _ = pose_tensors(pose, x)
    got = finish._finish_torch(x, v, model.num_pinned, [t, lin, ang])
    want = finish.pin_and_speed(x, v, model.pinned, pose)
    assert torch.equal(got[0], want[0]) and torch.equal(got[1], want[1])


def test_gradients_stay_on_the_definition(cpu_ops):
    model, x, v, pose = _case()
    v = v.requires_grad_()
    out, speed = finish.native_finish(model, x, v, pose)
    (out.sum() + speed.sum()).backward()
    want = torch.where(model.pinned[..., None], 0.0, 1.0 + (out - pose.velocity_at(x)) / speed[..., None])
    assert torch.allclose(v.grad, want.detach(), rtol=1e-12, atol=1e-12)


def _shaken(backend, dtype=F64):
    head = at.default_head(3)
    from ams_torch.grooms.head import hanging_groom
    from ams_torch.apps.motion import Shake

    rest = hanging_groom(head, 24, 8, 0.12, seed=3)
    sim = at.Simulator(rest, at.Params(substeps=2), dtype=dtype, backend=backend)
    return sim, Shake(amplitude=0.6, frequency=1.5).poses(12, 1 / 60, dtype=dtype)


def test_simulator_frames_native_equal_torch(cpu_ops):
    """Whole frames (dynamics + the frame's end) through both paths, float64: the finish adds no
    difference beyond the frame kernel's rounding."""
    out = {}
    for backend in ("native", "torch"):
        sim, poses = _shaken(backend)
        state = sim.initial_state()
        for pose in poses:
            state = sim.step(state, pose)
        out[backend] = state
    a, b = out["native"], out["torch"]
    assert (a.x - b.x).abs().max() <= 1e-12 and (a.v - b.v).abs().max() <= 1e-10
    assert int(a.diverged_frame) == -1 == int(b.diverged_frame)


def test_divergence_flag_through_the_native_finish(cpu_ops):
    """A particle made NaN in the state sets the flag on the next frame on the native path, and the
    guard names the input as bad, as on the torch path."""
    for backend in ("native", "torch"):
        sim, poses = _shaken(backend)
        state = sim.initial_state()
        state = sim.step(state, poses[0])
        x = state.x.clone()
        x[5, 4, 0] = math.nan
        state = step(sim.model, state.replace(x=x), Control(pose=poses[1]), sim.config)
        assert int(state.diverged_frame) == 2, backend
        with pytest.raises(SimulationDiverged) as err:
            check_state(state, sim.config)
        assert err.value.bad_input, backend



@pytest.mark.parametrize("scenes,dtype", [(None, F64), (2, F64), (2, F32)])
def test_frame_with_its_end_fused(cpu_ops, scenes, dtype):
    """``native_frame_dynamics(..., finish=pose)`` (the frame's end fused into the frame kernel,
    what a dynamics-only step runs) equals the torch frame followed by ``pin_and_speed``; float64
    to rounding, float32 within its conditioning (the frame's own float32 bound)."""
    from ams_torch.sim import native
    from ams_torch.sim.dynamics import frame_dynamics

    sim, state, pose1 = make_scene(dtype=dtype, scenes=scenes, substeps=2, num_pinned=3)
    args = frame_args(sim, state, pose1)
    with torch.no_grad():
        x, v, speed = native.native_frame_dynamics(*args, finish=pose1, pinned=sim.model.pinned)
        xt, vt = frame_dynamics(*args)
        vt, st = finish.pin_and_speed(xt, vt, sim.model.pinned, pose1)
    tol = 1e-12 if dtype == F64 else 2e-4
    assert rel(x, xt) <= tol and rel(v, vt) <= tol and rel(speed, st) <= tol
    assert speed.shape == x.shape[:-1]
    head = pose1.velocity_at(x)
    assert (v[..., sim.model.pinned, :] - head[..., sim.model.pinned, :]).abs().max() <= 1e3 * torch.finfo(dtype).eps


def test_dynamics_only_step_dispatches_one_op_for_dynamics_and_end(cpu_ops):
    """A dynamics-only native frame runs the fused frame op and no separate finish op; a frame
    with collisions keeps the finish op after them."""
    from torch.profiler import ProfilerActivity, profile

    names = {}
    for colliders in (None, [SphereCollider((0.0, 0.0, 0.0), 0.09)]):
        sim, poses = _shaken("native", F32)
        if colliders:
            sim = at.Simulator(sim.model.rest_positions, sim.params, dtype=F32, colliders=colliders, backend="native")
        state = sim.step(sim.initial_state(), poses[0])
        with profile(activities=[ProfilerActivity.CPU]) as prof:
            sim.step(state, poses[1])
        names[colliders is None] = {e.name for e in prof.events()}
    assert "ams_torch_cpu::frame_finish" in names[True] and "ams_torch::finish" not in names[True]
    assert "ams_torch::finish" in names[False]
    assert names[False] & {"ams_torch_cpu::frame", "ams_torch_cpu::frame_contact"}  # contact="substep"
