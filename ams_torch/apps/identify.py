"""Parameter identification through whole rollouts: fit material fields to captured motion.

A captured motion is the positions of a groom at fixed material points (rest arc-length
fractions, :func:`at_material_points`) after every frame. A simulator whose
material fields are ``nn.Parameter`` s (``Simulator(..., learnable=...)``) is fitted to it by
gradient descent on the mean squared distance at those points over every frame; the gradient
comes back through every frame (the step, the sag-free initial state, the non-Hookean yield) of a
checkpointed rollout (:func:`ams_torch.sim.rollout`, ``checkpoint_every`` frames per recomputed
segment: memory O(frames / k + k)).

Positive fields are optimised through their logarithm (:class:`Log`) and the non-Hookean
transition as a share of the breaking point (:class:`Fraction`), with
``torch.nn.utils.parametrize`` on the simulator's own parameters (``sim.model.drag`` *is*
``exp(z)``), so the optimiser works on unconstrained values z. Fields may be numbers (one value
for the groom) or per strand: ``Params(drag=torch.full((S, 1), 1.5))`` learnable gives an
(S, 1) parameter, one value per strand.

    sim = fit_simulator(rest, Params(drag=3.0), {"drag": Log()})
    check = fd_check(sim, poses, target)          # autograd against central differences
    hist = fit(sim, poses, target, iterations=30, optimizer="lbfgs")

``scripts/identify.py`` runs the cases of ``docs/identification.md`` with these functions.
"""
from __future__ import annotations

import time
from typing import Callable, Dict, Optional, Sequence

import torch
from torch.nn.utils import parametrize

from ams_torch.sim.params import Params
from ams_torch.sim.rollout import rollout
from ams_torch.sim.simulator import Simulator

__all__ = ["at_material_points", "Log", "Fraction", "fit_simulator", "unconstrained", "values", "set_values",
           "trajectory", "rollout_loss", "loss_mm2", "loss_and_grad", "loss_at", "make_target", "fd_check", "fit", "POINTS"]

F64 = torch.float64


def at_material_points(rest: torch.Tensor, x: torch.Tensor, points: int = 33) -> torch.Tensor:
    """Positions of x at fixed material points: the rest arc-length fractions k / (points − 1).

    rest: (S, N, 3) m, the rest shape that defines arc length; x: (..., S, N, 3) m, a simulated
    state of that groom. Each material point is interpolated linearly along the simulated
    polyline between the two particles whose rest arc lengths bracket it, so grooms of
    different N can be compared point for point (errors in N are measured this way, not by
    particle index). Returns (..., S, points, 3) m.
    """
    seg = (rest[:, 1:] - rest[:, :-1]).norm(dim=-1)
    arc = torch.nn.functional.pad(seg.cumsum(-1), (1, 0))
    arc = arc / arc[:, -1:]
    u = torch.linspace(0, 1, points, dtype=rest.dtype, device=rest.device).expand(rest.shape[0], points).contiguous()
    idx = torch.searchsorted(arc.contiguous(), u).clamp(1, rest.shape[1] - 1)  # (S, points)
    a0, a1 = arc.gather(1, idx - 1), arc.gather(1, idx)
    t = ((u - a0) / (a1 - a0)).clamp(0, 1)[..., None]
    lead = x.shape[:-3]
    gather = lambda i: torch.gather(x, -2, i[..., None].expand(lead + i.shape + (3,)))  # noqa: E731
    x0, x1 = gather(idx - 1), gather(idx)
    return x0 + t.to(x.dtype) * (x1 - x0)
POINTS = 33  # material points per strand


# ------------------------------------------------------------------------ parametrisations
class Log(torch.nn.Module):
    """value = exp(z): a positive field optimised through its logarithm (steps are relative)."""

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        return torch.exp(z)

    def right_inverse(self, value: torch.Tensor) -> torch.Tensor:
        return torch.log(value)


