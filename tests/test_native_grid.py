"""Native hair–hair grid kernels (SPEC §6) on the block-sparse grid: the dense torch definition vs
the sparse torch path vs native CPU vs CUDA, per stage and for the whole stage; the capacity and
its overflow flag; edge cases; op registration; backend selection and fallback.

The native CPU kernels are built once per session (``cpu_ops`` fixture in conftest; cached across runs in
``~/.cache/ams_torch`` or ``$AMS_TORCH_CACHE``); CUDA cases run only where a GPU is visible.

Tolerances (max |native − torch| / max |torch| per quantity):
* float64: 1e-10 (measured ≤ 1e-15 per stage, ≤ 1e-13 for whole-stage positions whose change
  x' − x is small next to x).
* float32: ``F32_REL = 8 · R · ε₃₂`` (2.3e-5 at R = 24; measured ≤ 7e-7 per stage, 3e-6 on
  velocities after the stage). Both paths compute trilinear weights from grid coordinates
  g = (x − origin)/h of magnitude up to R, so one rounding of g moves a weight by up to
  R · ε₃₂ (ε₃₂ = 2⁻²³ ≈ 1.2e-7), and fused multiply-adds in the kernels round differently from
  torch's separate ops; every later quantity is a weighted sum or a contraction (ω < 1) of
  those. Positions x' are compared with an extra absolute ``4 ulp(max |x|)``: both paths store
  x' = x + Δx rounded to the precision of x (measured: 1 ulp). With detailed collisions, which
  run on that rounded x', a contact normal turns by ~ulp(x)/radius, hence the whole-stage
  velocity bound ``max(F32_REL, 8 ε₃₂ max|x| / collision_radius)`` (measured 1.6e-5).
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch
from helpers import DEVICES
from native_cases import DT, F64_REL, MASS, solve_args, squeeze_scene, tol
from torch.utils._python_dispatch import TorchDispatchMode

from ams_torch.geometry.pose import Pose
from ams_torch.native import build as _native
from ams_torch.stages.hair_hair import HairHair, hair_hair_stage
from ams_torch.stages.hair_hair.native import g2p_op, p2g_op, pressure_op
from ams_torch.testing import head_groom, two_wisps
from ams_torch.stages.hair_hair.pressure import pressure_torch
from ams_torch.stages.hair_hair.sparse import (active_cells, blocks_per_axis, densify, g2p_sparse, p2g_sparse,
                                              pressure_sparse)
from ams_torch.stages.hair_hair.transfer import cell_mass, face_views, g2p_torch, p2g_torch, scene_frame


REPO = Path(__file__).resolve().parents[1]
DTYPES = [torch.float64, torch.float32]


def _namespace(device: str):
    if device == "cpu":
        return _native.native_ops("cpu")
    ns = _native.native_ops("cuda")
    st = _native.native_status()["cuda"]
    if ns is None and st["reason"].startswith("no CUDA toolkit"):
        pytest.skip(st["reason"])
    assert ns is not None, f"native CUDA grid kernels failed to build: {st['reason']}"
    return ns


# -- helpers -------------------------------------------------------------------------------


def rel(a: torch.Tensor, ref: torch.Tensor) -> float:
    scale = ref.abs().max()
    return float((a - ref).abs().max() / scale) if scale > 0 else float((a - ref).abs().max())


def _check_positions(x_new, x_ref, x_in, dtype, r):
    ulp = 4 * torch.finfo(dtype).eps * float(x_in.abs().max())
    err = float((x_new - x_ref).abs().max())
    assert err <= ulp + tol(dtype, r) * float((x_ref - x_in).abs().max()), err


def dense_faces(s):
    grid = s["grid"]
    return p2g_torch(s["xf"], s["vf"], s["m"], s["frame"], grid.origin, grid.cell_size, grid.resolution)


def dense_stage(s):
    """The grid part of the stage by the dense definition (transfer.py, pressure.py): x', v' (B, P, 3)."""
    grid = s["grid"]
    h, r = grid.cell_size, grid.resolution
    _, field = pressure_torch(dense_faces(s), grid.target_density, s["dt"], h, r, *solve_args(grid))
    return g2p_torch(s["xf"], s["vf"], field, s["frame"], grid.origin, s["free"], s["dt"], h, r, 1 - grid.config.flip)


def sparse_pool(s):
    """(faces, table, blocks, count) of the scene by the sparse torch path."""
    grid = s["grid"]
    return p2g_sparse(s["xf"], s["vf"], s["m"], s["frame"], grid.origin, grid.cell_size, grid.resolution,
                      grid.capacity)


# -- the sparse torch path is the dense definition -------------------------------------------
@pytest.mark.parametrize("resolution", [8, 24, 31])
def test_sparse_torch_path_equals_the_dense_definition(resolution):
    """float64, per stage and for the whole stage, with pressure active, particles outside and
    half outside, and R not a multiple of the block size (31): the values of the dense grid."""
    s = squeeze_scene(torch.float64, "cpu", resolution=resolution)
    grid = s["grid"]
    h, r = grid.cell_size, grid.resolution
    faces, table, blocks, count = sparse_pool(s)
    assert grid.capacity <= blocks_per_axis(r) ** 3 and bool((count <= grid.capacity).all())
    assert int(count.max()) * 64 < 0.6 * r ** 3 or r < 16  # the pool holds the hair, not the box
    ref = dense_faces(s)
    assert rel(densify(faces, blocks, r), ref) <= 1e-14
    phi_d, field_d = pressure_torch(ref, grid.target_density, s["dt"], h, r, *solve_args(grid))
    phi_s, field_s, over = pressure_sparse(faces, table, blocks, count, grid.target_density, s["dt"], h, r,
                                           *solve_args(grid), grid.active_capacity)
    assert not bool(over.any())
    assert int((phi_d > 0).sum()) > 5
    assert rel(densify(phi_s, blocks, r), phi_d) <= 1e-14
    assert rel(densify(field_s, blocks, r), field_d) <= 1e-14
    x_d, v_d = dense_stage(s)
    x_s, v_s = hair_hair_stage(grid, s["x"], s["v"], s["mass"], s["pose"], DT, s["free"], backend="torch")
    assert rel(v_s.reshape(v_d.shape) - s["vf"], v_d - s["vf"]) <= 1e-13
    _check_positions(x_s.reshape(x_d.shape), x_d, s["xf"], torch.float64, r)


# -- per-stage parity ------------------------------------------------------------------------
@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", DTYPES)
def test_p2g_parity(cpu_ops, device, dtype):
    ns = _namespace(device)
    s = squeeze_scene(dtype, device)
    grid = s["grid"]
    r, k = grid.resolution, grid.capacity
    args = (s["xf"], s["vf"], s["m"], s["frame"], grid.origin, grid.cell_size, r, k)
    faces_t, table_t, blocks_t, count_t = p2g_sparse(*args)
    faces, table, blocks, count = ns.p2g(*args)
    assert faces.shape == (2, k, 3, 64, 2) and table.shape == (2, blocks_per_axis(r) ** 3)
    assert table.dtype == blocks.dtype == count.dtype == torch.int32
    assert torch.equal(count, count_t)
    if device == "cpu":  # slots in block order, as the torch path; CUDA hands them out in any order
        assert torch.equal(table, table_t) and torch.equal(blocks, blocks_t)
    used = blocks >= 0
    assert torch.equal(used.sum(1), count.long()) and torch.equal(torch.sort(blocks, 1)[0], torch.sort(blocks_t, 1)[0])
    dense = densify(faces, blocks, r)
    ref = dense_faces(s)
    assert rel(dense[..., 0], ref[..., 0]) <= tol(dtype, r)
    assert rel(dense[..., 1], ref[..., 1]) <= tol(dtype, r)
    # the particles fully outside the grid are not on it: total mass = mass of the others
    inside = s["m"].sum(1) - s["mass"][:, :5, -1].sum(1)
    assert torch.allclose(dense[..., 0].sum((1, 2)) / 3, inside, rtol=0.02)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", DTYPES)
def test_pressure_parity_dense_squeeze(cpu_ops, device, dtype):
    ns = _namespace(device)
    s = squeeze_scene(dtype, device)
    grid = s["grid"]
    h, r = grid.cell_size, grid.resolution
    faces, table, blocks, count = sparse_pool(s)
    ref = dense_faces(s)
    rho = cell_mass(face_views(ref[..., 0], r)) / h ** 3
    assert float(rho.max()) > 1.2 * float(grid.target_density)  # the squeeze is above the target
    phi_t, field_t = pressure_torch(ref, grid.target_density, s["dt"], h, r, *solve_args(grid))
    phi_n, field_n, *_ = ns.pressure(faces, table, blocks, count, grid.target_density, s["dt"], h, r,
                                     *solve_args(grid), grid.active_capacity)
    assert int((phi_t > 0).sum()) > 20  # pressure active in many cells, in both scenes
    assert bool((phi_t.flatten(1).amax(1) > 0).all())
    assert rel(densify(phi_n, blocks, r), phi_t) <= tol(dtype, r)
    assert rel(densify(field_n, blocks, r), field_t) <= tol(dtype, r)
    # an odd number of sweeps returns the other buffer
    phi_t3, _ = pressure_torch(ref, grid.target_density, s["dt"], h, r, 3, 0.6, 1.0, 0.05)
    phi_n3, *_ = ns.pressure(faces, table, blocks, count, grid.target_density, s["dt"], h, r, 3, 0.6, 1.0, 0.05,
                             grid.active_capacity)
    assert rel(densify(phi_n3, blocks, r), phi_t3) <= tol(dtype, r)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", DTYPES)
def test_g2p_parity(cpu_ops, device, dtype):
    ns = _namespace(device)
    s = squeeze_scene(dtype, device)
    grid = s["grid"]
    h, r = grid.cell_size, grid.resolution
    faces, table, blocks, count = sparse_pool(s)
    _, field, *_ = pressure_sparse(faces, table, blocks, count, grid.target_density, s["dt"], h, r,
                                   *solve_args(grid))
    args = (s["xf"], s["vf"], field, table, s["frame"], grid.origin, s["free"], s["dt"], h, r, 0.05)
    x_t, v_t = g2p_sparse(*args)
    x_n, v_n = ns.g2p(*args)
    assert rel(v_n - s["vf"], v_t - s["vf"]) <= tol(dtype, r)
    _check_positions(x_n, x_t, s["xf"], dtype, r)
    x_d, v_d = g2p_torch(s["xf"], s["vf"], densify(field, blocks, r), s["frame"], grid.origin, s["free"], s["dt"], h,
                         r, 0.05)
    assert rel(v_n - s["vf"], v_d - s["vf"]) <= tol(dtype, r)
    pinned = (torch.arange(s["xf"].shape[1], device=device) % s["free"].shape[0]) < 2
    assert torch.equal(x_n[:, pinned], s["xf"][:, pinned]) and torch.equal(v_n[:, pinned], s["vf"][:, pinned])
    far = torch.zeros(200, 10, dtype=torch.bool, device=device)
    far[:5, -1] = True  # outside the grid: no weight, velocity kept
    far = far.reshape(-1)
    assert torch.equal(v_n[:, far], s["vf"][:, far]) and torch.equal(v_t[:, far], s["vf"][:, far])


def test_sweeps_visit_only_what_phi_can_reach_with_the_full_sweeps_values(cpu_ops):
    """Two wisps far apart: one squeezed (pushing cells), one at rest (active cells that never
    push). The CPU kernel sweeps only the slots φ can reach; φ everywhere, including the resting
    wisp's active cells (0), is what sweeping every cell gives (the torch path), in float64."""
    rest = two_wisps(strands=48, n=8, width=0.03, gap=0.2, seed=3)
    x = rest.clone()
    x[:48] = x[:48] * torch.tensor([0.5, 1.0, 0.5], dtype=torch.float64) + torch.tensor([-0.05, 0, 0],
                                                                                         dtype=torch.float64)
    grid = HairHair(resolution=32).build(rest, MASS)
    h, r = grid.cell_size, grid.resolution
    v = 0.05 * torch.randn(x.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    b, p = 1, x.shape[0] * x.shape[1]
    xf, vf, m = x.reshape(1, p, 3), v.reshape(1, p, 3), torch.full((1, p), MASS, dtype=torch.float64)
    frame = scene_frame(None, (), b, torch.float64, "cpu")
    dt = torch.full((), DT, dtype=torch.float64)
    faces, table, blocks, count = p2g_sparse(xf, vf, m, frame, grid.origin, h, r, grid.capacity)
    args = (grid.target_density, dt, h, r, 50, 0.6, 1.0, 0.05)
    phi_t, field_t, *_ = pressure_sparse(faces, table, blocks, count, *args)
    phi_n, field_n, *_ = cpu_ops.pressure(faces, table, blocks, count, *args, grid.active_capacity)
    used = blocks[0] >= 0
    assert torch.equal(phi_n[0, used] > 0, phi_t[0, used] > 0)
    assert rel(phi_n[0, used], phi_t[0, used]) <= 1e-13 and rel(field_n[0, used], field_t[0, used]) <= 1e-13
    # the resting wisp has active cells, out of φ's reach: they keep φ = 0
    dense = densify(faces, blocks, r)[..., 0]
    has = face_views(dense > float(grid.target_density) * 1e-6 * h ** 3, r)
    active = has[0][:, 1:] & has[0][:, :-1] & has[1][:, :, 1:] & has[1][:, :, :-1] & has[2][..., 1:] & has[2][..., :-1]
    phi_dense = densify(phi_n, blocks, r)
    right = torch.zeros_like(active)
    right[:, r // 2 + 2:] = True
    assert int((active & right).sum()) > 5 and bool((phi_dense[active & right] == 0).all())
    assert int((phi_dense > 0).sum()) > 5


# -- whole stage -----------------------------------------------------------------------------
@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("detailed", [False, True])
def test_stage_parity(cpu_ops, device, dtype, detailed):
    _namespace(device)
    s = squeeze_scene(dtype, device, strands=120, detailed_collisions=detailed, collision_radius=3e-3)
    grid = s["grid"]
    out = {b: hair_hair_stage(grid, s["x"], s["v"], s["mass"], s["pose"], DT, s["free"], backend=b)
           for b in ("torch", "native")}
    (x_t, v_t), (x_n, v_n) = out["torch"], out["native"]
    assert x_n.shape == s["x"].shape and v_n.dtype == dtype
    bound = tol(dtype, grid.resolution)
    if detailed and dtype == torch.float32:
        # contacts see x' rounded to float32 by each path: a normal turns by ~ulp(x)/radius
        bound = max(bound, 8 * torch.finfo(dtype).eps * float(s["x"].abs().max()) / grid.config.collision_radius)
    assert rel(v_n - s["v"], v_t - s["v"]) <= bound
    if not detailed:  # and against the dense definition
        x_d, v_d = dense_stage(s)
        assert rel(v_n.reshape(v_d.shape) - s["vf"], v_d - s["vf"]) <= bound
    per_strand = s["free"].expand(120, -1).clone()  # a (S, N) mask, here with one more pinned strand
    per_strand[3] = False
    x_s, v_s = hair_hair_stage(grid, s["x"], s["v"], s["mass"], s["pose"], DT, per_strand, backend="native")
    x_r, v_r = hair_hair_stage(grid, s["x"], s["v"], s["mass"], s["pose"], DT, per_strand, backend="torch")
    assert torch.equal(x_s[:, 3], s["x"][:, 3]) and torch.equal(v_s[:, 3], s["v"][:, 3])
    assert rel(v_s - s["v"], v_r - s["v"]) <= bound
    _check_positions(x_n, x_t, s["x"], dtype, grid.resolution)
    assert float((v_t - s["v"]).abs().max()) > 1e-2  # the stage did change velocities


@pytest.mark.parametrize("device", DEVICES)
def test_leading_scene_dims(cpu_ops, device):
    _namespace(device)
    s = squeeze_scene(torch.float64, device, strands=60, scenes=6)
    x, v, m = (t.reshape(2, 3, *t.shape[1:]) for t in (s["x"], s["v"], s["mass"]))
    pose = Pose(*(t.reshape(2, 3, *t.shape[1:]) for t in (s["pose"].rotation, s["pose"].translation,
                                                          s["pose"].linear_velocity, s["pose"].angular_velocity)))
    x_n, v_n = hair_hair_stage(s["grid"], x, v, m, pose, DT, s["free"], backend="native")
    x_t, v_t = hair_hair_stage(s["grid"], s["x"], s["v"], s["mass"], s["pose"], DT, s["free"], backend="torch")
    assert x_n.shape == (2, 3, 60, 10, 3)
    assert rel(v_n.reshape(v_t.shape), v_t) <= F64_REL
    assert rel(x_n.reshape(x_t.shape), x_t) <= F64_REL


# -- capacity --------------------------------------------------------------------------------
@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("backend", ["torch", "native"])
def test_capacity_overflow_is_flagged_never_silent(cpu_ops, device, backend):
    """A pool one block short of the hair: the flag is set (on the device) and the count says how
    many blocks the hair needed; a pool that just fits gives the whole-grid result exactly."""
    _namespace(device)
    s = squeeze_scene(torch.float64, device, strands=80, outside=False)
    needed = int(sparse_pool(s)[3].max())
    rest_args = (s["x"], s["v"], s["mass"], s["pose"], DT, s["free"])
    results = {}
    for k in (needed - 1, needed, blocks_per_axis(24) ** 3):
        grid = HairHair(resolution=24, max_blocks=k).build(head_groom(80, 10, dtype=torch.float64), MASS)
        grid = grid.to(device=device, dtype=torch.float64)
        assert grid.capacity == k
        results[k] = hair_hair_stage(grid, *rest_args, backend=backend, with_overflow=True)
        assert results[k][2].dtype == torch.bool and results[k][2].shape == ()
    assert bool(results[needed - 1][2]) and not bool(results[needed][2])
    assert not bool(results[blocks_per_axis(24) ** 3][2])
    x_fit, v_fit, _ = results[needed]
    x_all, v_all, _ = results[blocks_per_axis(24) ** 3]
    assert rel(v_fit - s["v"], v_all - s["v"]) <= 1e-14 and rel(x_fit, x_all) <= 1e-15
    grid = HairHair(resolution=24, max_blocks=needed - 1).build(head_groom(80, 10, dtype=torch.float64), MASS)
    count = p2g_op(s["xf"], s["vf"], s["m"], s["frame"], grid.origin.to(device), grid.cell_size, 24, grid.capacity,
                   False)[3]
    assert int(count.max()) == needed


@pytest.mark.parametrize("device", DEVICES)
def test_active_cell_capacity(cpu_ops, device):
    """The torch path sweeps a list of the active cells (a static capacity, so its cost is not the
    pool's): with room for exactly the active cells it gives the values of sweeping every cell;
    one short, both paths flag the overflow (the kernels count the same active cells)."""
    ns = _namespace(device)
    s = squeeze_scene(torch.float64, device)
    grid = s["grid"]
    h, r = grid.cell_size, grid.resolution
    faces, table, blocks, count = sparse_pool(s)
    args = (grid.target_density, s["dt"], h, r, *solve_args(grid))
    active = active_cells(faces, table, blocks, grid.target_density, h, r)
    need = int(active.max())
    assert int(active.min()) > 20
    phi_all, field_all, over = pressure_sparse(faces, table, blocks, count, *args)
    phi_fit, field_fit, over_fit = pressure_sparse(faces, table, blocks, count, *args, need)
    assert torch.equal(phi_fit, phi_all) and torch.equal(field_fit, field_all)
    assert not bool(over.any()) and not bool(over_fit.any())
    phi_short, *_ = pressure_sparse(faces, table, blocks, count, *args, need // 2)
    assert not torch.equal(phi_short, phi_all)  # cells were left out
    for cap in (need, need - 1):
        expect = active > cap
        assert torch.equal(pressure_sparse(faces, table, blocks, count, *args, cap)[2].cpu(), expect.cpu())
        assert torch.equal(ns.pressure(faces, table, blocks, count, *args, cap)[2].cpu(), expect.cpu())
    for backend in ("torch", "native"):
        tight = HairHair(resolution=24, max_active_cells=need - 1).build(head_groom(200, 10, dtype=torch.float64),
                                                                         MASS).to(device)
        assert tight.active_capacity == need - 1
        flags = [hair_hair_stage(g, s["x"], s["v"], s["mass"], s["pose"], DT, s["free"], backend=backend,
                                 with_overflow=True)[2] for g in (tight, grid)]
        assert bool(flags[0]) and not bool(flags[1]), backend


def test_pool_follows_the_hair_not_the_box():
    """The issue's 160 × 12 case: the blocks the rest groom occupies grow less than R³ (R³: × 8
    per doubling; sparse hair: at most 8 blocks per particle whatever R), and the automatic pool
    (4 × those blocks) holds a fraction of the R³ cells at R = 128."""
    rest = head_groom(160, 12, dtype=torch.float32)
    xf = rest.reshape(1, -1, 3)
    occupied = {}
    for r in (32, 64, 128):
        grid = HairHair(resolution=r).build(rest, MASS)
        whole = blocks_per_axis(r) ** 3
        occupied[r] = int(p2g_sparse(xf, torch.zeros_like(xf), torch.full(xf.shape[:2], MASS), scene_frame(
            None, (), 1, torch.float32, "cpu"), grid.origin, grid.cell_size, r, whole)[3])
        assert grid.capacity == min(whole, max(64, 4 * occupied[r]))
        assert occupied[r] <= 8 * xf.shape[1]
    assert occupied[128] < 5 * occupied[64] < 25 * occupied[32]  # measured 1062, 261, 79
    assert grid.capacity * 64 < 0.15 * 128 ** 3


# -- edge cases ------------------------------------------------------------------------------
@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", DTYPES)
def test_no_cell_above_target_gives_exactly_zero_phi(cpu_ops, device, dtype):
    """A groom at its rest shape (target = 1.1 × its peak density): φ is exactly 0 on both paths
    (the native kernels skip the sweeps), so the field is the PIC share alone."""
    ns = _namespace(device)
    s = squeeze_scene(dtype, device, squeeze=1.0, jitter=0.0, outside=False, seed=1)
    grid = s["grid"]
    h, r = grid.cell_size, grid.resolution
    faces, table, blocks, count = sparse_pool(s)
    ref = dense_faces(s)
    rho = cell_mass(face_views(ref[..., 0], r)) / h ** 3
    assert 0.5 * float(grid.target_density) < float(rho.max()) < float(grid.target_density)
    phi_t, field_t = pressure_torch(ref, grid.target_density, s["dt"], h, r, *solve_args(grid))
    phi_n, field_n, *_ = ns.pressure(faces, table, blocks, count, grid.target_density, s["dt"], h, r,
                                     *solve_args(grid), grid.active_capacity)
    phi_n, field_n = densify(phi_n, blocks, r), densify(field_n, blocks, r)
    assert bool((phi_t == 0).all()) and bool((phi_n == 0).all())
    vel = torch.where(ref[..., 0] > 0, ref[..., 1] / ref[..., 0].clamp_min(1e-300), torch.zeros_like(ref[..., 0]))
    assert rel(field_n, 0.05 * vel) <= tol(dtype, r)
    assert rel(field_n, field_t) <= tol(dtype, r)


@pytest.mark.parametrize("device", DEVICES)
def test_empty_grid(cpu_ops, device):
    """Every particle outside the grid: no block is used, and (x, v) come back unchanged."""
    ns = _namespace(device)
    s = squeeze_scene(torch.float64, device, strands=30, outside=False)
    grid = s["grid"]
    xf = s["xf"] + 10.0 * grid.extent
    h, r = grid.cell_size, grid.resolution
    faces, table, blocks, count = ns.p2g(xf, s["vf"], s["m"], s["frame"], grid.origin, h, r, grid.capacity)
    assert bool((count == 0).all()) and bool((table == -1).all()) and bool((blocks == -1).all())
    phi, field, *_ = ns.pressure(faces, table, blocks, count, grid.target_density, s["dt"], h, r, *solve_args(grid),
                                 grid.active_capacity)
    x1, v1 = ns.g2p(xf, s["vf"], field, table, s["frame"], grid.origin, s["free"], s["dt"], h, r, 0.05)
    assert torch.equal(x1, xf) and torch.equal(v1, s["vf"])
    for backend in ("torch", "native"):
        x2, v2 = hair_hair_stage(grid, xf.reshape(s["x"].shape), s["v"], s["mass"], s["pose"], DT, s["free"],
                                 backend=backend)
        assert torch.equal(x2, xf.reshape(s["x"].shape)) and torch.equal(v2, s["v"])


def test_native_results_do_not_depend_on_the_thread_count(cpu_ops):
    s = squeeze_scene(torch.float32, "cpu", strands=400, resolution=32, scenes=1)
    grid = s["grid"]
    args = (s["xf"], s["vf"], s["m"], s["frame"], grid.origin, grid.cell_size, grid.resolution, grid.capacity)
    before = torch.get_num_threads()
    try:
        outs = []
        for threads in (1, 2, 1):
            torch.set_num_threads(threads)
            faces, table, blocks, count = cpu_ops.p2g(*args)
            used = int(count[0])
            phi, field, _ = cpu_ops.pressure(faces, table, blocks, count, grid.target_density, s["dt"], grid.cell_size,
                                            grid.resolution, *solve_args(grid), grid.active_capacity)
            outs.append((faces[:, :used], table, phi[:, :used], field[:, :used]))
    finally:
        torch.set_num_threads(before)
    assert int((outs[0][2] > 0).sum()) > 10
    for a, b in ((outs[0], outs[1]), (outs[0], outs[2])):
        assert all(torch.equal(u, w) for u, w in zip(a, b))


# -- registration ----------------------------------------------------------------------------
@pytest.mark.parametrize("device", DEVICES)
def test_opcheck(cpu_ops, device):
    """The three ops against their fakes and schemas. The capacity is the blocks the scene uses
    (slots beyond them are unspecified: the kernels leave them unwritten)."""
    _namespace(device)
    for dtype in DTYPES:
        s = squeeze_scene(dtype, device, strands=20, resolution=8, scenes=2)
        grid = s["grid"]
        h, r = grid.cell_size, grid.resolution
        used = int(sparse_pool(s)[3].min())
        p2g_args = (s["xf"][:1], s["vf"][:1], s["m"][:1], s["frame"][:1], grid.origin, h, r, used, False)
        torch.library.opcheck(p2g_op, p2g_args)
        faces, table, blocks, count = p2g_op(*p2g_args)
        pr_args = (faces, table, blocks, count, grid.target_density, s["dt"], h, r, 4, 0.6, 1.0, 0.05, 64, False)
        torch.library.opcheck(pressure_op, pr_args)
        _, field, _ = pressure_op(*pr_args)
        torch.library.opcheck(g2p_op, (s["xf"][:1], s["vf"][:1], field, table, s["frame"][:1], grid.origin, s["free"],
                                       s["dt"], h, r, 0.05, False))


class _Record(TorchDispatchMode):
    def __init__(self):
        super().__init__()
        self.ops = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.ops.append(str(func))
        return func(*args, **(kwargs or {}))


def test_backend_selection(cpu_ops):
    s = squeeze_scene(torch.float64, "cpu", strands=20, resolution=8)
    call = lambda x, v, backend, grid=s["grid"]: hair_hair_stage(grid, x, v, s["mass"], s["pose"], DT,  # noqa: E731
                                                                 s["free"], backend=backend)
    ours = lambda rec: [o for o in rec.ops if "hair_hair" in o or "ams_torch_cpu" in o]  # noqa: E731
    with _Record() as rec:
        call(s["x"], s["v"], "auto")
    # eager: the native kernels directly (the registered ops wrap them for torch.compile)
    assert [o for o in rec.ops if "ams_torch_cpu" in o] == ["ams_torch_cpu.p2g.default",
                                                       "ams_torch_cpu.pressure.default",
                                                       "ams_torch_cpu.g2p.default"]
    v = s["v"].clone().requires_grad_(True)
    for backend in ("auto", "torch"):
        with _Record() as rec:
            out = call(s["x"], v, backend)
        assert ours(rec) == [] and out[1].requires_grad  # the differentiable torch definition
    with torch.no_grad(), _Record() as rec:
        call(s["x"], v, "auto")
    assert len(ours(rec)) == 3
    with pytest.raises(ValueError, match="no gradient"):
        call(s["x"], v, "native")
    with pytest.raises(ValueError, match="backend"):
        call(s["x"], s["v"], "fast")
    half = s["grid"].to(torch.bfloat16)
    with _Record() as rec:
        xb, vb = call(s["x"].bfloat16(), s["v"].bfloat16(), "auto", half)
    assert ours(rec) == [] and vb.dtype == torch.bfloat16
    with pytest.raises(ValueError, match="float32 or float64"):
        call(s["x"].bfloat16(), s["v"].bfloat16(), "native", half)


_FALLBACK_SCRIPT = textwrap.dedent(
    """
    import json, sys, warnings
    sys.path.insert(0, {tests!r})
    import torch
    from native_cases import squeeze_scene
    from ams_torch.stages.hair_hair import hair_hair_stage
    s = squeeze_scene(torch.float32, "cpu", strands=30, resolution=8)
    run = lambda b: hair_hair_stage(s["grid"], s["x"], s["v"], s["mass"], s["pose"], 1 / 60, s["free"], backend=b)
    with warnings.catch_warnings(record=True):
        warnings.simplefilter("always")
        same = all(torch.equal(a, b) for a, b in zip(run("auto"), run("torch")))
        try:
            run("native")
            error = None
        except RuntimeError as e:
            error = str(e)
    print(json.dumps(dict(same=same, error=error)))
    """
)


def test_disabled_native_falls_back_to_torch(tmp_path):
    """AMS_TORCH_NATIVE=0: 'auto' gives the torch path bit for bit; 'native' says why it cannot."""
    env = dict(os.environ, AMS_TORCH_NATIVE="0", AMS_TORCH_CACHE=str(tmp_path / "cache"), PYTHONPATH=str(REPO))
    script = _FALLBACK_SCRIPT.format(tests=str(REPO / "tests"))
    proc = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["same"]
    assert out["error"] and "AMS_TORCH_NATIVE" in out["error"]
    assert not (tmp_path / "cache").exists() or not any((tmp_path / "cache").iterdir())


@pytest.mark.slow
def test_issue_case_at_128_equals_the_dense_definition(cpu_ops):
    """The issue's 160 × 12 groom at R = 128 (float64, squeezed, moving head): the sparse torch
    path and the native kernels give the dense definition's velocities."""
    s = squeeze_scene(torch.float64, "cpu", strands=160, particles=12, resolution=128, scenes=1, outside=False)
    x_d, v_d = dense_stage(s)
    for backend in ("torch", "native"):
        x_s, v_s = hair_hair_stage(s["grid"], s["x"], s["v"], s["mass"], s["pose"], DT, s["free"], backend=backend)
        assert rel(v_s.reshape(v_d.shape) - s["vf"], v_d - s["vf"]) <= 1e-12, backend
        _check_positions(x_s.reshape(x_d.shape), x_d, s["xf"], torch.float64, 128)
