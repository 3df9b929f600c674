"""The CUDA path on a real GPU (skipped without one): what the emulated tests cannot run and what the
other CUDA tests never reach. Several blocks and 3+ scenes; 100k strands (checked against the CPU on a
sample of strands: strands do not interact in the frame); N = 128 and 256; every collider and the
grid ops and their adjoints on 3 scenes; the finish and yield adjoints; the collision stage's adjoint and the pressure sweeps with their adjoint; float32 bounded
against float64 (not an absolute 1e-5, which rounding reaches
at N = 40); opcheck of the collision and finish ops on CUDA; non-contiguous inputs; a side stream;
a second GPU; P2G under torch's deterministic mode; torch.compile of the step; the emulator's
self-test kernels on the device (its answers are the emulation's).

``AMS_TORCH_CUDA_TEST_DEVICE=cpu`` runs this file's code on the CPU instead (the device and the
reference are then the same kernels: it checks the tests themselves, not the GPU).
"""
from __future__ import annotations

import os

import pytest
import torch
from helpers import built_native, rel
from native_cases import (F32, F64, case_scene, compare_grid_adjoints, expected_warp_ops, frame_args, make_case,
                          make_colliders, make_scene, native_frame, native_system, set_pinned, solve_args,
                          squeeze_scene, sweeps_case, tol as grid_tol, without_hollow)

import ams_torch
from ams_torch.sim import native
from ams_torch.sim.op_support import pose_tensors
from ams_torch.stages.collide import SphereCollider, resolve_world_poses
from ams_torch.stages.hair_hair.native import p2g_op
from ams_torch.stages.hair_hair.sparse import densify, p2g_sparse

DEVICE = os.environ.get("AMS_TORCH_CUDA_TEST_DEVICE", "cuda")
EPS32 = torch.finfo(F32).eps
pytestmark = [pytest.mark.cuda,
              pytest.mark.skipif(DEVICE == "cuda" and not torch.cuda.is_available(), reason="no CUDA device")]


def backend(base: str):
    """The namespace of op group ``base``'s kernels on DEVICE (built), e.g. backend("frame"): the
    device's one library (every group but the emulator's self-test)."""
    if base == "selftest":
        return built_native("selftest_cuda_emu" if DEVICE == "cpu" else "selftest_cuda")
    return built_native(DEVICE)


def bounded(dev32, cpu32, ref64) -> bool:
    """float32 on the device no farther from the float64 result than twice float32 on the CPU is (+8 ulps)."""
    return rel(dev32, ref64) <= 2 * rel(cpu32, ref64) + 8 * EPS32


def _frame_on(device, case, dtype, **kw):
    sim, state, pose1, coeffs = case_scene(case, dtype=dtype, device=device, **kw)
    args = frame_args(sim, state, pose1, coeffs)
    ns = backend("frame") if device == DEVICE else built_native("cpu")
    k = sim.config.substeps - 1
    return native_frame(ns, *args), native_system(ns, *args[:10], k)


# -- the frame -----------------------------------------------------------------------------------

@pytest.mark.parametrize("case", ["default", "nonhookean", "stiff", "three_pins", "one_particle_angular"])
def test_cuda_frame_many_blocks_and_scenes(case):
    """4 scenes × 300 strands: several blocks at every block size, scene boundaries inside blocks;
    float64 to 1e-12 of the CPU kernel, float32 bounded by float64."""
    out = {}
    for dtype in (F64, F32):
        for device in ("cpu", DEVICE):
            out[dtype, device] = _frame_on(device, case, dtype, scenes=4, strands=300, particles=16)
    (xc, vc), (bc, rc) = out[F64, "cpu"]
    (xg, vg), (bg, rg) = out[F64, DEVICE]
    assert max(rel(xg, xc), rel(vg, vc), rel(bg, bc), rel(rg, rc)) <= 1e-12
    (x32c, v32c), _ = out[F32, "cpu"]
    (x32g, v32g), _ = out[F32, DEVICE]
    assert bounded(x32g, x32c, xc) and bounded(v32g, v32c, vc), (rel(x32g, xc), rel(x32c, xc))


@pytest.mark.parametrize("particles", [128, 256])
def test_cuda_frame_long_strands(particles):
    out = {(d, t): _frame_on(d, "default", t, strands=64, particles=particles, substeps=2)
           for d in ("cpu", DEVICE) for t in (F64, F32)}
    (xc, vc), _ = out["cpu", F64]
    (xg, vg), _ = out[DEVICE, F64]
    assert rel(xg, xc) <= 1e-11 and rel(vg, vc) <= 1e-11
    assert bounded(out[DEVICE, F32][0][0], out["cpu", F32][0][0], xc)


