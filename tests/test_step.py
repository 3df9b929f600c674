"""The pure step and the module around it (issue 14): compile/capture, one owner per datum,
batched scenes, gradients against finite differences, a pendulum, dtype moves, state_dict."""
import math

import pytest
import torch

import ams_torch as at
from ams_torch.geometry.sdf import SDFGrid
from ams_torch.grooms.head import hanging_groom
from ams_torch.apps.motion import Shake

from ams_torch.testing import curly_strand, sphere_groom

F64 = torch.float64


@pytest.fixture(scope="module")
def small_head(tmp_path_factory):
    head = at.default_head(3)
    grid = SDFGrid.from_mesh(head, resolution=32, cache_dir=tmp_path_factory.mktemp("sdf"))
    return head, grid


def _every_stage_sim(small_head, dtype=torch.float32, device="cpu"):
    head, grid = small_head
    rest = hanging_groom(head, 30, 12, 0.15, sdf=grid, seed=1)
    return at.Simulator(rest, at.Params(integrity_model="nonhookean"), dtype=dtype, device=device,
                        colliders=[at.MeshCollider(grid)], hair_hair=at.HairHair(resolution=16))


def test_step_has_no_graph_breaks_and_compiles_fullgraph(small_head):
    """Head collider, hair–hair and non-Hookean integrity all on: 0 graph breaks, and the
    fullgraph-compiled step equals eager over 3 frames (aot_eager: the whole step as one graph;
    the inductor backend is in the slow test below)."""
    sim = _every_stage_sim(small_head)
    s0 = sim.initial_state()
    poses = Shake(amplitude=1.0).poses(3, sim.params.dt)
    explained = torch._dynamo.explain(sim.step)(s0, poses[0])
    assert explained.graph_break_count == 0, [r.reason for r in explained.break_reasons]
    assert explained.graph_count == 1
    compiled = torch.compile(sim.step, fullgraph=True, backend="aot_eager")
    se = sc = s0
    for pose in poses:
        se, sc = sim.step(se, pose), compiled(sc, pose)
    for name in ("x", "v", "ghost_rest"):
        torch.testing.assert_close(getattr(sc, name), getattr(se, name), rtol=0, atol=0)
    assert int(sc.frame) == 3 and int(sc.diverged_frame) == -1


def test_dynamics_only_step_compiles_fullgraph(small_head):
    """Dynamics only: the native step is the fused frame_finish op (the frame's end inside the
    frame kernel) plus the divergence flag; 0 graph breaks, and compiled equals eager."""
    head, grid = small_head
    sim = at.Simulator(hanging_groom(head, 30, 12, 0.15, sdf=grid, seed=1), at.Params())
    s0 = sim.initial_state()
    poses = Shake(amplitude=1.0).poses(3, sim.params.dt)
    explained = torch._dynamo.explain(sim.step)(s0, poses[0])
    assert explained.graph_break_count == 0 and explained.graph_count == 1
    compiled = torch.compile(sim.step, fullgraph=True, backend="aot_eager")
    se = sc = s0
    for pose in poses:
        se, sc = sim.step(se, pose), compiled(sc, pose)
    for name in ("x", "v"):
        torch.testing.assert_close(getattr(sc, name), getattr(se, name), rtol=0, atol=0)
    assert int(sc.frame) == 3 and int(sc.diverged_frame) == -1


@pytest.mark.slow
def test_step_compiles_with_inductor(small_head):
    sim = _every_stage_sim(small_head)
    s0 = sim.initial_state()
    compiled = torch.compile(sim.step, fullgraph=True)
    se = sc = s0
    for pose in Shake(amplitude=1.0).poses(3, sim.params.dt):
        se, sc = sim.step(se, pose), compiled(sc, pose)
    torch.testing.assert_close(sc.x, se.x, rtol=1e-5, atol=1e-6)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_graph_capture_and_replay_equals_eager(small_head):
    sim = _every_stage_sim(small_head, device="cuda")
    poses = Shake(amplitude=1.0).poses(4, sim.params.dt, device="cuda")
    s0 = sim.initial_state()
    eager = s0
    for pose in poses:
        eager = sim.step(eager, pose)
    # warm-up on a side stream: builds/loads any native op and fills the caching allocator
    static_state, static_pose = s0, poses[0]
    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):
        for _ in range(2):
            sim.step(static_state, static_pose)
    torch.cuda.current_stream().wait_stream(side)
    graph = torch.cuda.CUDAGraph()
    check_every, sim.check_every = sim.check_every, 0
    with torch.cuda.graph(graph):
        out = sim.step(static_state, static_pose)
    sim.check_every = check_every
    state = s0
    for pose in poses:  # copy the inputs into the captured buffers, replay, read the outputs
        torch.utils._pytree.tree_map(lambda dst, src: dst.copy_(src) if isinstance(dst, torch.Tensor) else None,
                                     (static_state, static_pose), (state, pose))
        graph.replay()
        state = torch.utils._pytree.tree_map(lambda t: t.clone() if isinstance(t, torch.Tensor) else t, out)
    torch.testing.assert_close(state.x, eager.x, rtol=1e-5, atol=1e-6)


