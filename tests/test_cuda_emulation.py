"""The CUDA kernels, run on the CPU: every CUDA backend of the build table (its .cu files and its torch
binding) compiled as host code by the emulation (``ams_torch/native/emulation.py``,
``csrc/emulation/cuda_emulation.h``), against the CPU kernels (and the emulator's self-test).

What this shows: the CUDA launchers, kernels and bindings compute what the CPU kernels compute, for
every frame case, every collider, every grid op and the banded solve, in float64 and float32;
with several blocks, a scene boundary inside a block, the three block sizes that the launchers
choose by strand count (``strand_block_threads``), the grid-stride loops (the grid capped to one
or three blocks by ``AMS_TORCH_EMU_MAX_GRID``); that results do not depend on the order of blocks
and threads (forward, reverse, shuffled; blocks on two host threads, whose atomics then race); that
the launches respect the device's limits (the emulator refuses what a GPU refuses), that no kernel
waits at a divergent barrier or in a warp collective missing a lane (the emulator reports both),
and that the warp collectives and the warp-aggregated atomics do what CUDA specifies.

What it cannot show (the first GPU run, ``scripts/validate_cuda.sh``, does): anything about time
(warp scheduling, occupancy, coalescing, atomics contention, launch overhead); the device's math
library (its sin/cos/atan2/sqrt differ from the host libm by an ulp or so); nvcc's contraction of
a*b+c into fused multiply-adds (this build contracts nothing); out-of-bounds accesses (the host has
no bounds; compute-sanitizer on the GPU); the register and local-memory budget (the ptxas check,
``tests/test_ptxas_budget.py``); races that need two warps to really run at once (blocks run their
threads one at a time, in the orders above).

Tolerances: float64 1e-12 relative to the CPU kernel (measured ~1e-16: the same arithmetic,
different compiler, no FMA); float32: no farther from the float64 CPU result than twice the
float32 CPU kernel is, plus 8 ulps (both are roundings of the same computation amplified by the
same conditioning); the grid ops with the bounds of ``tests/test_native_grid.py``.
"""
from __future__ import annotations

import pytest
import torch
from helpers import built_native, rel
from native_cases import (FRAME_CASES, case_scene, compare_grid_adjoints, expected_warp_ops, frame_args, make_case,
                          native_frame, native_system, solve_args, squeeze_scene, strand_system, sweeps_case,
                          tol as grid_tol)

from ams_torch.sim import native
from ams_torch.native import build as _native
from ams_torch.solver.reference import solve_banded_dense
from ams_torch.stages.collide import resolve_world_poses
from ams_torch.stages.hair_hair.sparse import densify, p2g_sparse

F64, F32 = torch.float64, torch.float32
EPS32 = torch.finfo(F32).eps
ENV = {"order": "AMS_TORCH_EMU_ORDER", "workers": "AMS_TORCH_EMU_WORKERS", "sms": "AMS_TORCH_EMU_SMS",
       "max_grid": "AMS_TORCH_EMU_MAX_GRID", "seed": "AMS_TORCH_EMU_SEED"}
# emulated devices: (name, environment). 132 SMs: small scenes get 32-thread blocks; 1 SM: 128.
SCHEDULES = {
    "reverse_grid1": {"order": "reverse", "max_grid": "1"},
    "shuffle_2workers_grid3": {"order": "shuffle", "seed": "5", "workers": "2", "max_grid": "3"},
}


@pytest.fixture
def emu_env(monkeypatch):
    """Set the emulated device / schedule for one test: ``emu_env(order=..., sms=..., ...)``."""
    def apply(**kw):
        for key, name in ENV.items():
            monkeypatch.delenv(name, raising=False)
        for key, value in kw.items():
            monkeypatch.setenv(ENV[key], str(value))
    apply()
    return apply


@pytest.fixture(scope="session")
def emu():
    """Every emulated backend, built (or loaded from the cache) once per session."""
    out = {}
    for kind in _native.kinds("emulation"):
        out[kind] = built_native(kind)
    return out


@pytest.fixture(scope="session")
def cpu():
    return {"cpu": built_native("cpu")}


