"""Plain-torch banded block-Cholesky solver for the per-strand AMS systems (SPEC §4).

Every strand's implicit step is a symmetric positive definite matrix made of 3×3 blocks
with 3 blocks on each side of the diagonal (edge, bending and torsion springs couple
particle i with i±1, i±2, i±3). It is stored compactly as

    blocks: (..., N, 4, 3, 3)   blocks[..., i, k, :, :] = A[i, i-k]  (k = 0 is the diagonal)

entries with i − k < 0 are ignored (never read). Only the lower band is stored; the
upper band is its transpose.

The factorisation is A = L Lᵀ with L block lower-triangular (same band). Each 3×3 pivot
block is factored by a closed-form Cholesky and applied by forward/backward substitution:
no 3×3 inverse is ever formed, which is what keeps the solve backward stable on the very
badly conditioned systems of stiff strands (SPEC §4).

This module is the reference ("plain") implementation: pure tensor ops, any device and
dtype, differentiable by autograd. It loops over the N particles of a strand in Python
(the sweeps are sequential) but is batched over every leading dimension.
"""
from __future__ import annotations

import torch

__all__ = ["solve_banded_plain", "solve_banded_dense", "banded_to_dense", "banded_matvec"]

BANDWIDTH = 3  # blocks on each side of the diagonal


def _check(blocks: torch.Tensor, rhs: torch.Tensor) -> None:
    if blocks.dim() < 4 or blocks.shape[-3:] != (BANDWIDTH + 1, 3, 3):
        raise ValueError(f"blocks must have shape (..., N, 4, 3, 3); got {tuple(blocks.shape)}")
    if rhs.shape[-1] != 3 or rhs.shape[:-1] != blocks.shape[:-3]:
        raise ValueError(
            f"rhs must have shape {tuple(blocks.shape[:-3]) + (3,)} to match blocks "
            f"{tuple(blocks.shape)}; got {tuple(rhs.shape)}"
        )


# ---------------------------------------------------------------------------------------
# 3×3 kernels, element-wise over any batch. Written out so that they vectorise across
# strands (torch's batched LAPACK calls on 3×3 matrices cost far more than the arithmetic).
# ---------------------------------------------------------------------------------------

def _chol3(a: torch.Tensor) -> torch.Tensor:
    """Lower Cholesky factor of symmetric positive definite 3×3 blocks.

    a: (..., 3, 3) symmetric; only the lower triangle is read. Returns L: (..., 3, 3).
    A non-positive pivot yields NaN (the simulator's divergence guard reports it).
    """
    l00 = torch.sqrt(a[..., 0, 0])
    l10 = a[..., 1, 0] / l00
    l20 = a[..., 2, 0] / l00
    l11 = torch.sqrt(a[..., 1, 1] - l10 * l10)
    l21 = (a[..., 2, 1] - l20 * l10) / l11
    l22 = torch.sqrt(a[..., 2, 2] - l20 * l20 - l21 * l21)
    z = torch.zeros_like(l00)
    return torch.stack(
        (torch.stack((l00, z, z), -1), torch.stack((l10, l11, z), -1), torch.stack((l20, l21, l22), -1)),
        -2,
    )


