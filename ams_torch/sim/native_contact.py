"""The fused frame with substep contact (``Params(contact="substep")``, SPEC §8, §15): one registered
op, ``torch.ops.ams_torch.frame_contact``, the frame of :func:`ams_torch.sim.native.native_frame_dynamics`
with the contact response of every collider after each substep's position update.

* default implementation (any device): the torch definition, ``frame_dynamics`` with the contact
  callable of :func:`ams_torch.sim.contact.substep_contact` at the colliders' world poses given;
* CPU and CUDA: the frame kernels (``csrc/frame``: ``frame.h``'s ``strand_frame`` calls
  ``collide.h``'s ``collide_strand`` after every substep), float32 and float64;
* ``register_fake``: shapes for ``torch.compile``.

The colliders' world poses of every substep (the head at the substep's end: colliders that follow
the head move with it) are computed here, by the torch definition's own
:func:`~ams_torch.stages.collide.resolve_world_poses`, and stacked per substep, so both paths read
the same poses. Colliders of the five library classes only (others keep the torch definition).
"""
from __future__ import annotations

from functools import partial

import torch

from ams_torch.geometry.pose import Pose
from ams_torch.sim.contact import substep_contact
from ams_torch.sim.dynamics import frame_dynamics, substep_poses
from ams_torch.sim.model import Coefficients, Model
from ams_torch.sim.op_support import frame_op_schema
from ams_torch.native.dispatch import keeps_gradient
from ams_torch.sim.native import (
    _FRAME_HEAD,
    _SETTINGS,
    _all_tensors,
    _collider_views,
    _namespace,
    _rebuild,
    collision_arguments,
    native_colliders,
    native_frame_supported,
    op_arguments,
)
from ams_torch.sim.state import Config, ExternalForce
from ams_torch.stages.collide import collide, resolve_world_poses

__all__ = ["native_frame_contact", "frame_contact_op", "substep_world_poses"]


def substep_world_poses(model: Model, pose0: Pose, pose1: Pose, hermite: bool, config: Config,
                        collider_poses=()) -> list:
    """The colliders' world poses at the end of every substep, as ``frame_dynamics`` hands them to
    :func:`~ams_torch.sim.contact.substep_contact`: a list over substeps of lists over colliders."""
    poses = substep_poses(pose0, pose1, hermite, config.substeps, config.dt)
    cols = list(model.colliders)
    heads = [pose1 if k + 1 == config.substeps else poses[k + 1] for k in range(config.substeps)]
    return [resolve_world_poses(cols, head, list(collider_poses) or None) for head in heads]


def native_frame_contact_supported(model: Model, coeffs: Coefficients, x, v, ghost_rest, sag_offset, pose0: Pose,
                                   pose1: Pose, external_force: ExternalForce = None) -> bool:
    """:func:`~ams_torch.sim.native.native_frame_supported`, and every collider one of the five
    library classes (at most 16) with no parameter requiring grad (traceable checks only)."""
    cols = list(model.colliders)
    if not cols or not native_colliders(cols):
        return False
    if keeps_gradient(t for c in cols for t in c.parameters()):
        return False
    return native_frame_supported(model, coeffs, x, v, ghost_rest, sag_offset, pose0, pose1, external_force)


def _contact_arguments(model: Model, config: Config, x: torch.Tensor, world: list) -> tuple:
    """(tensors, poses, ints, floats) of the op: the collision op's collider arguments
    (:func:`~ams_torch.sim.native.collision_arguments`) with every pose tensor stacked over substeps."""
    per = [collision_arguments(model, config, x, x, Pose(torch.eye(3, dtype=x.dtype, device=x.device),
                                                         torch.zeros(3, dtype=x.dtype, device=x.device),
                                                         check=False), w) for w in world]
    tensors, ints, floats = per[0][4], per[0][6], per[0][7]
    if any(p[6] != ints for p in per):  # a collider with velocities at some substeps only: no shared layout
        return None
    poses = [torch.stack([p[5][i] for p in per]) for i in range(len(per[0][5]))]
    return tensors, poses, ints, floats


