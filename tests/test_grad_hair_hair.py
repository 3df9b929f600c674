"""The hair–hair stage in gradient frames of a native simulator (``recompute=True``): the native
forward (P2G, pressure, G2P kernels, no graph kept) and, in the backward pass, the native adjoint
kernels (``p2g_adjoint``, ``pressure_adjoint``, ``g2p_adjoint``; csrc/grid/grid_adjoint.h), or
where a library has none the torch definition's vector-Jacobian product recomputed.

* gradients with respect to x, v, the masses and the head pose equal the torch definition's
  (float64, pressure active, two scenes with their own poses, particles outside the grid), by
  either backward;
* each adjoint kernel equals autograd on its torch definition (float64 1e-12, float32 by its
  rounding), and the scattering one (G2P's) does not depend on the thread count;
* between the passes autograd keeps only the stage's inputs (no grid tensor).
"""
from __future__ import annotations

import pytest
import torch
from helpers import built_native, rel
from native_cases import squeeze_scene, sweeps_case

from ams_torch.geometry.pose import Pose
from ams_torch.stages.hair_hair import hair_hair_stage

F64 = torch.float64


@pytest.fixture(scope="module", autouse=True)
def cpu_lib():
    return built_native("cpu")


def _grads(case, recompute: bool):
    x = case["x"].detach().clone().requires_grad_()
    v = case["v"].detach().clone().requires_grad_()
    m = case["mass"].detach().clone().requires_grad_()
    p = case["pose"]
    t = p.translation.detach().clone().requires_grad_()
    ang = p.angular_velocity.detach().clone().requires_grad_()
    pose = Pose(p.rotation, t, p.linear_velocity, ang, check=False)
    saved = []

    def pack(u):
        saved.append(u.untyped_storage().nbytes())
        return u

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda u: u):
        x1, v1 = hair_hair_stage(case["grid"], x, v, m, pose, 1 / 60, case["free"], recompute=recompute)
    w = torch.linspace(-1.0, 1.0, x1.numel(), dtype=F64).reshape(x1.shape)
    loss = (w * x1).sum() + 0.3 * (w.flip(-1) * v1).sum()
    return torch.autograd.grad(loss, (x, v, m, t, ang)), sum(saved)


def test_recomputed_adjoint_equals_the_torch_definition():
    case = squeeze_scene(strands=120, particles=8, resolution=16, scenes=2)
    ref, ref_bytes = _grads(case, recompute=False)
    got, got_bytes = _grads(case, recompute=True)
    for name, a, b in zip(("x", "v", "mass", "translation", "angular velocity"), got, ref):
        assert float(b.abs().max()) > 0, name
        assert rel(a, b) <= 1e-10, (name, rel(a, b))
    inputs = sum(case[k].numel() * 8 for k in ("x", "v", "mass")) * 2  # x, v, m and their flattened copies
    assert got_bytes <= inputs + 64 * 1024, (got_bytes, inputs)  # the inputs (and the small frame), no grid
    assert ref_bytes > 4 * got_bytes  # the torch definition's graph keeps the grid


def test_pressure_sweeps_adjoint_equals_autograd(monkeypatch):
    """The pressure sweeps' written-out vector-Jacobian product (sparse._Sweeps) equals autograd
    through the plain loop: gradients of the face field with respect to the faces (mass and
    momentum), float64, pressure active, and keeps far less than autograd does."""
    from ams_torch.stages.hair_hair import sparse
    from native_cases import solve_args

    case = squeeze_scene(strands=120, particles=8, resolution=16, scenes=2)
    grid = case["grid"]
    stencils: list = []
    faces, table, blocks, count = sparse.p2g_sparse(case["xf"], case["vf"], case["m"], case["frame"], grid.origin,
                                                    grid.cell_size, grid.resolution, grid.capacity, stencils)
    faces = faces.detach()
    w = torch.randn(faces.shape[:2] + (3, 64), generator=torch.Generator().manual_seed(2), dtype=F64)

    def run():
        f = faces.clone().requires_grad_()
        saved = []
        with torch.autograd.graph.saved_tensors_hooks(lambda u: saved.append(u.untyped_storage().nbytes()) or u,
                                                      lambda u: u):
            phi, field, _ = sparse.pressure_sparse(f, table, blocks, count, grid.target_density, case["dt"],
                                                   grid.cell_size, grid.resolution, *solve_args(grid),
                                                   grid.active_capacity)
        assert float(phi.detach().abs().max()) > 0  # pressure active
        return torch.autograd.grad((w * field).sum(), f)[0], sum(saved)

    got, got_bytes = run()
    monkeypatch.setattr(sparse._Sweeps, "apply", lambda *a: sparse._sweeps(*a))
    ref, ref_bytes = run()
    assert float(ref.abs().max()) > 0
    assert rel(got, ref) <= 1e-12, rel(got, ref)
    assert got_bytes < ref_bytes / 3, (got_bytes, ref_bytes)