def test_cuda_frame_100k_strands():
    """100k strands × 32 particles, float32, on the device; the CPU kernel on 2,000 of them (a strand's
    frame depends on that strand alone), float32 and float64."""
    sim, state, pose1 = make_scene(dtype=F32, device=DEVICE, strands=100_000, particles=32, substeps=2)
    xg, vg = native_frame(backend("frame"), *frame_args(sim, state, pose1))
    pick = torch.randperm(100_000, generator=torch.Generator().manual_seed(0))[:2000].sort().values
    ref = {}
    for dtype in (F32, F64):
        small = ams_torch.Simulator(sim.model.rest_positions.cpu()[pick].double(), sim.params, dtype=dtype)
        set_pinned(small.model, 2)
        sub = state.replace(**{k: getattr(state, k).cpu()[pick].to(dtype) for k in ("x", "v", "ghost_rest",
                                                                                       "sag_offset")},
                            pose=state.pose.to(device="cpu", dtype=dtype), time=state.time.cpu().to(dtype))
        ref[dtype] = native_frame(built_native("cpu"), *frame_args(small, sub, pose1.to(device="cpu",
                                                                                               dtype=dtype)))
    got = xg.cpu()[pick]
    assert bounded(got, ref[F32][0], ref[F64][0]), (rel(got, ref[F64][0]), rel(ref[F32][0], ref[F64][0]))
    assert bounded(vg.cpu()[pick], ref[F32][1], ref[F64][1])


def test_cuda_frame_noncontiguous_inputs():
    sim, state, pose1, coeffs = case_scene("default", dtype=F64, device=DEVICE, scenes=2, strands=37)
    args = native.op_arguments(*frame_args(sim, state, pose1, coeffs)[:10], None)
    ns = backend("frame")
    state_nc = [t.transpose(-1, -3).contiguous().transpose(-1, -3) for t in args[0]]
    assert not state_nc[0].is_contiguous()
    got, want = ns.frame(state_nc, *args[1:], -1), ns.frame(*args, -1)
    assert torch.equal(got[0], want[0]) and torch.equal(got[1], want[1])


@pytest.mark.skipif(DEVICE != "cuda", reason="CUDA streams")
def test_cuda_side_stream():
    """Inputs made and the frame, collision and grid ops run on a side stream: the results of the
    default stream (the bindings launch on the current stream)."""
    sim, state, pose1, coeffs = case_scene("default", dtype=F64, device="cuda", scenes=2, strands=200)
    args = native.op_arguments(*frame_args(sim, state, pose1, coeffs)[:10], None)
    ns = backend("frame")
    want = ns.frame(*args, -1)
    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):
        moved = [[t * 1.0 for t in args[0]]] + list(args[1:])  # made on the side stream
        got = ns.frame(*moved, -1)
        gx = got[0] * 1.0
    torch.cuda.current_stream().wait_stream(side)
    assert torch.equal(gx, want[0]) and torch.equal(got[1], want[1])


@pytest.mark.skipif(DEVICE != "cuda" or torch.cuda.device_count() < 2, reason="needs two GPUs")
def test_cuda_second_device():
    out = {}
    for dev in ("cuda:0", "cuda:1"):
        sim, state, pose1, coeffs = case_scene("nonhookean", dtype=F64, device=dev, scenes=2, strands=50)
        out[dev] = native_frame(backend("frame"), *frame_args(sim, state, pose1, coeffs))
        assert out[dev][0].device == torch.device(dev)
    assert rel(out["cuda:1"][0], out["cuda:0"][0]) <= 1e-15


# -- collisions, the frame's end, the grid -----------------------------------------------------------

def _collide_case(device, dtype, scenes=3, strands=200):
    sim, x, v, head, _ = make_case("all", dtype=dtype, scenes=scenes, strands=strands)
    rest = sim.model.rest_positions.double().cpu()
    dsim = ams_torch.Simulator(rest, sim.params, device=device, dtype=dtype, colliders=make_colliders("all", rest))
    return dsim, x.to(device), v.to(device), head.to(device=device)


