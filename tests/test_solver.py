"""Plain-torch banded block-Cholesky solver against the dense reference (SPEC §4)."""
import pytest
import torch

import ams_torch as at
from ams_torch.sim.assembly import assemble_system
from ams_torch.sim.model import coefficients
from ams_torch.solver.reference import banded_matvec, banded_to_dense, solve_banded_dense, solve_banded_plain


def random_spd_blocks(strands, n, dtype, seed=0, device="cpu"):
    """Random SPD block-heptadiagonal systems: A = L Lᵀ from a random banded L."""
    g = torch.Generator().manual_seed(seed)
    lo = torch.randn(strands, n, 4, 3, 3, generator=g, dtype=torch.float64) * 0.3
    lo[:, :, 0] = torch.tril(lo[:, :, 0]) + 2.0 * torch.eye(3, dtype=torch.float64)
    ld = banded_to_dense_lower(lo)
    a = (ld @ ld.transpose(-1, -2)).reshape(strands, n, 3, n, 3)
    blocks = torch.zeros(strands, n, 4, 3, 3, dtype=torch.float64)
    for k in range(4):
        for i in range(k, n):
            blocks[:, i, k] = a[:, i, :, i - k, :]
    return blocks.to(device=device, dtype=dtype)


def banded_to_dense_lower(lo):
    s, n = lo.shape[:2]
    d = torch.zeros(s, n, 3, n, 3, dtype=lo.dtype)
    for k in range(4):
        for i in range(k, n):
            d[:, i, :, i - k, :] = lo[:, i, k]
    return d.reshape(s, 3 * n, 3 * n)


@pytest.mark.parametrize("n", [4, 5, 7, 32, 256])
@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-10), (torch.float32, 1e-4)])
def test_plain_matches_dense(n, dtype, tol, device):
    strands = 3 if n == 256 else 16
    blocks = random_spd_blocks(strands, n, dtype, seed=n, device=device)
    rhs = torch.randn(strands, n, 3, dtype=dtype, device=device)
    x = solve_banded_plain(blocks, rhs)
    ref = solve_banded_dense(blocks.double(), rhs.double())
    rel = (x.double() - ref).norm() / ref.norm()
    assert rel <= tol, f"N={n} {dtype}: relative error {rel:.3g} > {tol}"
    assert at.solver.solve_banded(blocks, rhs).shape == rhs.shape


def test_entries_above_the_band_start_are_ignored():
    blocks = random_spd_blocks(2, 6, torch.float64)
    rhs = torch.randn(2, 6, 3, dtype=torch.float64)
    junk = blocks.clone()
    for i in range(3):
        junk[:, i, i + 1:] = 1e30  # A[i, i-k] with i-k < 0 does not exist
    assert torch.equal(solve_banded_plain(junk, rhs), solve_banded_plain(blocks, rhs))


def test_leading_batch_dims_and_matvec():
    blocks = random_spd_blocks(6, 9, torch.float64).reshape(2, 3, 9, 4, 3, 3)
    rhs = torch.randn(2, 3, 9, 3, dtype=torch.float64)
    x = solve_banded_plain(blocks, rhs)
    assert x.shape == rhs.shape
    torch.testing.assert_close(banded_matvec(blocks, x), rhs, rtol=1e-12, atol=1e-12)


def stiff_strand_system(strands=8, n=32, seed=0):
    """A real AMS strand matrix with κ_L = 1e8 N/m and 1e-6 kg particles at Δt' = 1/60 s
    (condition number near 1e11), around a randomly perturbed wavy strand."""
    g = torch.Generator().manual_seed(seed)
    s = torch.linspace(0, 0.3, n, dtype=torch.float64)
    rest = torch.stack((s, 0.01 * torch.sin(40 * s), 0.01 * torch.cos(30 * s)), -1).expand(strands, n, 3)
    params = at.Params(material="per_particle", stretch_stiffness=1e8, particle_mass=1e-6, num_pinned=0, sag_free=False)
    sim = at.Simulator(rest, params, dtype=torch.float64)
    x = rest + 1e-3 * torch.randn(strands, n, 3, generator=g, dtype=torch.float64)
    v = torch.randn(strands, n, 3, generator=g, dtype=torch.float64)
    blocks, rhs = assemble_system(sim.model, coefficients(sim.model), sim.config, x, v, x, torch.zeros_like(x),
                                  torch.zeros_like(x), 1 / 60)
    return blocks, rhs


def test_backward_stable_on_stiff_strands():
    blocks, rhs = stiff_strand_system()
    a = banded_to_dense(blocks)
    cond = torch.linalg.cond(a).max()
    assert cond > 1e9, f"test system should be badly conditioned, cond = {cond:.3g}"
    x = solve_banded_plain(blocks, rhs)
    r = (banded_matvec(blocks, x) - rhs).flatten(1).norm(dim=1)
    berr = r / (torch.linalg.matrix_norm(a, ord=2) * x.flatten(1).norm(dim=1))
    assert berr.max() <= 1e-14, f"normwise backward error {berr.max():.3g} (cond {cond:.3g})"


def test_gradient_through_plain_solver():
    blocks = random_spd_blocks(2, 5, torch.float64).requires_grad_()
    rhs = torch.randn(2, 5, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda b, r: solve_banded_plain(b, r), (blocks, rhs))


def test_bad_shapes_raise():
    with pytest.raises(ValueError, match="blocks"):
        solve_banded_plain(torch.zeros(2, 5, 3, 3, 3), torch.zeros(2, 5, 3))
    with pytest.raises(ValueError, match="rhs"):
        solve_banded_plain(torch.zeros(2, 5, 4, 3, 3), torch.zeros(2, 4, 3))


def test_check_passes_large_finite_values_whose_sum_overflows():
    """The default check sums x, rhs and the read entries of the blocks (one pass, one sync); when
    that sum overflows on large but finite values, the strand-by-strand diagnosis finds nothing
    wrong and no error is raised; a NaN among them is still found and named."""
    from ams_torch.solver.op import _check_solution

    blocks, rhs = stiff_strand_system(strands=6, n=8)  # float64
    x = at.solver.solve_banded(blocks, rhs)
    x[:, :, 0] = 1e308  # finite, but their sum is not
    assert torch.isfinite(x).all() and not torch.isfinite(x.sum())
    _check_solution(x, blocks, rhs, torch.Size([6]))  # must not raise
    bad = blocks.clone()
    bad[4, 3, 1, 0, 0] = float("nan")
    with pytest.raises(torch.linalg.LinAlgError, match=r"strand \(4,\) \(1 of 6 failing\): its blocks"):
        _check_solution(x, bad, rhs, torch.Size([6]))