def test_every_cuda_backend_has_a_built_emulation(emu):
    """Each CUDA backend of the build table (the one CUDA library, and the self-test) has its
    emulated twin, built from the same sources and headers, smoke-tested, registered under its own
    namespace; the CUDA library's sources are every group's CUDA sources."""
    table = _native._ALL
    cuda = [k for k, spec in table.items() if spec[4] == "cuda"]
    assert set(cuda) == {"cuda", "selftest_cuda"}
    assert set(table["cuda"][1]) == {s for _, srcs in _native.GROUPS.values() for s in srcs}
    assert table["cuda_emu"][3] == "ams_torch_cuda_emu"
    status = _native.native_status()
    for kind in cuda:
        twin = table[kind + "_emu"]
        assert twin[1:3] == table[kind][1:3] and twin[3] == table[kind][3] + "_emu"
        assert status[kind + "_emu"]["built"], status[kind + "_emu"]["reason"]
        assert status[kind + "_emu"]["device"] == "emulation"


# -- the frame ----------------------------------------------------------------------------------

def _frame_pair(ns_cpu, ns_emu, case, dtype, **kw):
    sim, state, pose1, coeffs = case_scene(case, dtype=dtype, **kw)
    args = frame_args(sim, state, pose1, coeffs)
    out = {}
    for name, ns in (("cpu", ns_cpu), ("emu", ns_emu)):
        out[name] = native_frame(ns, *args), native_system(ns, *args[:10], sim.config.substeps - 1)
    return out


@pytest.mark.parametrize("case", list(FRAME_CASES))
def test_frame_float64(cpu, emu, emu_env, case):
    """Every frame case: 2 scenes × 37 strands = 74 threads in three 32-thread blocks, the scene
    boundary inside the second one."""
    out = _frame_pair(cpu["cpu"], emu["cuda_emu"], case, F64, scenes=2, strands=37)
    (xc, vc), (bc, rc) = out["cpu"]
    (xe, ve), (be, re) = out["emu"]
    for got, want, what in ((xe, xc, "x"), (ve, vc, "v"), (be, bc, "blocks"), (re, rc, "rhs")):
        assert rel(got, want) <= 1e-12, f"{case} {what}: {rel(got, want):.3g}"


@pytest.mark.parametrize("case", ["default", "nonhookean", "stiff", "one_particle_angular", "three_pins"])
def test_frame_float32_bounded_by_float64(cpu, emu, emu_env, case):
    ref = _frame_pair(cpu["cpu"], emu["cuda_emu"], case, F64, scenes=2, strands=21, particles=16)
    f32 = _frame_pair(cpu["cpu"], emu["cuda_emu"], case, F32, scenes=2, strands=21, particles=16)
    (x64, v64), _ = ref["cpu"]
    (xc, vc), _ = f32["cpu"]
    (xe, ve), _ = f32["emu"]
    assert xe.dtype == F32
    for emu_r, cpu_r, want, what in ((xe, xc, x64, "x"), (ve, vc, v64, "v")):
        bound = 2 * rel(cpu_r, want) + 8 * EPS32
        assert rel(emu_r, want) <= bound, f"{case} {what}: emulated {rel(emu_r, want):.3g}, CPU {rel(cpu_r, want):.3g}"


@pytest.mark.parametrize("sms,scenes,strands", [(1, 3, 200), (4, 3, 200), (132, 1, 5)])
def test_frame_block_sizes(cpu, emu, emu_env, sms, scenes, strands):
    """The three block sizes of strand_block_threads (1 SM: 600 strands in 128-thread blocks; 4 SMs:
    64; 132 SMs: a 5-strand scene in one 32-thread block), scene boundaries inside blocks."""
    emu_env(sms=sms)
    out = _frame_pair(cpu["cpu"], emu["cuda_emu"], "default", F64, scenes=scenes, strands=strands,
                      particles=8)
    (xc, vc), (bc, rc) = out["cpu"]
    (xe, ve), (be, re) = out["emu"]
    assert max(rel(xe, xc), rel(ve, vc), rel(be, bc), rel(re, rc)) <= 1e-12


@pytest.mark.parametrize("schedule", list(SCHEDULES))
def test_frame_does_not_depend_on_the_schedule(emu, emu_env, schedule):
    """Block and thread order, two host threads and the grid-stride loops of the transposes (grid
    capped to 1 or 3 blocks): bit for bit the forward result (every thread owns its strand)."""
    sim, state, pose1, coeffs = case_scene("nonhookean", dtype=F64, scenes=3, strands=23)
    args = frame_args(sim, state, pose1, coeffs)
    ns = emu["cuda_emu"]
    want = native_frame(ns, *args)
    emu_env(**SCHEDULES[schedule])
    got = native_frame(ns, *args)
    assert torch.equal(got[0], want[0]) and torch.equal(got[1], want[1])


