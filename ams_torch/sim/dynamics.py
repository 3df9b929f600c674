"""The strand dynamics of one frame (SPEC §4): M linearised backward-Euler substeps, then
follow-the-leader inextensibility. The torch implementation here is the definition; the fused
native kernel (:mod:`ams_torch.sim.native`) runs the same arithmetic.

Per substep s = 1 … M of length Δt' = Δt / M: the head pose at the substep's end is
interpolated between the frame's two poses (:meth:`Pose.interpolate`: slerp, and cubic Hermite
translation when both poses carry velocities); the ghosts follow it rigidly (world ghosts
``y = R ghost_rest + T``, their velocity the change over the substep), the pinned particles
are driven to their rest positions carried by the head, the system of :mod:`assembly` is solved
for the new velocities and the positions advance ``x += Δt' v`` (pinned particles land exactly on
their targets).
"""
from __future__ import annotations

from typing import Optional

import torch
from torch.profiler import record_function

from ams_torch.geometry.pose import Pose
from ams_torch.sim.assembly import assemble_system
from ams_torch.sim.forces import safe_normalize
from ams_torch.sim.inextensibility import follow_the_leader
from ams_torch.sim.model import Coefficients, Model
from ams_torch.sim.state import Config, ExternalForce
from ams_torch.solver.op import solve_banded

__all__ = ["frame_dynamics", "inextensibility", "substep_poses", "substep_system", "substep_targets"]


def substep_poses(pose0: Pose, pose1: Pose, hermite: bool, substeps: int, dt) -> list:
    """The head poses at the ends of the M substeps (the last one is ``pose1``). Without
    ``hermite`` the velocities are dropped so translation interpolates linearly."""
    start = pose0 if hermite else Pose(pose0.rotation, pose0.translation, check=False)
    end = pose1 if hermite else Pose(pose1.rotation, pose1.translation, check=False)
    return [start] + [start.interpolate(end, (s + 1) / substeps, dt) for s in range(substeps)]


def _external(external_force: ExternalForce, x, v, t):
    if external_force is None or isinstance(external_force, torch.Tensor):
        return external_force
    return external_force(x, v, t)


def inextensibility(model: Model, config: Config, x: torch.Tensor, v: torch.Tensor, pose: Pose, dt) -> tuple:
    """Restore every edge to its rest length (SPEC §4): follow-the-leader with Müller's velocity
    correction (``config.ftl_damping``); a collapsed edge takes its rest direction carried by
    ``pose`` (the head at the end of the frame). x, v: (..., S, N, 3) m, m/s; dt: the frame, s.
    Returns the new (x, v)."""
    with record_function("ams_torch.inextensibility"):
        rest = model.rest_positions
        fallback = safe_normalize(pose.rotate((rest[:, 1:, :] - rest[:, :-1, :]).expand(
            x.shape[:-3] + (rest.shape[0], rest.shape[1] - 1, 3))))[0]
        return follow_the_leader(x, v, model.edge_rest_length, model.pinned, dt, config.ftl_damping, fallback)


def substep_targets(model: Model, x: torch.Tensor, ghost_rest: torch.Tensor, y_a: torch.Tensor, pose_b: Pose,
                    h: float) -> tuple:
    """What a substep of length h (s) drives towards, given the ghosts y_a (..., S, N, 3) m at its
    start and the head pose ``pose_b`` at its end: the ghosts y_b there, their velocity
    w = (y_b − y_a)/h (m/s), the pinned particles' targets (the rest shape carried by pose_b, m)
    and the velocity pin_v = (target − x)/h that takes them there (m/s; 0 for free particles).
    x, ghost_rest: (..., S, N, 3) m. Returns (y_b, w, target, pin_v), each (..., S, N, 3)."""
    y_b = pose_b.to_world(ghost_rest)
    w = (y_b - y_a) / h
    target = pose_b.to_world(model.rest_positions.expand(x.shape))
    pin_v = torch.where(model.pinned[..., None], (target - x) / h, torch.zeros_like(x))
    return y_b, w, target, pin_v


