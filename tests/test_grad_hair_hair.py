"""The hair–hair stage in gradient frames of a native simulator (``recompute=True``): the native
forward (P2G, pressure, G2P kernels, no graph kept) and the torch definition's vector-Jacobian
product recomputed in the backward pass.

* gradients with respect to x, v, the masses and the head pose equal the torch definition's
  (float64, pressure active, two scenes with their own poses, particles outside the grid);
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
    """In a native gradient frame the grid's recomputed adjoint differentiates the sweeps natively."""
    from ams_torch.stages.hair_hair import sparse

    calls = []
    real = sparse._NativeSweeps.backward
    monkeypatch.setattr(sparse._NativeSweeps, "backward",
                        staticmethod(lambda ctx, g: calls.append(1) or real(ctx, g)))
    case = squeeze_scene(strands=120, particles=8, resolution=16, scenes=2)
    got, _ = _grads(case, recompute=True)
    ref, _ = _grads(case, recompute=False)
    assert calls, "the native sweeps' adjoint did not run"
    for a, b in zip(got, ref):
        assert rel(a, b) <= 1e-10, rel(a, b)