def test_frame_finish_and_noncontiguous_inputs(cpu, emu, emu_env):
    """frame_finish (the frame's end fused) and finish, as the CPU ops; non-contiguous state and
    poses (views) give the result of contiguous ones."""
    sim, state, pose1, coeffs = case_scene("default", dtype=F64, scenes=2, strands=37)
    args = native.op_arguments(*frame_args(sim, state, pose1, coeffs)[:10], None)
    finish = [pose1.translation.contiguous(), pose1.linear_velocity.contiguous(), pose1.angular_velocity.contiguous()]
    want = cpu["cpu"].frame_finish(*args, -1, finish)
    got = emu["cuda_emu"].frame_finish(*args, -1, finish)
    for g, w in zip(got, want):
        assert rel(g, w) <= 1e-12
    x, v = state.x, state.v
    want_f = cpu["cpu"].finish(x, v, sim.model.num_pinned, finish)
    got_f = emu["cuda_emu"].finish(x, v, sim.model.num_pinned, finish)
    assert all(rel(g, w) <= 1e-12 for g, w in zip(got_f, want_f))
    # non-contiguous: the state as a transposed copy's view, the same values
    state_nc = [t.transpose(-1, -3).contiguous().transpose(-1, -3) for t in args[0]]
    assert not state_nc[0].is_contiguous()
    got_nc = emu["cuda_emu"].frame(state_nc, *args[1:], -1)
    got_c = emu["cuda_emu"].frame(*args, -1)
    assert torch.equal(got_nc[0], got_c[0]) and torch.equal(got_nc[1], got_c[1])


# -- the collision stage --------------------------------------------------------------------------

def _collide(ns, sim, x, v, head):
    world = resolve_world_poses(sim.colliders, head, None)
    return ns.collide(*native.collision_arguments(sim.model, sim.config, x, v, head, world))


@pytest.mark.parametrize("kind", ["sphere", "capsule", "plane", "hollow", "hollow_closed", "mesh", "all"])
def test_collide_every_collider(cpu, emu, emu_env, kind):
    """Every collider (and all five together), float64 and float32, 2 scenes × 37 strands."""
    for dtype in (F64, F32):
        sim, x, v, head, _ = make_case(kind, dtype=dtype, scenes=2, strands=37)
        xc, vc = _collide(cpu["cpu"], sim, x, v, head)
        xe, ve = _collide(emu["cuda_emu"], sim, x, v, head)
        if dtype == F64:
            assert rel(xe, xc) <= 1e-12 and rel(ve, vc) <= 1e-12, (kind, rel(xe, xc), rel(ve, vc))
            ref = (xc, vc)
        else:
            for got, cpu32, want in ((xe, xc, ref[0]), (ve, vc, ref[1])):
                assert rel(got, want) <= 2 * rel(cpu32, want) + 8 * EPS32, (kind, rel(got, want), rel(cpu32, want))


def test_collide_does_not_depend_on_the_schedule(emu, emu_env):
    sim, x, v, head, _ = make_case("all", scenes=3, strands=23)
    ns = emu["cuda_emu"]
    want = _collide(ns, sim, x, v, head)
    for schedule in SCHEDULES.values():
        emu_env(**schedule)
        got = _collide(ns, sim, x, v, head)
        assert torch.equal(got[0], want[0]) and torch.equal(got[1], want[1])


@pytest.mark.parametrize("kind", ["sphere", "capsule", "plane", "mesh"])
def test_collide_adjoint(cpu, emu, emu_env, kind):
    """The collision stage's adjoint (one thread per strand) against the CPU kernel (SIMD lanes):
    x̄, v̄, every strand's pose and friction adjoints and the head rotation's, float64 and float32."""
    for dtype in (F64, F32):
        sim, x, v, head, _ = make_case(kind, dtype=dtype, scenes=2, strands=37, rounds=2)
        world = resolve_world_poses(sim.colliders, head, None)
        args = native.collision_arguments(sim.model, sim.config, x, v, head, world)
        g = torch.Generator().manual_seed(5)
        gx, gv = (torch.randn(x.shape, generator=g, dtype=F64).to(dtype) for _ in range(2))
        got_c = cpu["cpu"].collide_adjoint(*args, gx, gv)
        got_e = emu["cuda_emu"].collide_adjoint(*args, gx, gv)
        assert float(got_c[2].abs().max()) > 0, kind
        for c, e in zip(got_c, got_e):
            bound = 1e-12 if dtype == F64 else 64 * EPS32
            assert float((c - e).abs().max()) <= bound * max(float(c.abs().max()), 1.0), (kind, dtype, rel(e, c))


