"""The rollout API (``ams_torch.sim.rollout``): checkpointed gradients equal plain ones, memory falls
with the segment length, and the controls, observations and reducers it accepts."""
import pytest
import torch

import ams_torch as at
from ams_torch.geometry.pose import Pose
from ams_torch.apps.motion import Shake

from ams_torch.testing import at_material_points, sphere_groom

F64 = torch.float64
FRAMES = 8


def _setup(backend="torch", colliders=True):
    rest = sphere_groom(4, 8, length=0.12, seed=1, dtype=F64)
    cols = [at.stages.SphereCollider(radius=0.1, follow_head=True)] if colliders else None
    sim = at.Simulator(rest, at.Params(), dtype=F64, learnable=("integrity_rate", "drag"), backend=backend,
                       colliders=cols)
    poses = Shake(amplitude=0.8, frequency=2.0, translation=(0.02, 0.0, 0.0)).poses(FRAMES, 1 / 60, dtype=F64)
    return rest, sim, poses


def _leaves(rest):
    g = torch.Generator().manual_seed(0)
    dx = (1e-3 * torch.randn(rest.shape, generator=g, dtype=F64)).requires_grad_()
    shift = torch.zeros(3, dtype=F64, requires_grad=True)
    force = torch.zeros(rest.shape, dtype=F64, requires_grad=True)
    return dx, shift, force


def _run(sim, rest, poses, leaves, k, **kw):
    dx, shift, force = leaves

    def control(i):
        p = poses[i]
        return {"pose": Pose(p.rotation, p.translation + shift, p.linear_velocity, p.angular_velocity, check=False),
                "external_force": force * (i + 1)}

    s0 = sim.initial_state()
    s0 = s0.replace(x=s0.x + dx)
    return at.sim.rollout(sim, s0, control, frames=FRAMES, checkpoint_every=k, **kw)


def _loss(rest):
    w = torch.randn(rest.shape, generator=torch.Generator().manual_seed(3), dtype=F64)
    return lambda acc, i, s: acc + (i + 1) * (w * s.x).sum() + 1e-2 * (s.v * s.v).sum()


@pytest.mark.parametrize("k", [1, 3, FRAMES])
def test_checkpointed_gradients_equal_plain_ones(k):
    rest, sim, poses = _setup()
    leaves = _leaves(rest)
    wrt = [sim.model.integrity_rate, sim.model.drag, *leaves]
    plain = _run(sim, rest, poses, leaves, 0, reduce=_loss(rest), initial=0.0)
    g_plain = torch.autograd.grad(plain.value, wrt)
    ck = _run(sim, rest, poses, leaves, k, reduce=_loss(rest), initial=0.0)
    assert float(ck.value.detach()) == float(plain.value.detach())
    g_ck = torch.autograd.grad(ck.value, wrt)  # autograd.grad, not only .backward()
    for a, b in zip(g_plain, g_ck):
        assert float(a.abs().max()) > 0
        torch.testing.assert_close(b, a, rtol=1e-10, atol=1e-14)
    # .backward() accumulates the same into .grad
    for t in wrt:
        t.grad = None
    _run(sim, rest, poses, leaves, k, reduce=_loss(rest), initial=0.0).value.backward()
    for a, t in zip(g_plain, wrt):
        torch.testing.assert_close(t.grad, a, rtol=1e-10, atol=1e-14)


def test_observations_and_states_carry_gradients_through_segments():
    rest, sim, poses = _setup(colliders=False)
    leaves = _leaves(rest)
    obs = lambda s: at_material_points(rest, s.x, 5)  # noqa: E731
    a = _run(sim, rest, poses, leaves, 0, observe=obs)
    b = _run(sim, rest, poses, leaves, 3, observe=obs)
    assert len(b.outputs) == FRAMES and b.value is None
    la, lb = torch.stack(a.outputs).pow(2).sum(), torch.stack(b.outputs).pow(2).sum()
    ga, gb = torch.autograd.grad(la, leaves[0]), torch.autograd.grad(lb, leaves[0])
    torch.testing.assert_close(gb, ga, rtol=1e-10, atol=1e-14)
    states = _run(sim, rest, poses, leaves, 3)  # no observe, no reduce: the States
    assert len(states.outputs) == FRAMES and isinstance(states.outputs[0], at.State)
    assert states.outputs[-1].x is states.final.x
    gs = torch.autograd.grad(states.outputs[4].v.sum() + states.final.x.sum(), leaves[0])
    ref = _run(sim, rest, poses, leaves, 0)
    gr = torch.autograd.grad(ref.outputs[4].v.sum() + ref.final.x.sum(), leaves[0])
    torch.testing.assert_close(gs, gr, rtol=1e-10, atol=1e-14)


