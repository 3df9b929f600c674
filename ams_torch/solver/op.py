"""The banded strand solve as one differentiable, compilable op with native kernels.

``solve_banded(blocks, rhs)`` solves, for every strand, the symmetric positive definite
block-heptadiagonal system of the implicit step (SPEC §4). It is the public entry point the
simulator calls; it validates, broadcasts and flattens the leading dims, and calls the
registered op ``torch.ops.ams_torch.solve_banded``:

* default implementation, every device: the plain-torch block Cholesky of ``solver.py``;
* CPU and CUDA: the native kernels (``csrc/banded``), built lazily on first use
  (``_native.py``); float32/float64 only, other dtypes and failed builds use the plain path;
* ``register_fake``: shape/dtype propagation for ``torch.compile`` / meta tensors;
* ``register_autograd``: the adjoint solve with the same op (below).

Gradient. The kernels read, for each row i: the whole block ``blocks[i, k]`` for 1 <= k <= i
(as A[i, i-k], and its transpose as A[i-k, i]); the lower triangle of the diagonal block
``blocks[i, 0]`` (as both triangles of A[i, i]); nothing else. With x = A⁻¹ b, an upstream
gradient g = ∂L/∂x and u = A⁻¹ g (A is symmetric, so the adjoint system is A itself):

    ∂L/∂rhs             = u
    ∂L/∂blocks[i, k]    = −(u_i x_{i−k}ᵀ + x_i u_{i−k}ᵀ)              1 <= k <= i
    ∂L/∂blocks[i, 0]_rc = −(u_r x_c + u_c x_r)  (r > c),  −u_r x_r  (r = c),  0  (r < c)
    ∂L/∂blocks[i, k]    = 0                                           k > i

i.e. the gradient of the dense −u xᵀ, summed over the two places each stored entry appears
in A. Entries that are never read get exactly zero, matching finite differences of the solve.
"""
from __future__ import annotations

import math

import torch

from ams_torch.native import build as _native
from ams_torch.native.dispatch import NATIVE_DTYPES
from ams_torch.solver.reference import BANDWIDTH, solve_banded_plain

__all__ = ["solve_banded", "solve_banded_op", "banded_solve_grad_blocks"]



def _validate(blocks: torch.Tensor, rhs: torch.Tensor) -> None:
    if blocks.dim() < 4 or tuple(blocks.shape[-3:]) != (BANDWIDTH + 1, 3, 3):
        raise ValueError(f"blocks must have shape (..., N, 4, 3, 3); got {tuple(blocks.shape)}")
    if rhs.dim() != blocks.dim() - 2 or rhs.shape[-1] != 3 or rhs.shape[:-1] != blocks.shape[:-3]:
        raise ValueError(
            f"rhs must have shape {tuple(blocks.shape[:-3]) + (3,)} to match blocks {tuple(blocks.shape)}; "
            f"got {tuple(rhs.shape)}"
        )
    if blocks.dtype != rhs.dtype or blocks.device != rhs.device:
        raise ValueError(
            f"blocks and rhs must share dtype and device; got {blocks.dtype}/{blocks.device} and "
            f"{rhs.dtype}/{rhs.device}"
        )


@torch.library.custom_op("ams_torch::solve_banded", mutates_args=())
def solve_banded_op(blocks: torch.Tensor, rhs: torch.Tensor) -> torch.Tensor:
    """Registered op ``ams_torch::solve_banded``; default (any device): the plain solver.

    blocks: (..., N, 4, 3, 3); rhs: (..., N, 3), same dtype and device. Returns a new
    contiguous x: (..., N, 3).
    """
    _validate(blocks, rhs)
    if rhs.numel() == 0:
        return rhs.new_empty(rhs.shape)
    return solve_banded_plain(blocks, rhs)


def _native_or_plain(get_op, blocks: torch.Tensor, rhs: torch.Tensor) -> torch.Tensor:
    _validate(blocks, rhs)
    if rhs.numel() == 0:
        return rhs.new_empty(rhs.shape)
    if rhs.dtype in NATIVE_DTYPES:
        op = get_op()
        if op is not None:
            return op(blocks, rhs)
    return solve_banded_plain(blocks, rhs)