@pytest.mark.parametrize("dtype", [F64, F32])
def test_pressure_sweeps_and_adjoint(cpu, emu, emu_env, dtype):
    """The pressure sweeps (a launch per sweep) and their adjoint (per-slot launch, atomicAdd
    scatter) against the CPU kernels."""
    src, coef, w, nbr, gout = sweeps_case(1500, 6, dtype)
    bound = 1e-12 if dtype == F64 else 64 * EPS32
    for iterations in (0, 1, 7):
        phi_c = cpu["cpu"].sweeps(src, coef, w, nbr, iterations, 0.6)
        phi_e = emu["cuda_emu"].sweeps(src, coef, w, nbr, iterations, 0.6)
        assert float((phi_c - phi_e).abs().max()) <= bound * max(float(phi_c.abs().max()), 1.0), iterations
        for c, e in zip(cpu["cpu"].sweeps_adjoint(src, coef, w, nbr, iterations, 0.6, gout),
                        emu["cuda_emu"].sweeps_adjoint(src, coef, w, nbr, iterations, 0.6, gout)):
            assert float((c - e).abs().max()) <= bound * max(float(c.abs().max()), 1.0), (iterations, rel(e, c))


# -- the hair–hair grid ---------------------------------------------------------------------------

@pytest.mark.parametrize("dtype", [F64, F32])
@pytest.mark.parametrize("schedule", ["forward"] + list(SCHEDULES))
def test_grid_ops(cpu, emu, emu_env, dtype, schedule):
    """P2G (block slots by atomics, warp-aggregated adds into the pool), pressure (one block per
    scene, __syncthreads between sweeps) and G2P against the CPU kernels and the sparse torch
    definition, 3 scenes, every schedule (atomics racing on two threads). Slots may be handed out
    in another order than on the CPU: pools are compared in their dense layout."""
    if schedule != "forward":
        emu_env(**SCHEDULES[schedule])
    s = squeeze_scene(dtype, strands=60, particles=8, resolution=12, scenes=3)
    grid = s["grid"]
    h, r, k = grid.cell_size, grid.resolution, grid.capacity
    ns_c, ns_e = cpu["cpu"], emu["cuda_emu"]
    args = (s["xf"], s["vf"], s["m"], s["frame"], grid.origin, h, r, k)
    pool_c, pool_e, pool_t = ns_c.p2g(*args), ns_e.p2g(*args), p2g_sparse(*args)
    assert torch.equal(pool_e[3], pool_c[3])  # the same number of blocks per scene
    dense = lambda pool: densify(pool[0], pool[2], r)  # noqa: E731
    assert rel(dense(pool_e), dense(pool_c)) <= grid_tol(dtype, r)
    assert rel(dense(pool_e), dense(pool_t)) <= grid_tol(dtype, r)
    solve = (grid.target_density, s["dt"], h, r, *solve_args(grid), grid.active_capacity)
    phi_c, field_c, over_c = ns_c.pressure(*pool_c, *solve)
    phi_e, field_e, over_e = ns_e.pressure(*pool_e, *solve)
    used = pool_c[2] >= 0  # slots past count hold unspecified values (grid.h)
    assert float(phi_c[used].max()) > 0 and not bool(over_e.any()) and torch.equal(over_e, over_c)  # the squeeze pushes
    assert rel(densify(phi_e, pool_e[2], r), densify(phi_c, pool_c[2], r)) <= grid_tol(dtype, r)
    assert rel(densify(field_e, pool_e[2], r), densify(field_c, pool_c[2], r)) <= grid_tol(dtype, r)
    g2p = lambda field, pool: (s["xf"], s["vf"], field, pool[1], s["frame"], grid.origin, s["free"], s["dt"], h,  # noqa: E731
                               r, 0.05)
    (xc, vc), (xe, ve) = ns_c.g2p(*g2p(field_c, pool_c)), ns_e.g2p(*g2p(field_e, pool_e))
    assert rel(ve - s["vf"], vc - s["vf"]) <= grid_tol(dtype, r)
    assert rel(xe - s["xf"], xc - s["xf"]) <= grid_tol(dtype, r) + 8 * torch.finfo(dtype).eps


