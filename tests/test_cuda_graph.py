"""The simulator's CUDA-graph mode (``ams_torch.sim.cuda_graph.GraphedStep``): its capture logic on the
CPU with the eager stand-in (static input buffers, one capture per input layout, replays, what stays
eager, the divergence guard), and a real capture on a GPU when there is one."""
from __future__ import annotations

import pytest
import torch

from ams_torch.apps.motion import Shake
import ams_torch
from ams_torch import testing
from ams_torch.geometry.pose import Pose
from ams_torch.sim.cuda_graph import GraphedStep, eager_capture
from ams_torch.sim.stepping import SimulationDiverged
from ams_torch.stages.collide import SphereCollider
from ams_torch.stages.hair_hair import HairHair

F64 = torch.float64


def make_sim(device="cpu", dtype=F64, **kw):
    rest = testing.sphere_groom(10, 8, dtype=F64)
    return ams_torch.Simulator(rest, ams_torch.Params(substeps=2), device=device, dtype=dtype,
                               colliders=[SphereCollider((0.0, 0.0, 0.0), 0.106)], hair_hair=HairHair(resolution=8),
                               **kw)


def poses(sim, frames=8, scenes=None):
    one = lambda b: Shake(amplitude=0.5 + 0.2 * b).poses(frames, sim.config.dt, dtype=sim.dtype, device=sim.device)
    if scenes is None:
        return one(0)
    ms = [one(b) for b in range(scenes)]
    return [Pose.stack([m[k] for m in ms]) for k in range(frames)]


def run(step, sim, frames, start=None, **kw):
    state = start or sim.initial_state()
    out = []
    for p in frames:
        state = step(state, p, **kw)
        out.append(state)
    return out


def test_replays_equal_the_eager_step_bit_for_bit():
    """Colliders and hair–hair, poses with velocities: one capture, then replays, every frame equal to
    sim.step's."""
    sim = make_sim()
    frames = poses(sim)
    graphed = GraphedStep(sim, capture=eager_capture)
    got = run(graphed, sim, frames)
    want = run(sim.step, sim, frames)
    assert graphed.captures == 1 and graphed.replays == len(frames) - 1 and graphed.eager_calls == 0
    for g, w in zip(got, want):
        assert torch.equal(g.x, w.x) and torch.equal(g.v, w.v) and torch.equal(g.frame, w.frame)


def test_one_capture_per_input_layout():
    sim = make_sim()
    graphed = GraphedStep(sim, capture=eager_capture, max_graphs=3)
    state = sim.initial_state()
    p = poses(sim, 3)
    state = graphed(state, p[1])  # pose with velocities
    state = graphed(state, Pose(p[2].rotation, p[2].translation))  # without: a new layout
    state = graphed(state, None)  # the head still: a third
    state = graphed(state, p[1])  # back to the first: replayed
    assert graphed.captures == 3 and graphed.replays == 1
    batched = sim.initial_state(poses(sim, 2, scenes=2)[0])  # 2 scenes: a fourth, the oldest dropped
    graphed(batched, poses(sim, 2, scenes=2)[1])
    assert graphed.captures == 4 and len(graphed._graphs) == 3


def test_what_stays_eager():
    sim = make_sim()
    graphed = GraphedStep(sim, capture=eager_capture)
    state = sim.initial_state()
    force = lambda x, v, t: torch.zeros_like(x)  # noqa: E731  (Python inside the step)
    out = graphed(state, None, external_force=force)
    assert graphed.eager_calls == 1 and graphed.captures == 0
    assert torch.equal(out.x, sim.step(state, None, external_force=force).x)
    tensor_force = torch.full_like(state.x, 1e-6)  # a tensor force is an input like the others
    graphed(state, None, external_force=tensor_force)
    assert graphed.captures == 1
    learn = make_sim(learnable=("drag",))
    g2 = GraphedStep(learn, capture=eager_capture)
    g2(learn.initial_state(), None)  # a parameter requires grad: eager (autograd)
    assert g2.eager_calls == 1
    with torch.no_grad():
        g2(learn.initial_state(), None)
    assert g2.captures == 1
    assert GraphedStep(sim)._capture is None  # a CPU simulator has no CUDA graphs: eager
    cpu = GraphedStep(sim)
    cpu(state, None)
    assert cpu.eager_calls == 1


def test_static_outputs_without_clone():
    sim = make_sim()
    p = poses(sim, 4)
    fresh = run(GraphedStep(sim, capture=eager_capture), sim, p)
    assert len({s.x.data_ptr() for s in fresh}) == len(fresh)
    static = run(GraphedStep(sim, capture=eager_capture, clone=False), sim, p)
    assert len({s.x.data_ptr() for s in static}) == 1
    assert torch.equal(static[-1].x, fresh[-1].x)


def test_divergence_guard_runs_every_check_every_frames():
    sim = make_sim()
    graphed = GraphedStep(sim, capture=eager_capture)
    state = sim.initial_state()
    bad = state.replace(v=state.v.clone().index_fill_(-2, torch.tensor([4]), float("nan")))
    with pytest.raises(SimulationDiverged, match="frame 1"):
        graphed(bad, None)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_cuda_graph_replay_matches_eager(dtype):
    """A real capture on the GPU (float64 and float32): replays equal the eager steps."""
    sim = make_sim("cuda", dtype)
    frames = poses(sim, 6)
    graphed = GraphedStep(sim)
    got = run(graphed, sim, frames)
    want = run(sim.step, sim, frames)
    assert graphed.captures == 1 and graphed.replays == len(frames)
    tol = 1e-12 if dtype == F64 else 1e-5
    for g, w in zip(got, want):
        assert (g.x - w.x).abs().max().item() <= tol and (g.v - w.v).abs().max().item() <= 1e3 * tol