@solve_banded_op.register_kernel("cpu")
def _solve_banded_cpu(blocks: torch.Tensor, rhs: torch.Tensor) -> torch.Tensor:
    return _native_or_plain(_native.cpu_op, blocks, rhs)


@solve_banded_op.register_kernel("cuda")
def _solve_banded_cuda(blocks: torch.Tensor, rhs: torch.Tensor) -> torch.Tensor:
    return _native_or_plain(_native.cuda_op, blocks, rhs)


@solve_banded_op.register_fake
def _solve_banded_fake(blocks: torch.Tensor, rhs: torch.Tensor) -> torch.Tensor:
    _validate(blocks, rhs)
    return rhs.new_empty(rhs.shape)


def banded_solve_grad_blocks(u: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Gradient with respect to ``blocks`` of a banded solve (see the module docstring).

    u: (..., N, 3) adjoint solution A⁻¹ (∂L/∂x); x: (..., N, 3) the solution.
    Returns (..., N, 4, 3, 3), zero on entries the solver never reads.
    """
    n = x.shape[-2]
    outer = -u.unsqueeze(-1) * x.unsqueeze(-2)  # −u_i x_iᵀ: (..., N, 3, 3)
    diag = torch.tril(outer + outer.mT) - torch.diag_embed(torch.diagonal(outer, dim1=-2, dim2=-1))
    out = [diag]
    for k in range(1, BANDWIDTH + 1):
        if k >= n:
            out.append(torch.zeros_like(outer))
            continue
        lo = -(u[..., k:, :].unsqueeze(-1) * x[..., :-k, :].unsqueeze(-2)
               + x[..., k:, :].unsqueeze(-1) * u[..., :-k, :].unsqueeze(-2))
        pad = outer.new_zeros(outer.shape[:-3] + (k, 3, 3))
        out.append(torch.cat((pad, lo), dim=-3))
    return torch.stack(out, dim=-3)


def _setup_context(ctx, inputs, output) -> None:
    blocks, _ = inputs
    ctx.save_for_backward(blocks, output)


def _backward(ctx, grad_x: torch.Tensor):
    blocks, x = ctx.saved_tensors
    u = solve_banded_op(blocks, grad_x.contiguous())  # adjoint solve: Aᵀ = A
    grad_blocks = banded_solve_grad_blocks(u, x) if ctx.needs_input_grad[0] else None
    grad_rhs = u if ctx.needs_input_grad[1] else None
    return grad_blocks, grad_rhs


solve_banded_op.register_autograd(_backward, setup_context=_setup_context)


def solve_banded(blocks: torch.Tensor, rhs: torch.Tensor, check: bool = True) -> torch.Tensor:
    """Solve the symmetric positive definite block-heptadiagonal strand systems ``A x = rhs``.

    Args:
        blocks: (..., N, 4, 3, 3) lower band of A, ``blocks[..., i, k] = A[i, i-k]`` (k = 0 the
            diagonal, of which only the lower triangle is read; entries with i − k < 0 are
            ignored). Units of the implicit-step matrix (kg).
        rhs: (..., N, 3) (kg·m/s for the velocity solve). Leading dims of ``blocks`` and
            ``rhs`` broadcast against each other; dtypes are promoted to a common one.
        check: raise ``torch.linalg.LinAlgError`` naming the first strand whose system is not
            SPD (a non-positive pivot), or holds NaN/Inf, instead of returning NaN for it. Costs
            one sum over x, rhs and A's diagonal, and one host synchronisation per call
            (measured in docs/benchmarks/solver.md); skipped inside ``torch.compile``; the simulator's hot path
            passes ``check=False`` and relies on its divergence guard.
    Returns:
        x: (..., N, 3) with the broadcast leading dims, e.g. velocities in m/s.

    Differentiable in both arguments (adjoint solve), traceable by ``torch.compile`` (with
    ``check=False``); runs the native CPU/CUDA kernel when it could be built (see
    ``ams_torch.native_status()``).
    """
    if blocks.dim() < 4 or tuple(blocks.shape[-3:]) != (BANDWIDTH + 1, 3, 3):
        raise ValueError(f"blocks must have shape (..., N, 4, 3, 3); got {tuple(blocks.shape)}")
    n = blocks.shape[-4]
    if rhs.dim() < 2 or tuple(rhs.shape[-2:]) != (n, 3):
        raise ValueError(f"rhs must have shape (..., {n}, 3) to match blocks {tuple(blocks.shape)}; "
                         f"got {tuple(rhs.shape)}")
    dtype = torch.promote_types(blocks.dtype, rhs.dtype)
    batch = torch.broadcast_shapes(blocks.shape[:-4], rhs.shape[:-2])
    strands = math.prod(batch)
    blocks = blocks.to(dtype).expand(batch + blocks.shape[-4:]).reshape(strands, n, BANDWIDTH + 1, 3, 3)
    rhs = rhs.to(dtype).expand(batch + rhs.shape[-2:]).reshape(strands, n, 3)
    x = solve_banded_op(blocks, rhs)
    if check and not torch.compiler.is_compiling():  # a host sync: never inside a compiled graph
        _check_solution(x, blocks, rhs, batch)
    return x.reshape(batch + (n, 3))


def _read_entries_finite(blocks: torch.Tensor) -> torch.Tensor:
    """(S,) bool: every entry the solver reads is finite.

    Read are the lower triangle of each diagonal block and the blocks ``[i, k]`` with i − k ≥ 0;
    the other entries are ignored by contract and may hold anything (NaN included).
    """
    s, n = blocks.shape[:2]
    i = torch.arange(n, device=blocks.device).view(n, 1)
    k = torch.arange(BANDWIDTH + 1, device=blocks.device).view(1, -1)
    read = (i - k >= 0).view(n, BANDWIDTH + 1, 1, 1).expand(n, BANDWIDTH + 1, 3, 3).clone()
    read[:, 0] &= torch.ones(3, 3, dtype=torch.bool, device=blocks.device).tril()
    return (torch.isfinite(blocks.detach()) | ~read).flatten(1).all(1)


def _all_read_finite(x: torch.Tensor, blocks: torch.Tensor, rhs: torch.Tensor) -> bool:
    """Whether the solve met no NaN/Inf: one sum of x, rhs and the scalar diagonal of A, one sync.

    A NaN anywhere the solver reads, or an Inf off the diagonal, reaches x through the factor
    (an Inf below the diagonal makes the next pivot sqrt(a − Inf²) = NaN), and a non-SPD matrix
    gives a NaN pivot; only a +Inf on A's diagonal can leave x finite (its row of the factor and
    its unknown become 0), so the diagonal is summed too. NaN and Inf propagate through the sum.
    """
    diag = blocks.detach()[:, :, 0].diagonal(dim1=-2, dim2=-1)
    total = x.detach().sum() + rhs.detach().sum() + diag.sum()
    return bool(torch.isfinite(total))


def _check_solution(x: torch.Tensor, blocks: torch.Tensor, rhs: torch.Tensor, batch) -> None:
    """Raise LinAlgError for the first strand whose solution is not finite, or whose system
    holds NaN/Inf in an entry the solver reads (an Inf on a diagonal can still give a finite,
    meaningless x). One pass of sums and one host sync when all is well; the per-strand
    diagnosis runs only on failure."""
    if _all_read_finite(x, blocks, rhs):
        return
    system_ok = _read_entries_finite(blocks) & torch.isfinite(rhs.detach()).flatten(1).all(1)
    good = torch.isfinite(x.detach()).flatten(1).all(1) & system_ok
    if bool(good.all()):  # the sum overflowed on large finite values: nothing is wrong
        return
    first = int(torch.nonzero(~good)[0])
    where = tuple(int(i) for i in torch.unravel_index(torch.tensor(first), tuple(batch))) if len(batch) else ()
    count = int((~good).sum())
    if not bool(system_ok[first]):
        why = "its blocks or right-hand side hold NaN/Inf"
    else:
        why = "its matrix is not symmetric positive definite (a non-positive pivot in the Cholesky factorisation)"
    raise torch.linalg.LinAlgError(f"solve_banded: strand {where or first} ({count} of {x.shape[0]} failing): {why}")