@pytest.mark.parametrize("dtype", [F64, F32])
@pytest.mark.parametrize("schedule", ["forward", "shuffle_2workers_grid3"])
def test_grid_adjoints(cpu, emu, emu_env, dtype, schedule):
    """The grid's adjoints (p2g_adjoint: a gather per particle; g2p_adjoint: atomicAdd into the
    field's adjoint; pressure_adjoint: the pool-form sweeps reversed, a gather launch per sweep)
    against the CPU kernels on the same pool (the CPU's P2G table), 3 scenes, pressure active."""
    if schedule != "forward":
        emu_env(**SCHEDULES[schedule])
    compare_grid_adjoints(cpu["cpu"], emu["cuda_emu"], dtype, bound=1e-12 if dtype == F64 else 256 * EPS32)


@pytest.mark.parametrize("dtype", [F64, F32])
def test_finish_and_yield_adjoints(cpu, emu, emu_env, dtype):
    """The finish adjoint (a thread per strand, the pose adjoints per strand) and the yield adjoint (a
    thread per particle) against the CPU kernels, 3 scenes, the grid capped to one block."""
    emu_env(max_grid=1)
    g = torch.Generator().manual_seed(3)
    x, v = (torch.randn(3, 5, 7, 3, generator=g, dtype=dtype) for _ in range(2))
    pose = [torch.randn(3, 3, generator=g, dtype=dtype) for _ in range(3)]
    pinned = torch.tensor([0, 1, 2, 7, 3])
    gv, gs = torch.randn(x.shape, generator=g, dtype=dtype), torch.randn(x.shape[:-1], generator=g, dtype=dtype)
    bound = 1e-12 if dtype == F64 else 16 * EPS32
    for g_speed in (gs, None):
        for c, e in zip(cpu["cpu"].finish_adjoint(x, v, pinned, pose, gv, g_speed),
                        emu["cuda_emu"].finish_adjoint(x, v, pinned, pose, gv, g_speed)):
            assert float((c - e).abs().max()) <= bound * float(c.abs().max()), rel(e, c)
    anchor = x + 0.1 * torch.randn(x.shape, generator=g, dtype=dtype)
    limit = 0.1 * torch.rand(5, 7, generator=g, dtype=dtype)
    free = torch.rand(5, 7, generator=g) > 0.2
    for c, e in zip(cpu["cpu"].yield_adjoint(x, anchor, limit, free, gv),
                    emu["cuda_emu"].yield_adjoint(x, anchor, limit, free, gv)):
        assert float((c - e).abs().max()) <= bound * float(c.abs().max()), rel(e, c)


def test_sweeps_adjoint_tells_deterministic_mode(emu):
    """The CUDA sweeps' adjoint scatters by float atomics: under torch.use_deterministic_algorithms its
    binding raises (sparse._sweeps_namespace takes the torch definition there on CUDA)."""
    src, coef, w, nbr, gout = sweeps_case(200, 3, F64)
    before = torch.are_deterministic_algorithms_enabled()
    torch.use_deterministic_algorithms(True)
    try:
        with pytest.raises(RuntimeError, match="sweeps_adjoint"):
            emu["cuda_emu"].sweeps_adjoint(src, coef, w, nbr, 3, 0.6, gout)
    finally:
        torch.use_deterministic_algorithms(before)


def test_grid_p2g_tells_deterministic_mode(emu):
    """The P2G kernel's float atomics sum in a varying order: under torch.use_deterministic_algorithms
    the binding raises (alertNotDeterministic); the registered op takes the torch definition there on CUDA."""
    s = squeeze_scene(F64, strands=20, particles=6, resolution=8, scenes=1)
    grid = s["grid"]
    args = (s["xf"], s["vf"], s["m"], s["frame"], grid.origin, grid.cell_size, grid.resolution, grid.capacity)
    before = torch.are_deterministic_algorithms_enabled()
    torch.use_deterministic_algorithms(True)
    try:
        with pytest.raises(RuntimeError, match="ams_torch_cuda::p2g"):
            emu["cuda_emu"].p2g(*args)
    finally:
        torch.use_deterministic_algorithms(before)


# -- the banded solve ---------------------------------------------------------------------------

