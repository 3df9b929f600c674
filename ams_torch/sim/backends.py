"""Which native backends a simulator uses, built when it is constructed (never inside a step), and the
smoke tests of the fused ops' backends.

:func:`resolve_backend` is the simulator's backend decision: it builds (or loads) every backend the
configuration needs, raises for ``backend="native"`` naming each one that cannot be had and why,
and otherwise falls back to the torch definition with one warning per backend
(:mod:`ams_torch.native.build`). The probes registered here (frame, collisions, the collisions' adjoint, grid, the grid's adjoint, the
finish's adjoint) are what
``build`` runs right after loading such a backend: one tiny call compared with the torch definition.
"""
from __future__ import annotations

from typing import List, Tuple

import torch

from ams_torch.geometry.pose import Pose
from ams_torch.sim.contact import collisions_world
from ams_torch.sim.dynamics import frame_dynamics
from ams_torch.sim.model import Model, coefficients
from ams_torch.sim.native import _collisions_torch, collision_arguments, op_arguments
from ams_torch.sim.params import Params
from ams_torch.sim.state import Config
from ams_torch.native import build as _native, probes
from ams_torch.native.dispatch import NATIVE_DTYPES, native_kind
from ams_torch.stages.collide import SphereCollider, resolve_world_poses
from ams_torch.stages.hair_hair.sparse import densify, p2g_sparse

__all__ = ["needed_backends", "resolve_backend", "frame_route", "FRAME_ROUTES"]

F64 = torch.float64


def needed_backends(device, hair_hair: bool = False, colliders: bool = False) -> Tuple[List[str], List[str]]:
    """The native backends a simulator on ``device`` uses: (required by ``backend="native"``, used
    when there: the banded solve of the torch path, which frames that keep a gradient take).
    Kinds of :mod:`ams_torch.native.build`: the device's one library (``cpu`` or ``cuda``) holds
    every op group (frame, collisions, grid, banded solve), so it is the one kind either way:
    ``(["cpu"], ["cpu"])`` on the CPU whatever the stages, ``([], [])`` on a device without kernels."""
    if native_kind("frame", device) is None:
        return [], []
    groups = ["frame"] + (["collide"] if colliders else []) + (["grid"] if hair_hair else [])
    required = list(dict.fromkeys(native_kind(g, device) for g in groups))
    return required, [native_kind("banded", device)]


def resolve_backend(backend: str, device, dtype, hair_hair: bool = False, colliders: bool = False) -> str:
    """The step backend of a simulator, deciding and building everything now (not in the first step).

    Builds (or loads) every native backend the configuration uses (:func:`needed_backends`): a
    backend that cannot be had warns once (``NativeBuildWarning``, naming it and why) and its ops
    take the torch definition. ``"native"``: raises ``ValueError`` naming each required backend that
    is unavailable and why (or the dtype/device that has no native kernels). ``"auto"``: "native"
    when the frame backend is there, else "torch". ``"torch"``: "torch" (the banded solve is still
    built: the torch path uses it). Returns "native" or "torch".
    """
    dev = torch.device(device).type
    required, optional = needed_backends(device, hair_hair, colliders)
    if backend == "torch":
        _native.ensure(optional)
        return "torch"
    if not required or dtype not in NATIVE_DTYPES:
        if backend == "native":
            raise ValueError(f"backend='native' but there are no native kernels for {dev}/{dtype}: they take "
                             f"float32 or float64 tensors on CPU or CUDA")
        return "torch"
    missing = _native.ensure(dict.fromkeys(required + optional))
    lacking = {k: why for k, why in missing.items() if k in required}
    if backend == "native" and lacking:
        detail = "; ".join(f"{k}: {why}" for k, why in lacking.items())
        raise ValueError(f"backend='native' but {len(lacking)} native backend(s) it needs cannot be had: {detail} "
                         f"(ams_torch.native_status() has the details; backend='auto' runs the torch definition "
                         f"for them)")
    return "torch" if native_kind("frame", dev) in missing else "native"


#: The ways a frame's strand dynamics run (:func:`frame_route`) and the entry point of each.
FRAME_ROUTES = {
    "torch": "ams_torch.sim.dynamics.frame_dynamics (the definition; with substep contact when configured)",
    "native": "ams_torch.sim.native.native_frame_dynamics (the fused frame kernel)",
    "native_finish": "ams_torch.sim.native.native_frame_dynamics(..., finish=, pinned=) (the frame's end fused in: "
                     "nothing runs after the dynamics)",
    "native_contact": "ams_torch.sim.native_contact.native_frame_contact (the contact response at every substep)",
    "native_adjoint": "ams_torch.sim.native_grad.native_frame_dynamics_diff (native forward and adjoint)",
    "native_adjoint_contact": "ams_torch.sim.native_grad.native_frame_contact_diff (substep contact in a gradient "
                              "frame: each substep's native forward and adjoint, then the contact's, then "
                              "follow-the-leader on the torch definition)",
}