class Fraction(torch.nn.Module):
    """value = upper · sigmoid(z) ∈ (0, upper): e.g. the non-Hookean transition below its breaking
    point (Params requires 0 < transition < break; the optimiser cannot leave that range)."""

    def __init__(self, upper: float):
        super().__init__()
        self.upper = float(upper)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        return self.upper * torch.sigmoid(z)

    def right_inverse(self, value: torch.Tensor) -> torch.Tensor:
        return torch.logit(value / self.upper)


def fit_simulator(rest: torch.Tensor, params: Params, fields: Dict[str, torch.nn.Module], *,
                  dtype: torch.dtype = F64, backend: str = "torch", **simulator_kwargs) -> Simulator:
    """A simulator whose material ``fields`` are learnable and parametrised.

    rest: (S, N, 3) m; fields: {Params field: its parametrisation (:class:`Log`, :class:`Fraction`)};
    the field's value in ``params`` (a number, or an (S, 1) / (S, N) tensor for per-strand /
    per-particle values) is the start. ``sim.parameters()`` are then the unconstrained values z and
    ``sim.model.<field>`` the constrained value computed from z at every access. ``backend="torch"``
    (the default here) keeps the forward and the backward pass on the same arithmetic;
    ``simulator_kwargs`` go to :class:`~ams_torch.Simulator` (colliders, hair_hair, ...)."""
    sim = Simulator(rest, params, dtype=dtype, learnable=tuple(fields), backend=backend, **simulator_kwargs)
    for name, transform in fields.items():
        parametrize.register_parametrization(sim.model, name, transform)
    return sim


def unconstrained(sim: Simulator) -> Dict[str, torch.nn.Parameter]:
    """{field: its unconstrained nn.Parameter z} of a :func:`fit_simulator`."""
    return {name: sim.model.parametrizations[name].original for name in sim.model.learnable}


def _number(t: torch.Tensor):
    """A float for a one-value tensor, else a (nested) list."""
    t = t.detach()
    return float(t) if t.numel() == 1 else t.cpu().tolist()


def values(sim: Simulator) -> Dict[str, object]:
    """{field: current constrained value} of a :func:`fit_simulator` (a float, or a list per strand)."""
    with torch.no_grad():
        return {name: _number(getattr(sim.model, name)) for name in sim.model.learnable}


def set_values(sim: Simulator, new: Dict[str, object]) -> None:
    """Set constrained values (through each parametrisation's inverse)."""
    with torch.no_grad():
        for name, v in new.items():
            old = getattr(sim.model, name)
            setattr(sim.model, name, torch.as_tensor(v, dtype=old.dtype, device=old.device).expand(old.shape).clone())


# ------------------------------------------------------------------------ rollouts and loss
def trajectory(sim: Simulator, poses: Sequence, *, checkpoint_every: int = 1, points: int = POINTS,
               state=None) -> torch.Tensor:
    """Positions at ``points`` material points per strand after every frame: (F, ..., S, points, 3) m,
    from ``state`` (default ``sim.initial_state()``), one frame per head pose, checkpointed every
    ``checkpoint_every`` frames (0: a plain rollout). The divergence guard is read once, at the end."""
    rest = sim.model.rest_positions
    state = sim.initial_state() if state is None else state
    out = rollout(sim, state, poses, checkpoint_every=checkpoint_every,
                  observe=lambda s: at_material_points(rest, s.x, points))
    return torch.stack(out.outputs)


