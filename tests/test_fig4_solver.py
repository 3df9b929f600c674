"""The explicit-inverse block LU of ``scripts/fig4_solver_precision.py`` (the paper's two-sweep
solver, written for the Fig. 4 comparison in docs/stability_fig4.md): it is a correct solver, and
on a stiff float32 strand system its backward error is far above ours (the banded Cholesky)."""

import pytest
import torch
from helpers import load_script

from ams_torch.solver.reference import banded_matvec, banded_to_dense



@pytest.fixture(scope="module")
def fig4():
    return load_script("fig4_solver_precision")


def random_banded_spd(strands: int, n: int, dtype=torch.float64, seed: int = 0) -> torch.Tensor:
    """A well-conditioned SPD block-heptadiagonal band (strands, n, 4, 3, 3): random off-diagonal
    blocks, diagonal blocks made strictly diagonally dominant."""
    g = torch.Generator().manual_seed(seed)
    blocks = torch.randn(strands, n, 4, 3, 3, generator=g, dtype=torch.float64)
    for k in range(1, 4):
        blocks[:, :k, k] = 0.0  # outside the matrix
    d = blocks[:, :, 0]
    d = 0.5 * (d + d.transpose(-1, -2))
    row_sum = 2 * blocks[:, :, 1:].abs().sum((-3, -1)).amax(-1) + 3.0  # bound on each row's off-diagonal |.|
    blocks[:, :, 0] = d + torch.diag_embed(row_sum.unsqueeze(-1).expand(strands, n, 3) + 3.0)
    return blocks.to(dtype)


@pytest.mark.parametrize("inverse", ["adjugate", "linalg"])
def test_explicit_lu_solves_a_well_conditioned_system(fig4, inverse):
    blocks = random_banded_spd(3, 17)
    dense = banded_to_dense(blocks)
    assert float(torch.linalg.cond(dense).max()) < 1e3  # well conditioned
    x_true = torch.randn(3, 17, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    rhs = banded_matvec(blocks, x_true)
    x = fig4.block_lu_explicit(blocks, rhs, inverse=inverse)
    assert float((x - x_true).abs().max() / x_true.abs().max()) < 1e-10
    assert float(fig4.backward_error(blocks, rhs, x).max()) < 1e-14
    # the pivots it returns are those of the block LU: their product of determinants is det A
    _, piv = fig4.block_lu_explicit(blocks, rhs, inverse=inverse, return_pivots=True)
    logdet = torch.linalg.slogdet(piv)[1].sum(-1)
    assert torch.allclose(logdet, torch.linalg.slogdet(dense)[1], rtol=1e-10)


def test_explicit_lu_is_far_less_backward_stable_on_a_stiff_float32_strand(fig4):
    """The first frame's system of the Fig. 4 curly strand, plain MS at κ_L/m = 1e10, float32."""
    blocks, rhs = fig4.first_system("curly", 1e10, torch.float32)
    assert blocks.dtype == torch.float32
    assert float(fig4.condition_number(blocks).max()) > 1e6
    ours = float(fig4.backward_error(blocks, rhs, fig4.solve_cholesky(blocks, rhs)).max())
    lu = float(fig4.backward_error(blocks, rhs, fig4.block_lu_explicit(blocks, rhs)).max())
    eps = torch.finfo(torch.float32).eps
    assert ours < 2 * eps  # backward stable: a few units of rounding
    assert lu >= 10 * ours, (ours, lu)