def substep_system(model: Model, coeffs: Coefficients, config: Config, x: torch.Tensor, v: torch.Tensor,
                   ghost_rest: torch.Tensor, sag_offset: torch.Tensor, pose0: Pose, pose1: Pose, hermite: bool,
                   k: int, external_force=None) -> tuple:
    """Substep k's (0 ≤ k < M) system exactly as :func:`frame_dynamics` assembles it, at the state
    (x, v) given (the parity tests' reference for the native assembly). Arguments as
    :func:`frame_dynamics`; ``external_force``: a (..., S, N, 3) N tensor or None. Returns blocks
    (..., S, N, 4, 3, 3) kg and rhs (..., S, N, 3) kg·m/s."""
    h = config.dt / config.substeps
    poses = substep_poses(pose0, pose1, hermite, config.substeps, config.dt)
    pa, pb = poses[k], poses[k + 1]
    y_a = pa.to_world(ghost_rest)
    _, w, _, pin_v = substep_targets(model, x, ghost_rest, y_a, pb, h)
    offset = pa.rotate(sag_offset) if config.nonhookean else None
    return assemble_system(model, coeffs, config, x, v, y_a, w, pin_v, h, external_force, offset)


def frame_dynamics(model: Model, coeffs: Coefficients, config: Config, x: torch.Tensor, v: torch.Tensor,
                   ghost_rest: torch.Tensor, sag_offset: torch.Tensor, pose0: Pose, pose1: Pose, hermite: bool,
                   time: torch.Tensor, external_force: ExternalForce = None, poses: Optional[list] = None,
                   contact=None) -> tuple:
    """One frame of strand dynamics: M substeps and inextensibility (plain torch, differentiable).

    Args:
        model, coeffs, config: fixed data, its coefficients and the step's settings.
        x, v: (..., S, N, 3) m and m/s at the start of the frame.
        ghost_rest: (..., S, N, 3) m, the ghosts' rest shape in the head frame.
        sag_offset: (..., S, N, 3) m, head frame, the scene's sag-free offset (non-Hookean law).
        pose0, pose1: head poses at the start and end of the frame, with velocities.
        hermite: whether substep poses use cubic Hermite translation (both ends had velocities).
        time: () s at the start of the frame (for a callable external force).
        external_force: see :data:`~ams_torch.sim.state.ExternalForce`.
        poses: the M + 1 substep poses (default :func:`substep_poses` of pose0, pose1; the native
            adjoint's op gives them, computed in torch so that their gradients reach the frame's poses).
        contact: ``contact(x, v, pose, h) -> (x, v)`` run after every substep's position update
            with the head pose at the substep's end (the frame's end pose, with its velocities,
            after the last) and the substep length h (``Params(contact="substep")``:
            :func:`ams_torch.sim.contact.substep_contact`); None: nothing.
    Returns:
        (x, v): (..., S, N, 3) after the substeps and follow-the-leader.
    """
    dt = config.dt
    m_sub = config.substeps
    h = dt / m_sub
    pinned = model.pinned[..., None]  # (S, N, 1)
    poses = substep_poses(pose0, pose1, hermite, m_sub, dt) if poses is None else poses
    y_a = poses[0].to_world(ghost_rest)
    nonhookean = config.nonhookean
    offset = poses[0].rotate(sag_offset) if nonhookean else None
    for s in range(m_sub):
        pb = poses[s + 1]
        y_b, w, target, pin_v = substep_targets(model, x, ghost_rest, y_a, pb, h)
        f_ext = _external(external_force, x, v, time + s * h)
        blocks, rhs = assemble_system(model, coeffs, config, x, v, y_a, w, pin_v, h, f_ext, offset)
        with record_function("ams_torch.solve"):
            v = solve_banded(blocks, rhs, check=False)
        x = torch.where(pinned, target, x + h * v)
        if contact is not None:
            x, v = contact(x, v, pose1 if s + 1 == m_sub else pb, h)
        y_a = y_b
        if nonhookean:
            offset = pb.rotate(sag_offset)
    if config.inextensibility:
        x, v = inextensibility(model, config, x, v, poses[-1], dt)  # pose1's rotation
    return x, v
