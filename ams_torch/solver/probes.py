"""Smoke tests of a freshly loaded native backend: one tiny call of each op group, compared with
the torch definition (float64, a few particles). :mod:`ams_torch.solver.build` runs the probe of a
backend right after loading it and marks the backend unavailable, with the error, when it fails:
a library built for the wrong GPU architecture, a broken toolkit or driver, or a kernel that
crashes, is then reported at build time (and the torch path is used) instead of failing, or
returning garbage, inside the first step.

``probe(kind, ns, device)``: ``kind`` a key of the build table (``frame_cuda``, ``grid_cpu``,
``collide_cuda_emu``, ...), ``ns`` its ``torch.ops`` namespace, ``device`` where its ops take
tensors ("cpu" for the CPU and emulated backends, "cuda" for the CUDA ones). Raises
``AssertionError`` (wrong result) or the op's own error.
"""
from __future__ import annotations

import torch

__all__ = ["probe"]

F64 = torch.float64
TOL = 1e-8


def _close(got: torch.Tensor, want: torch.Tensor, what: str) -> None:
    got, want = got.detach().double().cpu(), want.detach().double().cpu()
    err = (got - want).norm().item()
    scale = max(want.norm().item(), 1e-30)
    if not (err <= TOL * scale):
        raise AssertionError(f"{what}: relative difference {err / scale:.3g} from the torch definition")


def _group(kind: str) -> str:
    base = kind[:-4] if kind.endswith("_emu") else kind
    return "banded" if base in ("cpu", "cuda") else base.rsplit("_", 1)[0]


def probe(kind: str, ns, device: str) -> None:
    """Run the smoke test of backend ``kind`` (see the module docstring)."""
    fn = {"banded": _banded, "frame": _frame, "collide": _collide, "grid": _grid}.get(_group(kind))
    if fn is not None:
        with torch.no_grad():
            fn(ns, torch.device(device))
        if torch.device(device).type == "cuda":
            torch.cuda.synchronize(device)


def _banded(ns, device) -> None:
    blocks = torch.zeros(2, 5, 4, 3, 3, dtype=F64, device=device)
    blocks[:, :, 0] = 2.0 * torch.eye(3, dtype=F64, device=device)
    rhs = torch.arange(30, dtype=F64, device=device).reshape(2, 5, 3)
    _close(ns.solve_banded(blocks, rhs), rhs / 2.0, "solve_banded")


def _scene(device, colliders=()):
    from ams_torch.geometry.pose import Pose
    from ams_torch.sim.params import Params
    from ams_torch.sim.simulator import Simulator

    s, n = 3, 5
    z = torch.linspace(0.0, -0.04, n, dtype=F64)
    rest = torch.stack([torch.stack([torch.full_like(z, 0.01 * i), torch.zeros_like(z), z], -1) for i in range(s)])
    rest = rest + torch.tensor([0.0, 0.0, 0.1], dtype=F64)
    sim = Simulator(rest, Params(substeps=1), device=device, dtype=F64, backend="torch", colliders=list(colliders))
    pose1 = Pose.from_rotvec((0.0, 0.3, 0.1), (0.01, 0.0, 0.0), device=device, dtype=F64)
    state = sim.initial_state()
    g = torch.Generator().manual_seed(0)
    v = state.v + 0.05 * torch.randn(state.v.shape, generator=g, dtype=F64).to(device)
    return sim, state.replace(v=v), pose1


def _frame(ns, device) -> None:
    from ams_torch.sim.dynamics import frame_dynamics
    from ams_torch.sim.model import coefficients
    from ams_torch.sim.native import op_arguments
    from ams_torch.sim.step import resolve_pose

    sim, state, pose1 = _scene(device)
    pose1, hermite = resolve_pose(state.pose, pose1, sim.config.dt)
    c = coefficients(sim.model)
    args = (sim.model, c, sim.config, state.x, state.v, state.ghost_rest, state.sag_offset, state.pose, pose1, hermite)
    want = frame_dynamics(*args, state.time, None)
    got = ns.frame(*op_arguments(*args, None), -1)
    _close(got[0], want[0], "frame (x)")
    _close(got[1], want[1], "frame (v)")


def _collide(ns, device) -> None:
    from ams_torch.sim.native import collision_arguments
    from ams_torch.sim.step import collisions
    from ams_torch.stages.collide import SphereCollider, resolve_world_poses

    sim, state, pose1 = _scene(device, [SphereCollider((0.01, 0.0, 0.08), 0.02, friction=0.3)])
    x = state.x + torch.tensor([0.0, 0.0, -0.01], dtype=F64, device=device)
    want = collisions(sim.model, sim.config, x, state.v, pose1, ())
    world = resolve_world_poses(sim.colliders, pose1, None)
    got = ns.collide(*collision_arguments(sim.model, sim.config, x, state.v, pose1, world))
    _close(got[0], want[0], "collide (x)")
    _close(got[1], want[1], "collide (v)")


def _grid(ns, device) -> None:
    from ams_torch.stages.hair_hair.transfer import p2g_torch

    g = torch.Generator().manual_seed(0)
    x = (0.3 * torch.rand(1, 6, 3, generator=g, dtype=F64) + 0.1).to(device)
    v = torch.randn(1, 6, 3, generator=g, dtype=F64).to(device)
    m = torch.full((1, 6), 1e-3, dtype=F64, device=device)
    frame = torch.zeros(1, 6, 3, dtype=F64, device=device)
    frame[0, :3] = torch.eye(3, dtype=F64, device=device)
    origin = torch.zeros(3, dtype=F64, device=device)
    _close(ns.p2g(x, v, m, frame, origin, 0.125, 4), p2g_torch(x, v, m, frame, origin, 0.125, 4), "p2g")