def loss_mm2(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean squared distance (mm²) over frames, strands and material points."""
    return ((pred - target) ** 2).sum(-1).mean() * 1e6


def rollout_loss(sim: Simulator, poses: Sequence, target: torch.Tensor, *, checkpoint_every: int = 1,
                 state=None) -> torch.Tensor:
    """:func:`loss_mm2` of the rollout against ``target`` (F, ..., S, P, 3) m, summed frame by frame
    inside the rollout (no frame's positions are kept): a () tensor, mm²."""
    rest = sim.model.rest_positions
    points = target.shape[-2]
    scale = 1e6 / (target[0].numel() // 3 * target.shape[0])

    def add(acc, k, s):
        return acc + ((at_material_points(rest, s.x, points) - target[k]) ** 2).sum() * scale

    state = sim.initial_state() if state is None else state
    return rollout(sim, state, poses, checkpoint_every=checkpoint_every, reduce=add,
                   initial=torch.zeros((), dtype=target.dtype, device=target.device)).value


def loss_and_grad(sim: Simulator, poses, target, checkpoint_every: int = 1) -> tuple:
    """(loss mm², {field: dloss/dz}) at the current values (gradients as floats, or lists per strand)."""
    zs = unconstrained(sim)
    loss = rollout_loss(sim, poses, target, checkpoint_every=checkpoint_every)
    grads = torch.autograd.grad(loss, list(zs.values()))
    return float(loss.detach()), {k: _number(g) for k, g in zip(zs, grads)}


def loss_at(sim: Simulator, poses, target) -> float:
    """The loss (mm²) at the current values, forward only."""
    with torch.no_grad():
        return float(rollout_loss(sim, poses, target, checkpoint_every=0))


def make_target(rest: torch.Tensor, params: Params, poses: Sequence, *, points: int = POINTS,
                dtype: torch.dtype = F64, backend: str = "torch", **simulator_kwargs) -> torch.Tensor:
    """The captured motion: ``rest`` (S, N, 3) m simulated with ``params``, positions at the material
    points after every frame: (F, S, points, 3) m (forward only)."""
    sim = Simulator(rest, params, dtype=dtype, backend=backend, **simulator_kwargs)
    with torch.no_grad():
        return trajectory(sim, poses, checkpoint_every=0, points=points)


# ------------------------------------------------------------------------ gradient check
def _flat(zs: Dict[str, torch.Tensor]) -> torch.Tensor:
    return torch.cat([z.detach().reshape(-1) for z in zs.values()])


def _assign(zs: Dict[str, torch.Tensor], flat: torch.Tensor) -> None:
    with torch.no_grad():
        i = 0
        for z in zs.values():
            z.copy_(flat[i:i + z.numel()].reshape(z.shape))
            i += z.numel()


def fd_check(sim: Simulator, poses, target, directions: int = 3, steps=(1e-4, 1e-6), seed: int = 0,
             checkpoint_every: int = 1) -> dict:
    """Directional derivatives of the rollout loss: autograd (checkpointed every ``checkpoint_every``
    frames) against central differences (L(z + h d) − L(z − h d)) / 2h in the unconstrained values z
    (every field's values flattened), along ``directions`` random unit directions d (seeded; one
    direction when there is one value), for each step h. The values are restored.

    Returns {"loss", "grad", "names", "steps", "directions": [{"d", "autograd", "fd": {h: value},
    "rel": {h: |ad − fd| / max(|ad|, |fd|)}, "best_rel"}], "worst_rel" (the best h per direction,
    worst over directions)}."""
    zs = unconstrained(sim)
    z0 = _flat(zs)
    loss = rollout_loss(sim, poses, target, checkpoint_every=checkpoint_every)
    grads = torch.autograd.grad(loss, list(zs.values()))
    g = torch.cat([t.reshape(-1) for t in grads]).to(F64)
    gen = torch.Generator().manual_seed(seed)
    rows = []
    for _ in range(directions if z0.numel() > 1 else 1):
        d = torch.randn(z0.numel(), generator=gen, dtype=F64) if z0.numel() > 1 else torch.ones(1, dtype=F64)
        d = d / d.norm()
        ad = float(g @ d)
        fd, rel = {}, {}
        for h in steps:
            vals = []
            for sign in (1.0, -1.0):
                _assign(zs, z0 + sign * h * d.to(z0.dtype))
                vals.append(loss_at(sim, poses, target))
            fd[h] = (vals[0] - vals[1]) / (2 * h)
            rel[h] = abs(ad - fd[h]) / max(abs(ad), abs(fd[h]), 1e-300)
        rows.append({"d": d.tolist(), "autograd": ad, "fd": {str(h): v for h, v in fd.items()},
                     "rel": {str(h): v for h, v in rel.items()}, "best_rel": min(rel.values())})
    _assign(zs, z0)
    return {"loss": float(loss.detach()), "grad": {k: _number(t) for k, t in zip(zs, grads)}, "names": list(zs),
            "steps": list(steps), "directions": rows, "worst_rel": max(r["best_rel"] for r in rows)}


# ------------------------------------------------------------------------ the fit
def fit(sim: Simulator, poses, target, iterations: int = 60, lr: float = 0.1, lr_final: float = 0.01,
        checkpoint_every: int = 1, optimizer: str = "adam", log: Optional[Callable[[str], None]] = print) -> dict:
    """Fit the learnable fields of ``sim`` to ``target`` by gradient descent on the unconstrained values
    (log-values / logits); one full rollout + backward per loss evaluation.

    optimizer "adam": ``iterations`` Adam steps, learning rate decaying geometrically from ``lr`` to
    ``lr_final``. "lbfgs": ``torch.optim.LBFGS`` with a strong-Wolfe line search, at most
    ``iterations`` loss evaluations (``lr`` and ``lr_final`` unused).

    Returns {"loss": [loss of each evaluation], "values": [{field: value} of each evaluation],
    "grad": [{field: dloss/dz}], "final_values", "final_loss" (a last rollout at the final values),
    "iterations" (evaluations), "wall_s", "s_per_iteration", "optimizer"}."""
    if optimizer not in ("adam", "lbfgs"):
        raise ValueError(f"optimizer must be 'adam' or 'lbfgs'; got {optimizer!r}")
    zs = unconstrained(sim)
    hist = {"loss": [], "values": [], "grad": []}

    def evaluate():
        vals = values(sim)
        for z in zs.values():
            z.grad = None
        loss = rollout_loss(sim, poses, target, checkpoint_every=checkpoint_every)
        loss.backward()
        hist["loss"].append(float(loss.detach()))
        hist["values"].append(vals)
        hist["grad"].append({k: _number(z.grad) for k, z in zs.items()})
        it = len(hist["loss"]) - 1
        if log and (it % 5 == 0 or it == iterations - 1):
            shown = {k: (f"{v:.5g}" if isinstance(v, float) else f"mean {torch.tensor(v).mean():.5g}")
                     for k, v in vals.items()}
            log(f"  it {it:3d}  loss {hist['loss'][-1]:.6g} mm²  " + "  ".join(f"{k} {v}" for k, v in shown.items()))
        return loss

    t0 = time.perf_counter()
    if optimizer == "adam":
        opt = torch.optim.Adam(list(zs.values()), lr=lr)
        gamma = (lr_final / lr) ** (1.0 / max(iterations - 1, 1))
        sched = torch.optim.lr_scheduler.ExponentialLR(opt, gamma)
        for _ in range(iterations):
            evaluate()
            opt.step()
            sched.step()
    else:
        opt = torch.optim.LBFGS(list(zs.values()), lr=1.0, max_iter=iterations, max_eval=iterations,
                                tolerance_grad=1e-12, tolerance_change=1e-15, history_size=10,
                                line_search_fn="strong_wolfe")
        opt.step(evaluate)
    wall = time.perf_counter() - t0
    hist["final_values"] = values(sim)
    hist["final_loss"] = loss_at(sim, poses, target)
    hist["iterations"] = len(hist["loss"])
    hist["wall_s"] = wall
    hist["s_per_iteration"] = wall / max(len(hist["loss"]), 1)
    hist["optimizer"] = optimizer
    return hist