def test_cuda_every_collider_three_scenes():
    out = {}
    for dtype in (F64, F32):
        for device in ("cpu", DEVICE):
            sim, x, v, head = _collide_case(device, dtype)
            world = resolve_world_poses(sim.colliders, head, None)
            ns = backend("collide") if device == DEVICE else built_native("cpu")
            out[dtype, device] = ns.collide(*native.collision_arguments(sim.model, sim.config, x, v, head, world))
    (xc, vc), (xg, vg) = out[F64, "cpu"], out[F64, DEVICE]
    assert rel(xg, xc) <= 1e-12 and rel(vg, vc) <= 1e-12
    assert bounded(out[F32, DEVICE][0], out[F32, "cpu"][0], xc) and bounded(out[F32, DEVICE][1], out[F32, "cpu"][1], vc)


def test_cuda_collide_adjoint_three_scenes():
    """The collision stage's adjoint (one thread per strand, C × 19 pose adjoints per strand) on the
    device against the CPU kernel: every native-adjoint collider together, 3 scenes × 200 strands."""
    out = {}
    for dtype in (F64, F32):
        for device in ("cpu", DEVICE):
            sim, x, v, head = _collide_case(device, dtype)
            world = resolve_world_poses(sim.colliders, head, None)
            args = without_hollow(native.collision_arguments(sim.model, sim.config, x, v, head, world))
            g = torch.Generator().manual_seed(8)
            gx, gv = (torch.randn(x.shape, generator=g, dtype=F64).to(device=device, dtype=dtype) for _ in range(2))
            ns = backend("collide") if device == DEVICE else built_native("cpu")
            out[dtype, device] = [t.cpu() for t in ns.collide_adjoint(*args, gx, gv)]
    for c, d in zip(out[F64, "cpu"], out[F64, DEVICE]):
        assert float((c - d).abs().max()) <= 1e-12 * max(float(c.abs().max()), 1.0)
    for ref, c32, d32 in zip(out[F64, "cpu"], out[F32, "cpu"], out[F32, DEVICE]):
        assert float((d32.double() - ref).abs().max()) <= 2 * float((c32.double() - ref).abs().max()) + \
            8 * EPS32 * max(float(ref.abs().max()), 1.0)


@pytest.mark.parametrize("dtype", [F64, F32])
def test_cuda_pressure_sweeps_and_adjoint(dtype):
    """The pressure sweeps (a launch per sweep) and their adjoint (atomicAdd scatter) on the device
    against the CPU kernels, 50 sweeps over 60k slots."""
    src, coef, w, nbr, gout = sweeps_case(60001, 9, dtype)
    cpu, dev = built_native("cpu"), backend("grid")
    on = lambda *ts: [t.to(DEVICE) for t in ts]  # noqa: E731
    want = cpu.sweeps(src, coef, w, nbr, 50, 0.6)
    got = dev.sweeps(*on(src, coef, w, nbr), 50, 0.6).cpu()
    bound = 1e-12 if dtype == F64 else 64 * EPS32
    assert float((got - want).abs().max()) <= bound * max(float(want.abs().max()), 1.0)
    for c, d in zip(cpu.sweeps_adjoint(src, coef, w, nbr, 50, 0.6, gout),
                    dev.sweeps_adjoint(*on(src, coef, w, nbr), 50, 0.6, gout.to(DEVICE))):
        assert float((c - d.cpu()).abs().max()) <= bound * max(float(c.abs().max()), 1.0), rel(d.cpu(), c)


def test_cuda_opcheck_collisions_and_finish():
    backend("collide"), backend("frame")
    for dtype in (F64, F32):
        sim, x, v, head = _collide_case(DEVICE, dtype, scenes=2, strands=5)
        world = resolve_world_poses(sim.colliders, head, None)
        torch.library.opcheck(torch.ops.ams_torch.collisions.default,
                              native.collision_arguments(sim.model, sim.config, x, v, head, world))
        (_, t, lin, ang), _ = pose_tensors(head, x)
        torch.library.opcheck(torch.ops.ams_torch.finish.default, (x, v, sim.model.num_pinned, [t, lin, ang]))