def _saved_bytes(fn):
    """Bytes of the distinct storages autograd saves for the backward while fn() runs."""
    seen = {}

    def pack(t):
        s = t.untyped_storage()
        seen[(s.data_ptr(), s.nbytes())] = s.nbytes()
        return t

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        out = fn()
    return sum(seen.values()), out


def _peak_saved_bytes(fn):
    """The most bytes of distinct storages that autograd holds saved at once while fn() runs."""
    live, count = {}, {"now": 0, "peak": 0}

    class Held:
        def __init__(self, t):
            self.t, s = t, t.untyped_storage()
            self.key = (s.data_ptr(), s.nbytes())
            if live.get(self.key, 0) == 0:
                count["now"] += self.key[1]
                count["peak"] = max(count["peak"], count["now"])
            live[self.key] = live.get(self.key, 0) + 1

        def __del__(self):
            live[self.key] -= 1
            if live[self.key] == 0:
                count["now"] -= self.key[1]

    with torch.autograd.graph.saved_tensors_hooks(Held, lambda h: h.t):
        out = fn()
    return count["peak"], out


def test_memory_falls_with_the_segment_length():
    """Saved tensors of a 16-frame rollout: every frame's intermediates without checkpointing (836
    KiB); with segments of k frames, the 16 / k segment inputs only (a State: x, v, ghost_rest,
    sag_offset, pose, time: 3.3 KiB each)."""
    rest, sim, _ = _setup(colliders=False)
    poses = Shake().poses(16, 1 / 60, dtype=F64)
    state_bytes = 4 * rest.numel() * 8
    sizes = {}
    for k in (0, 1, 4, 16):
        nbytes, r = _saved_bytes(lambda: at.sim.rollout(sim, sim.initial_state(), poses, checkpoint_every=k,
                                                        reduce=lambda acc, i, s: acc + s.x.sum(), initial=0.0))
        r.value.backward()
        sizes[k] = nbytes
    assert sizes[0] > 50 * state_bytes * 16 / 4
    for k in (1, 4, 16):
        segments = 16 // k
        assert sizes[k] <= segments * (state_bytes + 512) + 2048, sizes  # + the initial state's own graph
    assert sizes[1] > sizes[4] > sizes[16]


def test_frame_checkpoints_inside_segments():
    """``checkpoint_frames=True``: the gradients are the plain ones, and while a segment is
    differentiated autograd keeps one state per frame plus one frame's graph, not the segment's
    graph (saved bytes during the backward of one 8-frame segment)."""
    rest, sim, poses = _setup()
    leaves = _leaves(rest)
    wrt = [sim.model.integrity_rate, sim.model.drag, *leaves]
    plain = _run(sim, rest, poses, leaves, 0, reduce=_loss(rest), initial=0.0)
    g_plain = torch.autograd.grad(plain.value, wrt)
    peaks = {}
    for nested in (False, True):
        ck = _run(sim, rest, poses, leaves, FRAMES, reduce=_loss(rest), initial=0.0, checkpoint_frames=nested)
        nbytes, g = _peak_saved_bytes(lambda: torch.autograd.grad(ck.value, wrt))
        for a, b in zip(g_plain, g):
            assert float(a.abs().max()) > 0
            torch.testing.assert_close(b, a, rtol=1e-10, atol=1e-14)
        peaks[nested] = nbytes
    state_bytes = 4 * rest.numel() * 8
    assert peaks[True] < peaks[False] / 3, peaks
    assert peaks[True] > FRAMES * state_bytes / 2  # each frame's input x, v (at least) held at once