def _contact_torch(state, external_force, model, poses, *rest):
    settings, (collider_tensors, collider_poses, collider_ints, collider_floats) = rest[:_SETTINGS], rest[_SETTINGS:]
    mview, coeffs, config, pose0, pose1 = _rebuild(state, external_force, model, poses, *settings)
    hermite = settings[-1]
    x, v, ghost_rest, sag_offset = state
    views = _collider_views(collider_tensors, collider_ints, collider_floats)
    batch = x.shape[:-3]
    count = len(collider_ints) // 3
    free = ~mview.pinned
    step = [0]

    def world(k):
        out = []
        for c in range(count):
            r, t, lin, ang = (a[k] for a in collider_poses[4 * c:4 * c + 4])
            shape = () if r.numel() == 9 else batch
            r, t = r.reshape(shape + (3, 3)), t.reshape(shape + (3,))
            if collider_ints[3 * c + 2]:
                out.append(Pose(r, t, lin.reshape(shape + (3,)), ang.reshape(shape + (3,)), check=False))
            else:
                out.append(Pose(r, t, check=False))
        return out

    def contact(x, v, pose, h):
        k = step[0]
        step[0] += 1
        return collide(x, v, h, views, world(k), free=free)

    xo, vo = frame_dynamics(mview, coeffs, config, x, v, ghost_rest, sag_offset, pose0, pose1, hermite, 0.0,
                            external_force, contact=contact)
    return xo.contiguous(), vo.contiguous()


@torch.library.custom_op("ams_torch::frame_contact", mutates_args=(), schema=frame_op_schema(
    _FRAME_HEAD, "bool hermite, Tensor[] collider_tensors, Tensor[] collider_poses, SymInt[] collider_ints, "
    "float[] collider_floats", "(Tensor, Tensor)"))
def frame_contact_op(state, external_force, model, poses, *rest):
    """Registered op ``ams_torch::frame_contact``; default (any device): the torch definition.

    The arguments of :func:`~ams_torch.sim.native.frame_dynamics_op` (without ``finish_pose``),
    then per collider c, as :func:`~ams_torch.sim.native.collisions_op` but with one world pose per
    substep: collider_tensors[4c:4c+4] = friction () and its geometry, collider_poses[4c:4c+4] =
    R (M, P, 3, 3), t (M, P, 3) m, linear (M, P, 3) m/s and angular (M, P, 3) rad/s velocity (P = 1
    or the scenes), collider_ints[3c:3c+3] = type, push-out passes, has velocity,
    collider_floats[3c:3c+3] = the shape's numbers. Returns new contiguous (x, v), (..., S, N, 3).
    """
    return _contact_torch(state, external_force, model, poses, *rest)


def _contact_kernel(state, external_force, model, poses, *rest):
    tensors = _all_tensors(state, external_force, model, poses) + list(rest[_SETTINGS]) + list(rest[_SETTINGS + 1])
    ns = _namespace(state[0], tensors)
    if ns is None:
        return _contact_torch(state, external_force, model, poses, *rest)
    return tuple(ns.frame_contact(state, external_force, model, poses, *rest))


frame_contact_op.register_kernel("cpu")(_contact_kernel)
frame_contact_op.register_kernel("cuda")(_contact_kernel)


@frame_contact_op.register_fake
def _contact_fake(state, external_force, model, poses, *rest):
    x = state[0]
    return torch.empty_like(x, memory_format=torch.contiguous_format), \
        torch.empty_like(x, memory_format=torch.contiguous_format)


def native_frame_contact(model: Model, coeffs: Coefficients, config: Config, x: torch.Tensor, v: torch.Tensor,
                         ghost_rest: torch.Tensor, sag_offset: torch.Tensor, pose0: Pose, pose1: Pose, hermite: bool,
                         time: torch.Tensor, external_force: ExternalForce = None, collider_poses=()) -> tuple:
    """One frame of strand dynamics with substep contact by the fused kernel: the result of
    ``frame_dynamics(..., contact=partial(substep_contact, model, config, collider_poses=...))``.
    Arguments as :func:`~ams_torch.sim.native.native_frame_dynamics`; ``collider_poses``: the
    control's (one per collider, or empty). Returns (x, v), each (..., S, N, 3). Inputs that
    :func:`native_frame_contact_supported` rejects take the torch definition."""
    colliders = None
    if native_frame_contact_supported(model, coeffs, x, v, ghost_rest, sag_offset, pose0, pose1, external_force):
        world = substep_world_poses(model, pose0, pose1, hermite, config, collider_poses)
        colliders = _contact_arguments(model, config, x, world)
    if colliders is None:
        return frame_dynamics(model, coeffs, config, x, v, ghost_rest, sag_offset, pose0, pose1, hermite, time,
                              external_force, contact=partial(substep_contact, model, config,
                                                              collider_poses=collider_poses))
    args = op_arguments(model, coeffs, config, x, v, ghost_rest, sag_offset, pose0, pose1, hermite, external_force)
    return frame_contact_op(*args, *colliders)