def test_batched_rotated_heads_equal_one_scene_at_a_time():
    """Scenes of one groom whose heads start in different orientations (1.2 rad among them) with
    the non-Hookean law: each scene's sag-free offset is its own (SPEC §7), so the batch equals
    separate runs (before: 0.37 m apart)."""
    rest = sphere_groom(12, 10, seed=11, dtype=F64)
    p = at.Params(integrity_model="nonhookean")
    sim = at.Simulator(rest, p, dtype=F64)
    starts = [at.Pose.from_rotvec(rv, dtype=F64) for rv in ([0.0, 0.0, 0.0], [1.2, 0.0, 0.0], [0.0, 0.4, -0.9])]
    motions = [Shake(amplitude=0.8, frequency=1.5, axis=ax).poses(40, p.dt, dtype=F64)
               for ax in ((0.0, 1.0, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0))]
    composed = [[at.Pose(q.rotation @ s.rotation, q.translation, q.linear_velocity, q.angular_velocity) for q in m]
                for m, s in zip(motions, starts)]
    batch = sim.initial_state(at.Pose.stack(starts))
    for k in range(40):
        batch = sim.step(batch, at.Pose.stack([c[k] for c in composed]))
    worst = 0.0
    for b in range(3):
        one = sim.initial_state(starts[b])
        for k in range(40):
            one = sim.step(one, composed[b][k])
        worst = max(worst, float((one.x - batch.x[b]).abs().max()), float((one.ghost_rest - batch.ghost_rest[b]).abs().max()))
    assert worst <= 1e-9, f"batched vs one scene at a time: {worst:.3g} m"


@pytest.mark.parametrize("law", ["hookean", "nonhookean"])
def test_groom_at_rest_with_pose_only_in_initial_state_does_not_drift(law, capsys):
    """The head pose given only to initial_state (the simulator built with the identity): the
    groom at rest stays put for 2 s (before: 574 mm in 1 s under the non-Hookean law)."""
    rest = sphere_groom(40, 16, seed=12)
    sim = at.Simulator(rest, at.Params(integrity_model=law))
    pose = at.Pose.from_rotvec([1.2, 0.3, 0.0], [0.05, -0.02, 0.01])
    s0 = sim.initial_state(pose)
    s = s0
    for _ in range(120):
        s = sim.step(s)
    drift = float((s.x - s0.x).norm(dim=-1).max())
    with capsys.disabled():
        print(f"\n[drift] {law}, pose only in initial_state, 2 s: {drift * 1e3:.3g} mm")
    assert drift <= 1e-4


def test_gradcheck_of_a_rollout_against_finite_differences():
    """Float64 gradcheck of a 3-frame rollout with respect to the integrity rate (κ_I = ω_I² m), drag
    and x₀ (the sag-free offset depends on κ_I: gradients pass through initial_state too)."""
    rest = curly_strand(particles=6, dtype=F64).expand(2, 6, 3).clone()
    rest[1, :, 2] += 0.01
    poses = Shake(amplitude=0.5).poses(3, 1 / 60, dtype=F64)

    def rollout(kappa, drag, x0):
        sim = at.Simulator(rest, at.Params(integrity_rate=kappa, drag=drag), dtype=F64)
        s = sim.initial_state()
        s = s.replace(x=s.x + x0)
        for pose in poses:
            s = sim.step(s, pose)
        return s.x

    kappa = torch.tensor(1e2, dtype=F64, requires_grad=True)  # the integrity rate ω_I², s⁻²
    drag = torch.tensor(1.5, dtype=F64, requires_grad=True)
    x0 = (1e-3 * torch.randn(rest.shape, generator=torch.Generator().manual_seed(0), dtype=F64)).requires_grad_()
    assert torch.autograd.gradcheck(rollout, (kappa, drag, x0), eps=1e-7, atol=1e-6, rtol=1e-4)


