"""The collision stage of a frame (SPEC §8) for colliders already placed in the world: the torch
definition that :func:`ams_torch.sim.stepping.collisions` runs and the fused native kernel
(:func:`ams_torch.sim.native.native_collisions`) reproduces."""
from __future__ import annotations

from typing import Sequence

import torch

from ams_torch.geometry.pose import Pose
from ams_torch.sim.dynamics import inextensibility
from ams_torch.sim.model import Model
from ams_torch.sim.state import Config
from ams_torch.stages.collide import collide, resolve_world_poses

__all__ = ["collisions_world", "substep_contact"]


def collisions_world(model: Model, config: Config, x: torch.Tensor, v: torch.Tensor, head_pose: Pose,
                     world_poses: Sequence[Pose], colliders=None) -> tuple:
    """The contact response of every collider in order (at its world pose), then
    ``config.collision_rounds`` rounds of edge-length restore (follow-the-leader, carried by
    ``head_pose``) and push-out (the response with Δt = 0), so contact does not leave stretched
    edges. x, v: (..., S, N, 3) m, m/s. Pinned particles are never touched. Returns the new (x, v)."""
    cols = list(model.colliders) if colliders is None else list(colliders)
    free = ~model.pinned
    x, v = collide(x, v, config.dt, cols, world_poses, free=free)
    if config.inextensibility:
        for _ in range(config.collision_rounds):
            x, v = inextensibility(model, config, x, v, head_pose, config.dt)
            x, v = collide(x, v, 0.0, cols, world_poses, free=free)
    return x, v


def substep_contact(model: Model, config: Config, x: torch.Tensor, v: torch.Tensor, head_pose: Pose, h,
                    collider_poses=()) -> tuple:
    """The contact response inside a substep (``Params(contact="substep")``): every collider in
    order, at its world pose for the head pose ``head_pose`` at the substep's end (colliders that
    follow the head move with it; the others take ``collider_poses``, the frame's, or their own),
    with the substep's Δt' = ``h`` s: :func:`~ams_torch.stages.collide.collide` (velocity response,
    position made consistent with it, push-out). x, v: (..., S, N, 3) m, m/s. Pinned particles are
    never touched. Returns the new (x, v)."""
    cols = list(model.colliders)
    poses = resolve_world_poses(cols, head_pose, list(collider_poses) or None)
    return collide(x, v, h, cols, poses, free=~model.pinned)