@pytest.mark.parametrize("dtype", [F64, F32])
def test_cuda_grid_three_scenes(dtype):
    """The block-sparse grid ops on the device against the CPU kernels, 3 scenes. Slots may be
    handed out in another order on the device (atomics): pools are compared in their dense layout."""
    s_cpu = squeeze_scene(dtype, "cpu", strands=300, particles=10, resolution=24, scenes=3)
    s_dev = squeeze_scene(dtype, DEVICE, strands=300, particles=10, resolution=24, scenes=3)
    grid, grid_d = s_cpu["grid"], s_dev["grid"]
    h, r, k = grid.cell_size, grid.resolution, grid.capacity
    ns_c, ns_d = built_native("cpu"), backend("grid")
    pool_c = ns_c.p2g(s_cpu["xf"], s_cpu["vf"], s_cpu["m"], s_cpu["frame"], grid.origin, h, r, k)
    pool_d = ns_d.p2g(s_dev["xf"], s_dev["vf"], s_dev["m"], s_dev["frame"], grid_d.origin, h, r, k)
    assert torch.equal(pool_d[3].cpu(), pool_c[3])  # the same number of blocks per scene
    dense = lambda values, pool: densify(values.cpu(), pool[2].cpu(), r)  # noqa: E731
    assert rel(dense(pool_d[0], pool_d), dense(pool_c[0], pool_c)) <= grid_tol(dtype, r)
    phi_c, field_c, over_c = ns_c.pressure(*pool_c, grid.target_density, s_cpu["dt"], h, r, *solve_args(grid),
                                           grid.active_capacity)
    phi_d, field_d, over_d = ns_d.pressure(*pool_d, grid_d.target_density, s_dev["dt"], h, r, *solve_args(grid),
                                           grid.active_capacity)
    assert torch.equal(over_d.cpu(), over_c) and not bool(over_c.any())
    assert float(phi_c[pool_c[2] >= 0].max()) > 0  # the squeeze pushes
    assert rel(dense(phi_d, pool_d), dense(phi_c, pool_c)) <= grid_tol(dtype, r)
    assert rel(dense(field_d, pool_d), dense(field_c, pool_c)) <= grid_tol(dtype, r)


@pytest.mark.parametrize("dtype", [F64, F32])
def test_cuda_grid_adjoints_three_scenes(dtype):
    """The grid's adjoints (p2g_adjoint, pressure_adjoint, g2p_adjoint) on the device against the CPU
    kernels on the same pool (the CPU's P2G table), 3 scenes, pressure active, 50 sweeps."""
    compare_grid_adjoints(built_native("cpu"), backend("grid"), dtype, DEVICE, strands=300, particles=10,
                          resolution=24, bound=1e-12 if dtype == F64 else 256 * EPS32)


@pytest.mark.parametrize("dtype", [F64, F32])
def test_cuda_finish_and_yield_adjoints(dtype):
    """The finish and yield adjoints on the device against the CPU kernels, 3 scenes × 2,000 strands."""
    g = torch.Generator().manual_seed(3)
    x, v = (torch.randn(3, 2000, 16, 3, generator=g, dtype=dtype) for _ in range(2))
    pose = [torch.randn(3, 3, generator=g, dtype=dtype) for _ in range(3)]
    pinned = torch.randint(0, 4, (2000,), generator=g)
    gv, gs = torch.randn(x.shape, generator=g, dtype=dtype), torch.randn(x.shape[:-1], generator=g, dtype=dtype)
    cpu, dev = built_native("cpu"), backend("frame")
    on = lambda *ts: [t.to(DEVICE) for t in ts]  # noqa: E731
    bound = 1e-12 if dtype == F64 else 16 * EPS32
    for c, d in zip(cpu.finish_adjoint(x, v, pinned, pose, gv, gs),
                    dev.finish_adjoint(*on(x, v, pinned), on(*pose), *on(gv, gs))):
        assert float((c - d.cpu()).abs().max()) <= bound * float(c.abs().max()), rel(d.cpu(), c)
    anchor = x + 0.1 * torch.randn(x.shape, generator=g, dtype=dtype)
    limit = 0.1 * torch.rand(2000, 16, generator=g, dtype=dtype)
    free = torch.rand(2000, 16, generator=g) > 0.2
    for c, d in zip(cpu.yield_adjoint(x, anchor, limit, free, gv), dev.yield_adjoint(*on(x, anchor, limit, free, gv))):
        assert float((c - d.cpu()).abs().max()) <= bound * float(c.abs().max()), rel(d.cpu(), c)