@pytest.mark.parametrize("dtype", [F64, torch.float32])
def test_native_sweeps_and_their_adjoint_equal_the_definition(dtype):
    """The native pressure sweeps (csrc/grid/sweeps.h) and their adjoint against the torch definition
    (sparse._sweeps, sparse._Sweeps.backward) on a pressure-active pool's cell list: float64 to 1e-12,
    float32 bounded by its rounding."""
    from ams_torch.native.dispatch import native_namespace
    from ams_torch.stages.hair_hair import sparse

    ns = native_namespace("grid", torch.zeros(1))
    src, coef, w, nbr, gout = sweeps_case(3001, 4, dtype)
    got = ns.sweeps(src, coef, w, nbr, 30, 0.6)
    want = sparse._sweeps(src, coef, w, nbr, 30, 0.6)
    tol = 1e-12 if dtype == F64 else 1e-5
    assert float(want.abs().max()) > 0 and rel(got, want) <= tol, rel(got, want)
    leaves = [t.clone().requires_grad_() for t in (src, coef, w)]
    ref = torch.autograd.grad(sparse._sweeps(leaves[0], leaves[1], leaves[2], nbr, 30, 0.6), leaves, gout)
    nat = ns.sweeps_adjoint(src, coef, w, nbr, 30, 0.6, gout)
    for name, a, b in zip(("src", "coef", "w"), nat, ref):
        a, b = a[..., :-1], b[..., :-1]  # the padding slot's adjoint is discarded by its callers
        assert float(b.abs().max()) > 0, name
        assert rel(a, b) <= tol, (name, rel(a, b))


def test_recomputed_adjoint_runs_the_native_sweeps(monkeypatch):
    """Without the native adjoint kernels (a library without them) the backward recomputes the torch
    definition, its sweeps differentiated natively; gradients equal the torch path's."""
    from ams_torch.stages.hair_hair import sparse, stage

    calls = []
    real = sparse._NativeSweeps.backward
    monkeypatch.setattr(sparse._NativeSweeps, "backward",
                        staticmethod(lambda ctx, g: calls.append(1) or real(ctx, g)))
    monkeypatch.setattr(stage, "native_adjoint_namespace", lambda x: None)
    case = squeeze_scene(strands=120, particles=8, resolution=16, scenes=2)
    got, _ = _grads(case, recompute=True)
    ref, _ = _grads(case, recompute=False)
    assert calls, "the native sweeps' adjoint did not run"
    for a, b in zip(got, ref):
        assert rel(a, b) <= 1e-10, rel(a, b)


def test_gradient_frame_runs_the_native_adjoint_kernels(monkeypatch):
    """With the native library built, the backward runs the three adjoint kernels once each and no
    torch recompute of the grid."""
    from ams_torch.stages.hair_hair import stage

    ns = stage.native_adjoint_namespace(torch.zeros(1, dtype=F64))
    assert ns is not None
    calls = []

    class Counting:
        def __getattr__(self, name):
            fn = getattr(ns, name)
            return lambda *a: calls.append(name) or fn(*a)

    monkeypatch.setattr(stage, "native_adjoint_namespace", lambda x: Counting())
    monkeypatch.setattr(stage, "_recomputed_adjoint", None)  # must not be called
    case = squeeze_scene(strands=120, particles=8, resolution=16, scenes=2)
    _grads(case, recompute=True)
    assert sorted(calls) == ["g2p_adjoint", "p2g", "p2g_adjoint", "pressure", "pressure_adjoint"], calls


