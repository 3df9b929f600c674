"""Derivatives of the force terms where their directions vanish (float64, against central differences).

At the rest state every segment lies along its ghost segment (θ = 0) and every particle on its
anchor (elongation 0): the angular spring ``κ θ t̂`` and the non-Hookean law ``κ L φ(e) d̂`` are
smooth there, but their normalised directions are zeroed, and so were their autograd derivatives
(a rollout's gradient with respect to x₀ was half the finite differences'). The forward values
are unchanged (checked bit for bit)."""
import torch

from ams_torch.sim import forces

F64 = torch.float64


def _jacobians(fn, x):
    jac = torch.autograd.functional.jacobian(fn, x)
    h = 1e-7
    cols = []
    for k in range(x.numel()):
        e = torch.zeros(x.numel(), dtype=F64)
        e[k] = h
        e = e.reshape(x.shape)
        cols.append(((fn(x + e) - fn(x - e)) / (2 * h)).reshape(-1))
    return jac.reshape(-1, x.numel()), torch.stack(cols, -1)


def test_angular_force_derivative_at_alignment():
    g = torch.Generator().manual_seed(0)
    x = torch.cumsum(torch.rand(1, 5, 3, generator=g, dtype=F64), 1)
    ghost = 2.0 * x + torch.tensor([0.1, -0.2, 0.3], dtype=F64)  # every ghost segment ∥ its segment
    kappa = torch.rand(1, 4, generator=g, dtype=F64) + 0.5
    for reaction in (True, False):
        f0, _ = forces.angular_force(x, ghost, kappa, reaction)
        assert float(f0.abs().max()) == 0.0  # aligned: no force (the forward value is exact)
        jac, fd = _jacobians(lambda p: forces.angular_force(p, ghost, kappa, reaction)[0], x)
        assert float(fd.abs().max()) > 0.1
        torch.testing.assert_close(jac, fd, rtol=1e-6, atol=1e-7)
    # away from alignment the term's derivative is unchanged
    y = ghost + 1e-2 * torch.rand(ghost.shape, generator=g, dtype=F64)
    jac, fd = _jacobians(lambda p: forces.angular_force(p, y, kappa)[0], x)
    torch.testing.assert_close(jac, fd, rtol=1e-6, atol=1e-7)


def test_nonhookean_integrity_derivative_at_the_anchor():
    g = torch.Generator().manual_seed(1)
    x = torch.rand(2, 4, 3, generator=g, dtype=F64)
    preload = 1e-3 * torch.rand(2, 4, 3, generator=g, dtype=F64)
    kappa = torch.rand(2, 4, generator=g, dtype=F64) + 1.0
    seg = torch.full((2, 4), 0.01, dtype=F64)

    def force(p):
        return forces.integrity_force_nonhookean(p, x, preload, kappa, seg, 0.5, 1.0, 0.25)[0]

    torch.testing.assert_close(force(x), preload, rtol=0, atol=0)
    jac, fd = _jacobians(force, x)
    torch.testing.assert_close(jac, fd, rtol=1e-6, atol=1e-7)
    torch.testing.assert_close(jac, -torch.diag(kappa.repeat_interleave(3, -1).reshape(-1)), rtol=1e-12, atol=0)