@pytest.mark.parametrize("geometric,tolerance", [(False, 6e-4), (True, 5e-3)])
def test_small_swing_pendulum_period_of_a_stiff_strand(capsys, geometric, tolerance):
    """A stiff short strand pinned only at its root swings as a rigid compound pendulum. Its rest
    shape is a planar zigzag, so edge and bending springs triangulate it (a straight chain has no
    linear bending stiffness and would swing as a chain). About the pivot, in the plane:
    T = 2π √(I / (M g d)) (1 + θ₀²/16) with I = Σ m r², d the pivot–centre-of-mass distance.
    The geometric stiffness (the default) lengthens the period at M = 2 (measured +0.40 %, against
    −0.04 % for the SPEC form)."""
    n, seg, width, amp = 6, 0.02, 0.005, 0.05
    i = torch.arange(n, dtype=F64)
    pts = torch.stack((width * (i % 2), -seg * i, torch.zeros_like(i)), -1)
    hang = math.atan2(float(pts[:, 0].mean()), -float(pts[:, 1].mean()))  # centre of mass straight below the root

    def rot(a):
        return torch.tensor([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]],
                            dtype=F64)

    rest = (pts @ rot(-hang).T @ rot(amp).T)[None]
    p = at.Params(material="per_particle", stretch_stiffness=1e2, integrity_stiffness=0.0, angular_stiffness=0.0,
                  drag=0.0, num_pinned=1, sag_free=False, dt=1 / 60, substeps=2, geometric_stiffness=geometric)
    sim = at.Simulator(rest, p, dtype=F64)
    s = sim.initial_state()
    xs = []
    for _ in range(150):
        s = sim.step(s)
        xs.append(float(s.x[0].mean(0)[0]))
    xs = torch.tensor(xs, dtype=F64)
    t = torch.arange(1, len(xs) + 1, dtype=F64) * p.dt
    down = torch.nonzero((xs[:-1] > 0) & (xs[1:] <= 0)).flatten()
    cross = t[down] + xs[down] / (xs[down] - xs[down + 1]) * p.dt  # interpolated downward crossings
    period = float((cross[-1] - cross[0]) / (len(cross) - 1))
    r = pts - pts[0]
    inertia, arm = float((r[:, :2] ** 2).sum()), float(r.mean(0).norm())
    expected = 2 * math.pi * math.sqrt(inertia / (n * 9.81 * arm)) * (1 + amp ** 2 / 16)
    with capsys.disabled():
        print(f"\n[pendulum] M = 2, dt = 1/60, geometric stiffness {geometric}: period {period:.6f} s vs rigid body "
              f"{expected:.6f} s "
              f"({period / expected - 1:+.4%}) over {len(cross) - 1} periods")
    assert len(cross) >= 3
    assert abs(period / expected - 1) <= tolerance


def test_double_moves_the_whole_model():
    rest = sphere_groom(6, 8, seed=3)
    sim = at.Simulator(rest, at.Params(), colliders=[at.stages.SphereCollider(radius=0.1, follow_head=True)],
                       hair_hair=at.HairHair(resolution=8))
    sim.double()
    assert all(b.dtype in (F64, torch.bool, torch.int64) for b in sim.buffers())
    s = sim.initial_state()
    s = sim.step(s, Shake().poses(1, sim.params.dt, dtype=F64)[0])
    assert s.x.dtype == F64 and s.v.dtype == F64 and s.ghost_rest.dtype == F64
    assert sim.model.colliders[0].center.dtype == F64


def test_state_dict_round_trip_reproduces_a_run_bit_for_bit():
    rest = sphere_groom(8, 10, seed=4)
    params = at.Params(integrity_rate=200.0, drag=1.0)
    a = at.Simulator(rest, params, learnable=("drag",))
    with torch.no_grad():
        a.model.drag.mul_(0.5)
    b = at.Simulator(rest, params.replace(integrity_rate=500.0, linear_density=2e-4), learnable=("drag",))
    assert len(a.state_dict()) > 10
    b.load_state_dict(a.state_dict())
    poses = Shake().poses(10, params.dt)
    sa, sb = a.initial_state(), b.initial_state()
    for pose in poses:
        sa, sb = a.step(sa, pose), b.step(sb, pose)
    assert torch.equal(sa.x, sb.x) and torch.equal(sa.v, sb.v)