def _head_frame_case(dtype, **config):
    """The squeeze scene's grid inputs in the head frame, its P2G pool (torch definition) and field
    (``config``: HairHair settings)."""
    from ams_torch.stages.hair_hair import sparse
    from ams_torch.stages.hair_hair.transfer import to_head
    from native_cases import solve_args

    case = squeeze_scene(dtype=dtype, strands=120, particles=8, resolution=16, scenes=2, **config)
    grid = case["grid"]
    xl, vl = to_head(case["frame"], case["xf"], case["vf"])
    b = xl.shape[0]
    ident = torch.zeros(b, 6, 3, dtype=dtype)
    ident[:, :3] = torch.eye(3, dtype=dtype)
    args = (grid.origin, grid.cell_size, grid.resolution, grid.capacity)
    faces, table, blocks, count = sparse.p2g_sparse(xl, vl, case["m"], ident, *args)
    solve = solve_args(grid)
    phi, field, over = sparse.pressure_sparse(faces, table, blocks, count, grid.target_density, case["dt"],
                                              grid.cell_size, grid.resolution, *solve)
    assert not bool(over.any())  # nothing left out
    if config.get("volume_stiffness", 1.0) > 0:
        assert float(phi.abs().max()) > 0  # pressure active
    return dict(case=case, grid=grid, xl=xl.contiguous(), vl=vl.contiguous(), faces=faces, table=table, blocks=blocks,
                count=count, field=field, solve=solve, ident=ident)


def _used(t, count):
    """The used slots of a per-slot pool tensor (B, K, ...), concatenated (the rest is never read)."""
    return torch.cat([t[b, :int(c)].reshape(-1) for b, c in enumerate(count)])


@pytest.mark.parametrize("dtype", [F64, torch.float32])
def test_native_grid_adjoints_equal_autograd_on_the_definition(dtype):
    """p2g_adjoint, pressure_adjoint and g2p_adjoint against autograd through sparse.py, on a
    pressure-active pool with particles half and fully outside the grid, two scenes."""
    from ams_torch.stages.hair_hair import sparse, stage
    from ams_torch.stages.hair_hair.transfer import interpolate_change

    ns = stage.native_adjoint_namespace(torch.zeros(1, dtype=dtype))
    d = _head_frame_case(dtype)
    grid, case = d["grid"], d["case"]
    h, r, k = grid.cell_size, grid.resolution, grid.capacity
    gen = torch.Generator().manual_seed(5)
    tol = 1e-12 if dtype == F64 else 2e-5
    # P2G
    leaves = [t.detach().clone().requires_grad_() for t in (d["xl"], d["vl"], case["m"])]
    faces, table, _, _ = sparse.p2g_sparse(*leaves, d["ident"], grid.origin, h, r, k)
    g_faces = torch.randn(faces.shape, generator=gen, dtype=dtype)
    ref = torch.autograd.grad(faces, leaves, g_faces)
    got = ns.p2g_adjoint(d["xl"], d["vl"], case["m"].contiguous(), grid.origin, table, g_faces, h, r)
    for name, a, b in zip(("xl", "vl", "m"), got, ref):
        assert float(b.abs().max()) > 0, name
        assert rel(a, b) <= tol, ("p2g", name, rel(a, b))
    # pressure
    f = d["faces"].detach().clone().requires_grad_()
    _, field, _ = sparse.pressure_sparse(f, d["table"], d["blocks"], d["count"], grid.target_density, case["dt"], h,
                                         r, *d["solve"])
    g_field = torch.randn(field.shape, generator=gen, dtype=dtype)
    ref, = torch.autograd.grad(field, f, g_field)
    got = ns.pressure_adjoint(d["faces"].detach(), d["table"], d["blocks"], d["count"], grid.target_density,
                              case["dt"], h, r, *d["solve"], g_field)
    for comp in (0, 1):  # mass, momentum
        a, b = _used(got[..., comp], d["count"]), _used(ref[..., comp], d["count"])
        assert float(b.abs().max()) > 0
        assert rel(a, b) <= tol * (10 if dtype == F64 else 50), ("pressure", comp, rel(a, b))
    # G2P (the head-frame change; the rotation back is the caller's)
    fl = d["field"].detach().clone().requires_grad_()
    xl, vl = (t.detach().clone().requires_grad_() for t in (d["xl"], d["vl"]))
    pic = d["solve"][3]
    dv = torch.stack([interpolate_change(sparse._with_sentinel(fl), *sparse.pool_stencil(xl, grid.origin, h, r, c,
                                                                                          d["table"], k),
                                         vl[..., c], pic, corner_dim=0) for c in range(3)], -1)
    g_dv = torch.randn(dv.shape, generator=gen, dtype=dtype)
    ref = torch.autograd.grad(dv, (xl, vl, fl), g_dv)
    got = ns.g2p_adjoint(d["xl"], d["vl"], d["field"].detach(), d["table"], grid.origin, g_dv, h, r, pic)
    for name, a, b in zip(("xl", "vl", "field"), got[:3], ref):
        assert float(b.abs().max()) > 0, name
        assert rel(a, b) <= tol, ("g2p", name, rel(a, b))
    assert rel(got[3], dv.detach()) <= tol


