"""Property-based tests of the core's input validation and the banded solve.

* ``Pose``: any 3×3 matrix (random, perturbed rotations, reflections, NaN/Inf) is accepted
  exactly when it is a proper rotation within ``rotation_tolerance`` (decided here
  independently, in numpy float64), and otherwise rejected with a ``ValueError`` naming the
  field; wrong shapes name the field too; accepted poses map points there and back.
* ``solve_banded``: random SPD block-heptadiagonal systems (any N, batch shape, broadcasting,
  conditioning over 9 decades) match a dense float64 solve with a backward error near ε;
  negative-definite or non-finite systems raise ``LinAlgError`` naming the strand, never
  return NaN; malformed shapes raise ``ValueError``.

Profiles: ``fast`` (default, a few seconds) and ``slow``:
``HYPOTHESIS_PROFILE=slow pytest tests/test_core_property.py``.
"""
import os

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from ams_torch import Pose
from ams_torch.solver import solve_banded
from ams_torch.geometry.pose import axis_angle_to_matrix, rotation_tolerance
from ams_torch.solver.reference import banded_matvec, banded_to_dense

settings.register_profile("fast", max_examples=40, deadline=None, derandomize=True,
                          suppress_health_check=[HealthCheck.too_slow])
settings.register_profile("slow", max_examples=2000, deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "fast"))

batch_shapes = st.lists(st.integers(1, 3), min_size=0, max_size=2).map(tuple)
dtypes = st.sampled_from([torch.float32, torch.float64])