def _forward3(l: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Solve L y = b for lower-triangular 3×3 L. l: (..., 3, 3); b: (..., 3, K) → (..., 3, K)."""
    y0 = b[..., 0, :] / l[..., 0, 0, None]
    y1 = (b[..., 1, :] - l[..., 1, 0, None] * y0) / l[..., 1, 1, None]
    y2 = (b[..., 2, :] - l[..., 2, 0, None] * y0 - l[..., 2, 1, None] * y1) / l[..., 2, 2, None]
    return torch.stack((y0, y1, y2), -2)


def _backward3(l: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Solve Lᵀ x = y for lower-triangular 3×3 L. l: (..., 3, 3); y: (..., 3, K) → (..., 3, K)."""
    x2 = y[..., 2, :] / l[..., 2, 2, None]
    x1 = (y[..., 1, :] - l[..., 2, 1, None] * x2) / l[..., 1, 1, None]
    x0 = (y[..., 0, :] - l[..., 1, 0, None] * x1 - l[..., 2, 0, None] * x2) / l[..., 0, 0, None]
    return torch.stack((x0, x1, x2), -2)


def solve_banded_plain(blocks: torch.Tensor, rhs: torch.Tensor) -> torch.Tensor:
    """Solve A x = rhs for every strand by banded block Cholesky (plain torch reference).

    Args:
        blocks: (..., N, 4, 3, 3) lower band of the symmetric positive definite matrix,
            ``blocks[..., i, k] = A[i, i-k]``; entries with ``i-k < 0`` are ignored.
        rhs: (..., N, 3).
    Returns:
        x: (..., N, 3), same dtype and device as ``rhs``.
    """
    _check(blocks, rhs)
    n = blocks.shape[-4]
    # Factor: L[i, j] for j = i-3..i, kept as a list of per-row tuples (autograd-safe, no
    # in-place writes). Lrow[i][k] = L[i, i-k].
    lrow: list[list[torch.Tensor | None]] = []
    for i in range(n):
        row: list[torch.Tensor | None] = [None] * (BANDWIDTH + 1)
        for k in range(min(i, BANDWIDTH), 0, -1):  # columns j = i-k, left to right
            j = i - k
            c = blocks[..., i, k, :, :]
            # subtract sum over m < j in the band of both rows: L[i, m] L[j, m]^T
            for m in range(max(0, i - BANDWIDTH), j):
                lim = row[i - m]
                ljm = lrow[j][j - m]
                c = c - lim @ ljm.transpose(-1, -2)
            # L[i, j] L[j, j]^T = c  →  L[j, j] L[i, j]^T = c^T
            row[k] = _forward3(lrow[j][0], c.transpose(-1, -2)).transpose(-1, -2)
        d = blocks[..., i, 0, :, :]
        for k in range(1, min(i, BANDWIDTH) + 1):
            d = d - row[k] @ row[k].transpose(-1, -2)
        row[0] = _chol3(d)
        lrow.append(row)

    # Forward sweep: L z = rhs.
    z: list[torch.Tensor] = []
    for i in range(n):
        r = rhs[..., i, :].unsqueeze(-1)
        for k in range(1, min(i, BANDWIDTH) + 1):
            r = r - lrow[i][k] @ z[i - k]
        z.append(_forward3(lrow[i][0], r))
    # Backward sweep: Lᵀ x = z.
    x: list[torch.Tensor | None] = [None] * n
    for i in range(n - 1, -1, -1):
        r = z[i]
        for k in range(1, min(n - 1 - i, BANDWIDTH) + 1):
            r = r - lrow[i + k][k].transpose(-1, -2) @ x[i + k]
        x[i] = _backward3(lrow[i][0], r)
    return torch.stack([xi.squeeze(-1) for xi in x], -2)


def banded_to_dense(blocks: torch.Tensor) -> torch.Tensor:
    """Expand the lower band (..., N, 4, 3, 3) to the full symmetric matrix (..., 3N, 3N)."""
    n = blocks.shape[-4]
    batch = blocks.shape[:-4]
    dense = blocks.new_zeros(batch + (n, 3, n, 3))
    for k in range(BANDWIDTH + 1):
        for i in range(k, n):
            dense[..., i, :, i - k, :] = blocks[..., i, k, :, :]
            if k:
                dense[..., i - k, :, i, :] = blocks[..., i, k, :, :].transpose(-1, -2)
    return dense.reshape(batch + (3 * n, 3 * n))


def banded_matvec(blocks: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """y = A x for the banded symmetric matrix. blocks: (..., N, 4, 3, 3); x: (..., N, 3)."""
    _check(blocks, x)
    n = blocks.shape[-4]
    y = torch.einsum("...ij,...j->...i", blocks[..., 0, :, :], x)
    for k in range(1, BANDWIDTH + 1):
        if k >= n:
            break
        lower = blocks[..., k:, k, :, :]  # A[i, i-k] for i >= k
        # row i gets A[i,i-k] x[i-k]; row i-k gets A[i,i-k]^T x[i]
        add_lo = torch.einsum("...ij,...j->...i", lower, x[..., :-k, :])
        add_up = torch.einsum("...ji,...j->...i", lower, x[..., k:, :])
        pad = x.new_zeros(x.shape[:-2] + (k, 3))
        y = y + torch.cat((pad, add_lo), -2) + torch.cat((add_up, pad), -2)
    return y


def solve_banded_dense(blocks: torch.Tensor, rhs: torch.Tensor) -> torch.Tensor:
    """Dense reference: expand to (..., 3N, 3N) and call ``torch.linalg.solve`` (tests only)."""
    _check(blocks, rhs)
    a = banded_to_dense(blocks).contiguous()
    b = rhs.reshape(rhs.shape[:-2] + (-1, 1)).contiguous()  # explicit column: no vector/matrix ambiguity
    return torch.linalg.solve(a, b).reshape(rhs.shape)