def test_cuda_p2g_deterministic_mode():
    """P2G's float atomics: the raw CUDA op refuses torch's deterministic mode (alertNotDeterministic);
    the registered op takes the sparse torch definition there, and gives the same bits twice."""
    s = squeeze_scene(F32, DEVICE, strands=300, particles=10, resolution=24, scenes=2)
    grid = s["grid"]
    args = (s["xf"], s["vf"], s["m"], s["frame"], grid.origin, grid.cell_size, grid.resolution, grid.capacity)
    ns = backend("grid")
    before = torch.are_deterministic_algorithms_enabled()
    torch.use_deterministic_algorithms(True)
    try:
        if DEVICE == "cuda":
            with pytest.raises(RuntimeError, match="ams_torch_cuda::p2g"):
                ns.p2g(*args)
        a, b = p2g_op(*args, False), p2g_op(*args, False)
        same = lambda p, q: (all(torch.equal(u, w) for u, w in zip(p[1:], q[1:]))  # noqa: E731
                             and torch.equal(p[0][p[2] >= 0], q[0][q[2] >= 0]))  # unused slots: unspecified
        assert same(a, b)
        if DEVICE == "cuda":
            assert same(a, p2g_sparse(*args))
    finally:
        torch.use_deterministic_algorithms(before)
    pool, ref = p2g_op(*args, False), p2g_sparse(*args)
    assert rel(densify(pool[0], pool[2], grid.resolution), densify(ref[0], ref[2], grid.resolution)) <= \
        grid_tol(F32, grid.resolution)


# -- the whole step ----------------------------------------------------------------------------------

def test_cuda_step_compiles_fullgraph():
    """torch.compile(sim.step, fullgraph=True) with inductor on the device, every stage on: equal to
    eager over 3 frames."""
    from ams_torch.apps.motion import Shake

    from ams_torch.testing import sphere_groom

    sim = ams_torch.Simulator(sphere_groom(200, 16), ams_torch.Params(), device=DEVICE,
                              colliders=[SphereCollider((0.0, 0.0, 0.0), 0.106)],
                              hair_hair=ams_torch.HairHair(resolution=16))
    torch._dynamo.reset()
    compiled = torch.compile(sim.step, fullgraph=True, backend="inductor" if DEVICE == "cuda" else "aot_eager")
    se = sc = sim.initial_state()
    for pose in Shake(amplitude=1.0).poses(3, sim.params.dt, device=DEVICE):
        se, sc = sim.step(se, pose), compiled(sc, pose)
    torch.testing.assert_close(sc.x, se.x, rtol=1e-5, atol=1e-6)
    torch._dynamo.reset()


# -- the emulator's self-test on the device: the emulation's answers are the hardware's ---------------

@pytest.mark.parametrize("threads", [32, 50, 96])
def test_cuda_selftest_warp_collectives(threads):
    ns = backend("selftest")
    got = ns.warp_ops(torch.zeros(1, device=DEVICE), threads).cpu()
    assert torch.equal(got, expected_warp_ops(threads)), (got - expected_warp_ops(threads)).nonzero()[:8]


def test_cuda_selftest_atomics_and_launch_limits():
    ns = backend("selftest")
    like = torch.zeros(1, device=DEVICE)
    x = torch.rand(100_000, dtype=F64, generator=torch.Generator().manual_seed(0))
    assert abs(ns.block_sum(x.to(DEVICE), 64).item() - x.sum().item()) <= 1e-12 * x.sum().item()
    assert ns.atomics(like, 300, 256).tolist() == [76800.0, 38400.0, 19200.0]
    g = torch.Generator().manual_seed(1)
    for index in (torch.zeros(5000, dtype=torch.int64), torch.arange(5000) // 7, torch.randint(0, 3, (5000,),
                                                                                                  generator=g)):
        values = torch.randn(5000, dtype=F64, generator=g)
        size = int(index.max()) + 1
        got = ns.warp_add(values.to(DEVICE), index.to(DEVICE), size, 128, 8).cpu()
        want = torch.zeros(size, dtype=F64).index_add_(0, index, values)
        assert (got - want).abs().max().item() <= 1e-12 * values.abs().sum().item()
    for grid, block, shared in (((1, 1, 1), (1025, 1, 1), 0), ((0, 1, 1), (32, 1, 1), 0),
                                ((1, 1, 1), (32, 1, 1), 64 * 1024)):
        with pytest.raises(RuntimeError, match="invalid"):
            ns.launch(like, list(grid), list(block), shared)
    ns.launch(like, [2, 1, 1], [1024, 1, 1], 48 * 1024)