@pytest.mark.parametrize("nested", [False, True])
def test_checkpointed_rollout_leaves_nothing_alive(nested):
    """After a checkpointed rollout and its backward, no tensor of it stays alive (a segment's outputs
    referenced from its own recompute closure were a cycle through the autograd graph that Python's
    collector cannot break: every segment's outputs leaked)."""
    import gc

    rest, sim, poses = _setup()

    def live() -> int:
        gc.collect()
        return sum(1 for o in gc.get_objects() if isinstance(o, torch.Tensor))

    def once():
        out = at.sim.rollout(sim, sim.initial_state(), poses, checkpoint_every=3, checkpoint_frames=nested,
                             reduce=lambda acc, i, s: acc + s.x.sum(), initial=0.0)
        out.value.backward()

    once()  # warm-up (lazily built model tensors)
    before = live()
    once()
    assert live() == before


def test_native_forward_with_checkpointed_recompute_matches_the_torch_rollout():
    """backend="auto": segment forwards run without grad (native kernels), their recomputation
    with grad; in float64 the gradient equals an all-torch rollout's to rounding."""
    rest, sim_native, poses = _setup(backend="auto")
    _, sim_torch, _ = _setup(backend="torch")
    leaves = _leaves(rest)
    grads = []
    for sim in (sim_torch, sim_native):
        r = _run(sim, rest, poses, leaves, 2, reduce=_loss(rest), initial=0.0)
        grads.append(torch.autograd.grad(r.value, [sim.model.integrity_rate, *leaves]))
    for a, b in zip(*grads):
        torch.testing.assert_close(b, a, rtol=1e-8, atol=1e-12)


def test_controls_forms_and_errors():
    rest, sim, poses = _setup(colliders=False)
    s0 = sim.initial_state()
    ref = at.sim.rollout(sim, s0, poses).final
    forms = [[{"pose": p} for p in poses], [(p, None, None) for p in poses], lambda i: poses[i],
             [sim.control(s0, p) for p in poses]]
    for form in forms:
        out = at.sim.rollout(sim, s0, form, frames=FRAMES, checkpoint_every=3)
        assert torch.equal(out.final.x, ref.x)
    assert at.sim.rollout(sim, s0, [None, None]).final.frame == 2
    with pytest.raises(ValueError, match="frames="):
        at.sim.rollout(sim, s0, lambda i: None)
    with pytest.raises(ValueError, match="checkpoint_every"):
        at.sim.rollout(sim, s0, poses, checkpoint_every=-1)
    with pytest.raises(ValueError, match="control dict"):
        at.sim.rollout(sim, s0, [{"head": poses[0]}])
    with pytest.raises(ValueError, match="a frame's control"):
        at.sim.rollout(sim, s0, ["left"])
    with pytest.raises(ValueError, match="controls"):
        at.sim.rollout(sim, s0, poses, frames=FRAMES + 1)


def test_rollout_runs_the_simulators_own_stages():
    """A simulator built with a swapped stage (here the collisions replaced by one that pushes every
    free particle 1 mm along x) rolls out with that stage, as sim.step does, with and without
    checkpointing (gradients included)."""
    from ams_torch.sim.stepping import STAGES, replace_stage

    def shift(frame):
        return frame.replace(x=frame.x + torch.tensor([1e-3, 0.0, 0.0], dtype=frame.x.dtype))

    rest = sphere_groom(4, 8, length=0.12, seed=1, dtype=F64)
    stages = replace_stage(STAGES, "collisions", shift)
    sim = at.Simulator(rest, at.Params(), dtype=F64, learnable=("drag",), backend="torch", stages=stages,
                       colliders=[at.stages.SphereCollider(radius=0.1, follow_head=True)])
    poses = Shake(amplitude=0.8, frequency=2.0).poses(3, 1 / 60, dtype=F64)
    s = sim.initial_state()
    for p in poses:
        s = sim.step(s, p)
    for k in (0, 1):
        out = at.sim.rollout(sim, sim.initial_state(), poses, checkpoint_every=k)
        assert torch.equal(out.final.x, s.x)
    g = torch.autograd.grad(at.sim.rollout(sim, sim.initial_state(), poses, checkpoint_every=1).final.x.sum(),
                            sim.model.drag)[0]
    assert torch.isfinite(g).all()