def frame_route(config: Config, needs_grad: bool) -> str:
    """How this frame's strand dynamics run: the one decision, from the frozen config and whether an
    input keeps a gradient (a key of :data:`FRAME_ROUTES`). A config whose backend is not "native"
    runs the torch definition; a gradient frame of a native config runs the native forward and
    adjoint (with substep contact: substep by substep, the contact's own adjoint between); otherwise
    the fused kernel with substep contact, or without, with the frame's end fused in when no stage
    runs after the dynamics. Each entry point still sends the inputs its kernel cannot take (a
    callable external force, another dtype, a collider class without kernels) to the torch
    definition (:mod:`ams_torch.native.dispatch`)."""
    if config.backend != "native":
        return "torch"
    contact = config.contact == "substep" and bool(config.colliders)
    if needs_grad:
        return "native_adjoint_contact" if contact else "native_adjoint"
    if contact:
        return "native_contact"
    return "native" if (config.hair_hair or config.colliders) else "native_finish"


# -- smoke tests (registered with ams_torch.native.probes) -----------------------------------------

def _tiny(device, colliders=()):
    """3 strands × 5 particles hanging at the origin, moving; (model, config, x, v, pose0, pose1)."""
    z = torch.linspace(0.0, -0.04, 5, dtype=F64)
    rest = torch.stack([torch.stack([torch.full_like(z, 0.01 * i), torch.zeros_like(z), z + 0.1], -1)
                        for i in range(3)])
    params = Params(substeps=1)
    model = Model(rest, params, device=device, dtype=F64)
    model.colliders = torch.nn.ModuleList([c.to(device=device, dtype=F64) for c in colliders])
    config = Config(dt=float(params.dt), substeps=1, collision_rounds=1, colliders=len(colliders))
    g = torch.Generator().manual_seed(0)
    x = model.rest_positions.clone()
    v = 0.05 * torch.randn(x.shape, generator=g, dtype=F64).to(device)
    pose0 = Pose.identity(device=device, dtype=F64)
    pose1 = Pose.from_rotvec((0.0, 0.3, 0.1), (0.01, 0.0, 0.0), (0.6, 0.0, 0.0), (0.0, 18.0, 6.0), device=device,
                             dtype=F64)
    return model, config, x, v, pose0, pose1


def _frame(ns, device) -> None:
    model, config, x, v, pose0, pose1 = _tiny(device)
    args = (model, coefficients(model), config, x, v, model.rest_positions, torch.zeros_like(x), pose0, pose1, True)
    want = frame_dynamics(*args, torch.zeros((), dtype=F64, device=device), None)
    got = ns.frame(*op_arguments(*args, None), -1)
    probes.close(got[0], want[0], "frame (x)")
    probes.close(got[1], want[1], "frame (v)")


def _collide(ns, device) -> None:
    model, config, x, v, _, pose1 = _tiny(device, [SphereCollider((0.01, 0.0, 0.08), 0.02, friction=0.3)])
    x = x + torch.tensor([0.0, 0.0, -0.01], dtype=F64, device=device)
    world = resolve_world_poses(list(model.colliders), pose1, None)
    want = collisions_world(model, config, x, v, pose1, world)
    got = ns.collide(*collision_arguments(model, config, x, v, pose1, world))
    probes.close(got[0], want[0], "collide (x)")
    probes.close(got[1], want[1], "collide (v)")


def _check_adjoint(what: str, loss, ad: float, h: float) -> None:
    """Raise unless the adjoint's directional derivative ``ad`` equals the central difference
    (loss(h) − loss(−h)) / 2h of the torch definition, ``loss(t)`` the loss at t along the
    direction, to 1e-6 relative. No autograd: a library may be built, and probed, inside another
    op's kernel, below autograd."""
    fd = (loss(h) - loss(-h)) / (2 * h)
    if not abs(ad - fd) <= 1e-6 * max(abs(fd), 1e-30):
        raise AssertionError(f"{what}: directional derivative {ad!r}, central difference of the torch definition "
                             f"{fd!r}")