@pytest.mark.parametrize("n", [1, 2, 4, 5, 33])
def test_banded_solve(emu, emu_env, n):
    """19 strands (one block) and 300 (several, with 128 threads at 1 SM), float64 and float32, the
    transposes' grid capped to one block."""
    ns = emu["cuda_emu"]
    for strands, env in ((19, {}), (300, {"sms": 1, "max_grid": 1})):
        emu_env(**env)
        for dtype, tol in ((F64, 1e-12), (F32, 1e-4)):
            blocks, rhs = strand_system(strands, n, dtype=dtype, seed=n)
            ref = solve_banded_dense(blocks.double(), rhs.double())
            x = ns.solve_banded(blocks, rhs)
            assert rel(x, ref) <= tol, (strands, n, dtype, rel(x, ref))


# -- the emulator itself (the same kernels run on the GPU in scripts/validate_cuda.py) ------------


@pytest.mark.parametrize("threads", [32, 50, 96])
def test_selftest_warp_collectives(emu, threads):
    """__activemask (converged and in divergent branches), ballot, shfl/up/down/xor (width 16),
    match_any, any/all, __syncwarp as a memory barrier, a partial last warp."""
    got = emu["selftest_cuda_emu"].warp_ops(torch.zeros(1), threads)
    assert torch.equal(got, expected_warp_ops(threads))


def test_selftest_shared_memory_and_atomics(emu, emu_env):
    ns = emu["selftest_cuda_emu"]
    x = torch.rand(5000, dtype=F64, generator=torch.Generator().manual_seed(0))
    assert abs(ns.block_sum(x, 3).item() - x.sum().item()) <= 1e-12 * x.sum().item()
    for workers in (1, 2):  # two host threads: the atomics race for real
        emu_env(workers=workers, order="shuffle")
        assert ns.atomics(torch.zeros(1), 7, 96).tolist() == [672.0, 336.0, 168.0]


@pytest.mark.parametrize("pattern", ["one_address", "few", "distinct", "strands"])
def test_selftest_warp_aggregated_add(emu, emu_env, pattern):
    """The warp-aggregated atomic add of common/ (P2G's): every pattern of shared addresses in a
    warp, a partial last warp, grid-stride tails."""
    emu_env(max_grid=2)
    n = 1000
    g = torch.Generator().manual_seed(1)
    index = {"one_address": torch.zeros(n, dtype=torch.int64),
             "few": torch.randint(0, 3, (n,), generator=g),
             "distinct": torch.randperm(n, generator=g),
             "strands": torch.arange(n) // 7}[pattern]
    values = torch.randn(n, dtype=F64, generator=g)
    size = int(index.max()) + 1
    got = emu["selftest_cuda_emu"].warp_add(values, index, size, 64, 1 << 20)
    want = torch.zeros(size, dtype=F64).index_add_(0, index, values)
    assert (got - want).abs().max().item() <= 1e-12 * values.abs().sum().item()


@pytest.mark.parametrize("grid,block,shared,match", [
    ((1, 1, 1), (1025, 1, 1), 0, r"block \(1025, 1, 1\)"),
    ((1, 1, 1), (32, 32, 2), 0, r"block \(32, 32, 2\)"),
    ((1, 1, 1), (1, 1, 65), 0, r"block \(1, 1, 65\)"),
    ((0, 1, 1), (32, 1, 1), 0, r"grid \(0, 1, 1\)"),
    ((1, 65536, 1), (32, 1, 1), 0, r"grid \(1, 65536, 1\)"),
    ((1, 1, 1), (32, 1, 1), 64 * 1024, "65536 bytes of dynamic shared memory"),
])
def test_selftest_launch_limits(emu, grid, block, shared, match):
    """The emulator refuses the launches a GPU refuses (the error comes back through
    cudaGetLastError(), as on a device), and runs the largest legal ones."""
    ns = emu["selftest_cuda_emu"]
    with pytest.raises(RuntimeError, match=match):
        ns.launch(torch.zeros(1), list(grid), list(block), shared)
    ns.launch(torch.zeros(1), [2, 1, 1], [1024, 1, 1], 48 * 1024)
    ns.launch(torch.zeros(1), [1, 2, 1], [32, 32, 1], 0)


@pytest.mark.parametrize("mode,match", [(1, "different __syncthreads"), (2, "after others exited"),
                                        (3, "exited or does not exist")])
def test_selftest_undefined_behaviour_is_reported(emu, mode, match):
    with pytest.raises(RuntimeError, match=match):
        emu["selftest_cuda_emu"].bad_barrier(torch.zeros(1), mode)