def test_learnable_parameters_get_gradients_and_fit():
    """learnable fields are nn.Parameters of the module; Adam on them reduces a rollout loss
    toward a target made with other values."""
    rest = sphere_groom(6, 8, seed=5, dtype=F64)
    poses = Shake(amplitude=0.8).poses(8, 1 / 60, dtype=F64)
    truth = at.Simulator(rest, at.Params(integrity_rate=300.0, drag=3.0), dtype=F64)
    s = truth.initial_state()
    for pose in poses:
        s = truth.step(s, pose)
    target = s.x.detach()
    sim = at.Simulator(rest, at.Params(integrity_rate=100.0, drag=1.5), dtype=F64,
                       learnable=("integrity_rate", "drag"))
    names = {n for n, _ in sim.named_parameters()}
    assert names == {"model.integrity_rate", "model.drag"}
    opt = torch.optim.Adam([{"params": [sim.model.integrity_rate], "lr": 20.0},
                            {"params": [sim.model.drag], "lr": 0.2}])
    losses = []
    for _ in range(25):
        opt.zero_grad()
        s = sim.initial_state()
        for pose in poses:
            s = sim.step(s, pose)
        loss = ((s.x - target) ** 2).sum()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    assert losses[-1] < 0.2 * losses[0]
    assert abs(float(sim.model.integrity_rate.detach()) - 300.0) < abs(100.0 - 300.0)


# ----------------------------------------------------------------------- inputs at the boundary
@pytest.mark.parametrize("rotation", [torch.zeros(3, 3), 2 * torch.eye(3),
                                      torch.tensor([[1.0, 0.3, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]),
                                      torch.diag(torch.tensor([1.0, 1.0, -1.0]))])
def test_pose_that_is_not_a_rotation_is_refused(rotation):
    with pytest.raises(ValueError, match="not a rotation"):
        at.Pose(rotation, torch.zeros(3))


def test_bad_frame_inputs_name_the_argument():
    rest = sphere_groom(4, 8, seed=6)
    sim = at.Simulator(rest, at.Params())
    s = sim.initial_state()
    with pytest.raises(ValueError, match=r"Pose.rotation must have shape \(\.\.\., 3, 3\); got \(4, 4\)"):
        at.Pose(torch.eye(4), torch.zeros(3))
    with pytest.raises(ValueError, match=r"Pose.translation must have shape \(3,\).*got \(2,\)"):
        at.Pose(torch.eye(3), torch.zeros(2))
    with pytest.raises(ValueError, match=r"external_force must have shape \(4, 8, 3\)"):
        sim.step(s, external_force=torch.zeros(4, 7, 3))
    with pytest.raises(ValueError, match=r"pose has batch shape \(2,\) but the state's scenes are \(\)"):
        sim.step(s, at.Pose(torch.eye(3).expand(2, 3, 3), torch.zeros(2, 3)))
    with pytest.raises(ValueError, match="state is torch.float64 but the simulator is torch.float32"):
        sim.step(s.replace(x=s.x.double(), v=s.v.double()))
    with pytest.raises(ValueError, match="collider_poses given but the simulator has no colliders"):
        sim.step(s, collider_poses=[None])


def test_divergence_from_nan_input_says_so():
    rest = sphere_groom(4, 8, seed=7)
    sim = at.Simulator(rest, at.Params())
    s = sim.initial_state()
    v = s.v.clone()
    v[2, 5, 0] = float("nan")
    with pytest.raises(at.SimulationDiverged, match="input of that frame .* already held NaN/Inf") as info:
        sim.step(s.replace(v=v))
    assert info.value.bad_input and info.value.frame == 1 and info.value.strands == [[2]]
    fast = s.replace(v=s.v + 1e5)
    with pytest.raises(at.SimulationDiverged, match="Try more substeps") as info:
        sim.step(fast)
    assert not info.value.bad_input


def test_solve_banded_reports_systems_that_are_not_spd():
    blocks = torch.zeros(2, 3, 5, 4, 3, 3, dtype=F64)
    blocks[..., 0, :, :] = torch.eye(3, dtype=F64)
    rhs = torch.ones(2, 3, 5, 3, dtype=F64)
    at.solver.solve_banded(blocks, rhs)  # SPD: fine
    for bad, why in ((-torch.eye(3), "not symmetric positive definite"), (torch.zeros(3, 3), "not symmetric"),
                     (torch.full((3, 3), float("nan")), "NaN/Inf")):
        b = blocks.clone()
        b[1, 2, 3, 0] = bad
        with pytest.raises(torch.linalg.LinAlgError, match=rf"strand \(1, 2\) \(1 of 6 failing\): .*{why}"):
            at.solver.solve_banded(b, rhs)
        assert torch.isnan(at.solver.solve_banded(b, rhs, check=False)[1, 2]).any()
