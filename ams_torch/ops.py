"""The banded strand solve as one entry point (native kernels land here, see issue 3)."""
from __future__ import annotations

import torch

from .solver import solve_banded_plain

__all__ = ["solve_banded"]


def solve_banded(blocks: torch.Tensor, rhs: torch.Tensor) -> torch.Tensor:
    """Solve the symmetric block-heptadiagonal strand systems ``A x = rhs``.

    blocks: (..., N, 4, 3, 3), ``blocks[..., i, k] = A[i, i-k]`` (k = 0 diagonal; entries with
    i − k < 0 ignored); rhs: (..., N, 3). Returns x: (..., N, 3).
    """
    return solve_banded_plain(blocks, rhs)