def _collide_adjoint(ns, device) -> None:
    """The collision stage's adjoint along one direction of x and v (:func:`_check_adjoint`)."""
    model, config, x, v, _, pose1 = _tiny(device, [SphereCollider((0.01, 0.0, 0.08), 0.02, friction=0.3)])
    x = x + torch.tensor([0.0, 0.0, -0.013], dtype=F64, device=device)  # no particle at σ = 0
    world = resolve_world_poses(list(model.colliders), pose1, None)
    args = list(collision_arguments(model, config, x, v, pose1, world))
    gx, gv = torch.ones_like(x), torch.linspace(-1.0, 1.0, x.numel(), dtype=F64, device=device).reshape(x.shape)
    got = ns.collide_adjoint(*args, gx, gv)
    dx = torch.linspace(0.5, -1.0, x.numel(), dtype=F64, device=device).reshape(x.shape)
    dv = torch.cos(torch.arange(x.numel(), dtype=F64, device=device)).reshape(x.shape)

    def loss(t):
        xo, vo = _collisions_torch(x + t * dx, v + t * dv, *args[2:])
        return float((gx * xo).sum() + (gv * vo).sum())

    _check_adjoint("collide_adjoint", loss, float((got[0] * dx).sum() + (got[1] * dv).sum()), 1e-7)


def _tiny_grid(device):
    """6 particles (1 scene) in a 4³ grid of 0.125 m cells, head frame = world: x, v, m, frame, origin."""
    g = torch.Generator().manual_seed(0)
    x = (0.3 * torch.rand(1, 6, 3, generator=g, dtype=F64) + 0.1).to(device)
    v = torch.randn(1, 6, 3, generator=g, dtype=F64).to(device)
    m = torch.full((1, 6), 1e-3, dtype=F64, device=device)
    frame = torch.zeros(1, 6, 3, dtype=F64, device=device)
    frame[0, :3] = torch.eye(3, dtype=F64, device=device)
    return x, v, m, frame, torch.zeros(3, dtype=F64, device=device)


def _grid(ns, device) -> None:
    x, v, m, frame, origin = _tiny_grid(device)
    got = ns.p2g(x, v, m, frame, origin, 0.125, 4, 8)  # 8 block slots: the sparse pool (issue 26)
    want = p2g_sparse(x, v, m, frame, origin, 0.125, 4, 8)
    # slots may be given out in another order (CUDA's atomics): compare the dense layouts
    probes.close(densify(got[0], got[2], 4), densify(want[0], want[2], 4), "p2g")


def _grid_adjoint(ns, device) -> None:
    """p2g_adjoint along one direction of the positions and velocities (:func:`_check_adjoint`)."""
    xl, vl, m, frame, origin = _tiny_grid(device)
    faces, table, _, _ = p2g_sparse(xl, vl, m, frame, origin, 0.125, 4, 8)
    gf = torch.cos(torch.arange(faces.numel(), dtype=F64, device=device)).reshape(faces.shape)
    got = ns.p2g_adjoint(xl, vl, m, origin, table, gf, 0.125, 4)
    dx = torch.linspace(0.5, -1.0, xl.numel(), dtype=F64, device=device).reshape(xl.shape)
    dv = torch.sin(torch.arange(xl.numel(), dtype=F64, device=device)).reshape(xl.shape)

    def loss(t):
        return float((gf * p2g_sparse(xl + t * dx, vl + t * dv, m, frame, origin, 0.125, 4, 8)[0]).sum())

    _check_adjoint("p2g_adjoint", loss, float((got[0] * dx).sum() + (got[1] * dv).sum()), 1e-7)


def _finish_adjoint(ns, device) -> None:
    """finish_adjoint along one direction of x, v and the pose (:func:`_check_adjoint`)."""
    from ams_torch.sim.finish import _finish_torch

    g = torch.Generator().manual_seed(0)
    x, v = (torch.randn(2, 3, 4, 3, generator=g, dtype=F64).to(device) for _ in range(2))
    pose = [torch.randn(2, 3, generator=g, dtype=F64).to(device) for _ in range(3)]
    pinned = torch.tensor([0, 1, 4], device=device)
    gv = torch.randn(x.shape, generator=g, dtype=F64).to(device)
    gs = torch.randn(x.shape[:-1], generator=g, dtype=F64).to(device)
    got = ns.finish_adjoint(x, v, pinned, pose, gv, gs)
    dirs = [torch.randn(t.shape, generator=g, dtype=F64).to(device) for t in (x, v, *pose)]

    def loss(t):
        a = [u + t * d for u, d in zip((x, v, *pose), dirs)]
        out, speed = _finish_torch(a[0], a[1], pinned, a[2:])
        return float((gv * out).sum() + (gs * speed).sum())

    g_pose = got[2].reshape(2, 3, 9).sum(1)
    ad = float((got[0] * dirs[0]).sum() + (got[1] * dirs[1]).sum()) + sum(
        float((g_pose[:, 3 * k:3 * k + 3] * dirs[2 + k]).sum()) for k in range(3))
    _check_adjoint("finish_adjoint", loss, ad, 1e-6)


probes.register("frame", _frame)
probes.register("collide", _collide)
probes.register("collide_adjoint", _collide_adjoint)
probes.register("grid", _grid)
probes.register("grid_adjoint", _grid_adjoint)
probes.register("finish_adjoint", _finish_adjoint)