def test_pressure_adjoint_at_zero_stiffness():
    """volume_stiffness = 0: only compressing cells above the target push (b = -div), every other
    active cell's source is exactly 0 (its updates sit at the clamp's kink, where autograd passes the
    gradient; the kernel sweeps those slots too, though the source's derivative vanishes there);
    the native adjoint equals autograd."""
    from ams_torch.stages.hair_hair import sparse, stage

    d = _head_frame_case(F64, volume_stiffness=0.0)
    grid, case = d["grid"], d["case"]
    ns = stage.native_adjoint_namespace(d["xl"])
    f = d["faces"].detach().clone().requires_grad_()
    args = (d["table"], d["blocks"], d["count"], grid.target_density, case["dt"], grid.cell_size, grid.resolution,
            *d["solve"])
    _, field, _ = sparse.pressure_sparse(f, *args)
    g_field = torch.randn(field.shape, generator=torch.Generator().manual_seed(9), dtype=F64)
    ref, = torch.autograd.grad(field, f, g_field)
    got = ns.pressure_adjoint(d["faces"].detach(), *args, g_field)
    assert rel(_used(got[..., 0], d["count"]), _used(ref[..., 0], d["count"])) <= 1e-11


def test_g2p_adjoint_does_not_depend_on_the_thread_count():
    """The G2P adjoint's scatter into the field's adjoint sums every face in one order: 1 and 2
    threads give the same bits."""
    from ams_torch.stages.hair_hair import stage

    d = _head_frame_case(torch.float32)
    grid = d["grid"]
    ns = stage.native_adjoint_namespace(d["xl"])
    g_dv = torch.randn(d["xl"].shape, generator=torch.Generator().manual_seed(3))
    args = (d["xl"], d["vl"], d["field"], d["table"], grid.origin, g_dv, grid.cell_size, grid.resolution,
            d["solve"][3])
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = ns.g2p_adjoint(*args)
        torch.set_num_threads(2)
        two = ns.g2p_adjoint(*args)
    finally:
        torch.set_num_threads(threads)
    for a, b in zip(one, two):
        assert torch.equal(a, b)


def test_opcheck_of_the_grid_op():
    """``ams_torch::hair_hair_grid`` (the grid part as one differentiable op): torch.library.opcheck
    (schema, fake tensors, autograd registration) on a small pressure-active case, float64."""
    from native_cases import solve_args

    from ams_torch.stages.hair_hair.stage import grid_op

    case = squeeze_scene(strands=30, particles=6, resolution=8, scenes=2)
    grid = case["grid"]
    xf, vf, m = (case[k].detach().clone().requires_grad_() for k in ("xf", "vf", "m"))
    frame = case["frame"].detach().clone().requires_grad_()
    args = (xf, vf, m, frame, grid.origin, grid.target_density, case["dt"], case["free"], grid.cell_size,
            grid.resolution, grid.capacity, *solve_args(grid), grid.active_capacity)
    torch.library.opcheck(torch.ops.ams_torch.hair_hair_grid.default, args)
    x1, v1, _ = grid_op(*args)
    assert x1.requires_grad and v1.requires_grad