def _is_rotation(r: np.ndarray, tol: float) -> bool:
    """The acceptance rule, restated independently: every matrix finite, orthonormal and det +1."""
    if not np.isfinite(r).all():
        return False
    m = r.reshape(-1, 3, 3)
    ortho = np.abs(m @ m.transpose(0, 2, 1) - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(m)
    return bool(((ortho <= tol) & (np.abs(det - 1) <= tol)).all())


def _margin(r: np.ndarray, tol: float) -> float:
    """Distance of the worst matrix's criterion from the tolerance, relative (0 = on the edge)."""
    m = r.reshape(-1, 3, 3)
    ortho = np.abs(m @ m.transpose(0, 2, 1) - np.eye(3)).max(axis=(1, 2))
    det = np.abs(np.linalg.det(m) - 1)
    return float(np.min(np.abs(np.concatenate([ortho, det]) - tol)) / tol)


@st.composite
def matrices(draw):
    """(batch..., 3, 3) float64 arrays: rotations, perturbed rotations (±a few tolerances),
    reflections, scaled rotations, arbitrary matrices, and rotations with a NaN/Inf entry."""
    batch = draw(batch_shapes)
    count = int(np.prod(batch)) if batch else 1
    seed = draw(st.integers(0, 2**31 - 1))
    rng = np.random.default_rng(seed)
    rot = axis_angle_to_matrix(torch.as_tensor(rng.normal(size=(count, 3)) * draw(st.floats(0.0, 4.0)),
                                               dtype=torch.float64)).numpy()
    kind = draw(st.sampled_from(["rotation", "perturbed", "reflection", "scaled", "arbitrary", "nonfinite"]))
    if kind == "perturbed":
        rot = rot + rng.normal(size=rot.shape) * draw(st.floats(1e-9, 1e-1))
    elif kind == "reflection":
        rot[rng.integers(count)] *= -1.0
    elif kind == "scaled":
        rot[rng.integers(count)] *= draw(st.floats(0.5, 1.5))
    elif kind == "arbitrary":
        rot = rng.normal(size=rot.shape) * draw(st.floats(0.1, 10.0))
    elif kind == "nonfinite":
        rot.reshape(-1)[rng.integers(rot.size)] = draw(st.sampled_from([np.nan, np.inf, -np.inf]))
    return rot.reshape(batch + (3, 3))


@given(matrices(), dtypes)
def test_pose_accepts_exactly_the_proper_rotations(r, dtype):
    tol = rotation_tolerance(dtype)
    rt = torch.as_tensor(r, dtype=dtype)
    if np.isfinite(r).all():
        assume(_margin(rt.double().numpy(), tol) > 0.05)  # not on the edge, where rounding decides
    expected = _is_rotation(rt.double().numpy(), tol)
    t = torch.zeros(rt.shape[:-2] + (3,), dtype=dtype)
    try:
        pose = Pose(rt, t)
    except ValueError as err:
        assert not expected, f"a proper rotation was rejected: {err}"
        assert "Pose.rotation" in str(err), err
        assert ("NaN/Inf" in str(err)) == (not np.isfinite(r).all()), err
        return
    assert expected, "an improper or non-finite matrix was accepted as a rotation"
    assert pose.batch_shape == rt.shape[:-2]


@given(batch_shapes, st.sampled_from(["translation", "linear_velocity", "angular_velocity"]),
       st.lists(st.integers(1, 4), min_size=0, max_size=3).map(tuple), st.booleans())
def test_pose_field_shape_and_value_errors_name_the_field(batch, field, shape, nonfinite):
    r = torch.eye(3, dtype=torch.float64).expand(batch + (3, 3)).clone()
    good = torch.zeros(batch + (3,), dtype=torch.float64)
    fields = dict(translation=good, linear_velocity=good, angular_velocity=good)
    bad = torch.ones(shape + (3,), dtype=torch.float64)
    if nonfinite:
        bad = torch.ones(batch + (3,), dtype=torch.float64)
        bad.view(-1)[-1] = float("nan")
    elif shape == batch:
        return  # the right shape: nothing wrong with it
    fields[field] = bad
    with pytest.raises(ValueError, match=f"Pose.{field}"):
        Pose(r, **fields)


@given(st.integers(0, 2**31 - 1), batch_shapes, st.integers(1, 6))
def test_pose_maps_points_there_and_back(seed, batch, k):
    g = torch.Generator().manual_seed(seed)
    rotvec = torch.randn(batch + (3,), generator=g, dtype=torch.float64) * 3
    pose = Pose(axis_angle_to_matrix(rotvec), torch.randn(batch + (3,), generator=g, dtype=torch.float64),
                torch.randn(batch + (3,), generator=g, dtype=torch.float64),
                torch.randn(batch + (3,), generator=g, dtype=torch.float64))
    p = torch.randn(batch + (k, 3), generator=g, dtype=torch.float64)
    x = pose.to_world(p)
    torch.testing.assert_close(pose.to_local(x), p, rtol=0, atol=1e-12)
    torch.testing.assert_close(pose.unrotate(pose.rotate(p)), p, rtol=0, atol=1e-12)
    # distances are kept: a rigid map
    torch.testing.assert_close(torch.cdist(x, x), torch.cdist(p, p), rtol=0, atol=1e-11)


# --------------------------------------------------------------------------------------------
# solve_banded
def _random_band(g, batch, n, dtype, shift_sign=1.0, shift=1.0):
    """Random symmetric block-heptadiagonal blocks (batch..., n, 4, 3, 3) whose diagonal is
    shifted by ``shift_sign × (row sum of |off-diagonal| + shift)``: SPD for +1 and negative
    definite for −1 (Gershgorin), with a condition number growing as ``shift`` → 0."""
    blocks = torch.randn(batch + (n, 4, 3, 3), generator=g, dtype=torch.float64)
    for k in range(1, 4):
        blocks[..., :k, k, :, :] = 0.0  # entries above the matrix: ignored, zero for the dense copy
    d = blocks[..., 0, :, :]
    blocks[..., 0, :, :] = 0.5 * (d + d.transpose(-1, -2))
    dense = banded_to_dense(blocks)
    rows = dense.abs().sum(-1) - dense.diagonal(dim1=-2, dim2=-1).abs()
    diag = shift_sign * (rows + dense.diagonal(dim1=-2, dim2=-1).abs() + shift)
    eye = torch.eye(3, dtype=torch.float64)
    blocks[..., 0, :, :] = blocks[..., 0, :, :] * (1 - eye) + torch.diag_embed(diag.reshape(batch + (n, 3)))
    return blocks.to(dtype)


@given(st.integers(0, 2**31 - 1), batch_shapes, st.integers(1, 12), st.floats(-6.0, 3.0))
def test_solve_banded_matches_dense_solve_on_random_spd_systems(seed, batch, n, log_shift):
    g = torch.Generator().manual_seed(seed)
    blocks = _random_band(g, batch, n, torch.float64, shift=10.0 ** log_shift)
    rhs = torch.randn(batch + (n, 3), generator=g, dtype=torch.float64)
    x = solve_banded(blocks, rhs)
    a = banded_to_dense(blocks)
    ref = torch.linalg.solve(a, rhs.reshape(batch + (3 * n, 1))).reshape(rhs.shape)
    # backward error: the residual relative to |A| |x| is a few ε, however ill-conditioned A is
    res = (banded_matvec(blocks, x) - rhs).flatten(-2).norm(dim=-1)
    scale = torch.linalg.matrix_norm(a, ord=2) * x.flatten(-2).norm(dim=-1) + rhs.flatten(-2).norm(dim=-1)
    assert float((res / scale).max()) < 1e-13
    cond = float(torch.linalg.cond(a).max())
    err = float(((x - ref).flatten(-2).norm(dim=-1) / ref.flatten(-2).norm(dim=-1)).max())
    assert err < 1e-14 * cond + 1e-13, (err, cond)


@given(st.integers(0, 2**31 - 1), st.integers(1, 3), st.integers(1, 8), dtypes)
def test_solve_banded_broadcasts_blocks_against_many_right_hand_sides(seed, b, n, dtype):
    g = torch.Generator().manual_seed(seed)
    blocks = _random_band(g, (), n, dtype)
    rhs = torch.randn((b, n, 3), generator=g, dtype=torch.float64).to(dtype)
    x = solve_banded(blocks, rhs)
    assert x.shape == (b, n, 3) and x.dtype == dtype
    for i in range(b):
        torch.testing.assert_close(x[i], solve_banded(blocks, rhs[i]), rtol=0, atol=0)


@given(st.integers(0, 2**31 - 1), batch_shapes, st.integers(1, 8), dtypes,
       st.sampled_from(["indefinite", "nan", "inf", "-inf"]))
def test_solve_banded_raises_on_bad_systems_naming_the_strand(seed, batch, n, dtype, kind):
    g = torch.Generator().manual_seed(seed)
    blocks = _random_band(g, batch, n, torch.float64)
    rhs = torch.randn(batch + (n, 3), generator=g, dtype=torch.float64)
    count = int(np.prod(batch)) if batch else 1
    victim = int(torch.randint(count, (1,), generator=g))
    flat_b, flat_r = blocks.view(count, n, 4, 3, 3), rhs.view(count, n, 3)
    if kind == "indefinite":
        flat_b[victim] = _random_band(g, (), n, torch.float64, shift_sign=-1.0)
    else:
        value = float(kind)
        row = int(torch.randint(n, (1,), generator=g))
        if bool(torch.randint(2, (1,), generator=g)):  # any entry the solver reads
            k = int(torch.randint(min(row, 3) + 1, (1,), generator=g))  # A[row, row - k], row - k >= 0
            r = int(torch.randint(3, (1,), generator=g))
            c = int(torch.randint(r + 1 if k == 0 else 3, (1,), generator=g))  # lower triangle on the diagonal
            flat_b[victim, row, k, r, c] = value
        else:
            flat_r[victim, row, int(torch.randint(3, (1,), generator=g))] = value
    with pytest.raises(torch.linalg.LinAlgError) as err:
        solve_banded(blocks.to(dtype), rhs.to(dtype))
    where = tuple(int(i) for i in np.unravel_index(victim, batch)) if batch else victim
    assert f"strand {where}" in str(err.value), str(err.value)
    assert ("NaN/Inf" in str(err.value)) == (kind != "indefinite"), str(err.value)
    # without the check the other strands are untouched, and a NaN or indefinite strand comes
    # back non-finite (an Inf on a diagonal may give a finite x: why the check reads the input)
    x = solve_banded(blocks.to(dtype), rhs.to(dtype), check=False).view(count, n, 3)
    if kind not in ("inf", "-inf"):
        assert not bool(torch.isfinite(x[victim]).all())
    others = [i for i in range(count) if i != victim]
    assert bool(torch.isfinite(x[others]).all())


@given(st.lists(st.integers(0, 5), min_size=1, max_size=6).map(tuple), st.lists(st.integers(0, 5), min_size=1,
                                                                                  max_size=4).map(tuple))
def test_solve_banded_rejects_malformed_shapes_with_a_value_error(bshape, rshape):
    blocks, rhs = torch.zeros(bshape), torch.zeros(rshape)
    ok = len(bshape) >= 4 and bshape[-3:] == (4, 3, 3) and len(rshape) >= 2 and rshape[-2:] == (bshape[-4], 3)
    if ok:
        try:
            torch.broadcast_shapes(bshape[:-4], rshape[:-2])
        except RuntimeError:
            ok = False
    if ok:
        return  # well formed (and all zeros: singular); shapes are what this test is about
    with pytest.raises((ValueError, RuntimeError), match="shape|broadcast|size"):
        solve_banded(blocks, rhs)
