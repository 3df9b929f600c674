"""World poses of colliders for one frame: their own pose, a per-frame override, and the head
for colliders attached to it (SPEC §8)."""
from __future__ import annotations

import math
from typing import List, Mapping, Optional, Sequence, Union

import torch

from ams_torch.geometry.pose import Pose
from ams_torch.stages.collide.shapes import Collider

__all__ = ["resolve_world_poses", "flat_pose"]


def _compose(head: Pose, rel: Pose) -> Pose:
    """World pose of a frame attached to ``head`` at relative pose ``rel`` (velocities composed)."""
    rel = rel.to(device=head.rotation.device, dtype=head.rotation.dtype)
    rot = head.rotation @ rel.rotation
    arm = (head.rotation @ rel.translation[..., None])[..., 0]  # origin offset in world axes
    trans = arm + head.translation
    if not head.has_velocity and not rel.has_velocity:
        return Pose(rot, trans, check=False)
    zero = torch.zeros_like(trans)
    hv = head.linear_velocity if head.has_velocity else zero
    hw = head.angular_velocity if head.has_velocity else zero
    rv = (head.rotation @ rel.linear_velocity[..., None])[..., 0] if rel.has_velocity else zero
    rw = (head.rotation @ rel.angular_velocity[..., None])[..., 0] if rel.has_velocity else zero
    hw_b = hw.expand_as(arm)
    lin = hv + torch.linalg.cross(hw_b, arm) + rv
    return Pose(rot, trans, lin.expand_as(trans), (hw + rw).expand_as(trans), check=False)


def resolve_world_poses(colliders: Sequence[Collider], head_pose: Optional[Pose] = None,
                        overrides: Optional[Union[Sequence[Optional[Pose]], Mapping[int, Pose]]] = None
                        ) -> List[Pose]:
    """World pose (with velocities) of each collider for one frame.

    Args:
        colliders: the scene's colliders.
        head_pose: world pose of the head at the end of the frame (with its velocities);
            ``None`` = identity, static.
        overrides: replaces ``collider.pose`` for this frame (same meaning: relative to the head
            for ``follow_head`` colliders, world otherwise). Either a sequence with one entry per
            collider (``None`` = keep), or a mapping ``{collider index: Pose}``.

    Returns: a list of :class:`Pose`, one per collider, in the world. A follow-head collider
    gets R = R_h R_c, T = R_h T_c + T_h, linear velocity v_h + ω_h × (R_h T_c) + R_h v_c and
    angular velocity ω_h + R_h ω_c (missing velocities count as zero; if both are missing the
    result has none, i.e. static).
    """
    n = len(colliders)
    if overrides is None:
        chosen: List[Optional[Pose]] = [None] * n
    elif isinstance(overrides, Mapping):
        chosen = [overrides.get(i) for i in range(n)]
        if any(not 0 <= int(i) < n for i in overrides):
            raise IndexError(f"collider pose override index out of range (have {n} colliders)")
    else:
        chosen = list(overrides)
        if len(chosen) != n:
            raise ValueError(f"got {len(chosen)} collider poses for {n} colliders")
    out = []
    for col, over in zip(colliders, chosen):
        pose = over if over is not None else col.pose
        if col.follow_head:
            head = head_pose if head_pose is not None else Pose.identity(dtype=pose.rotation.dtype,
                                                                         device=pose.rotation.device)
            out.append(_compose(head, pose))
        else:
            out.append(pose)
    return out


def flat_pose(pose: Optional[Pose], batch: torch.Size, x: torch.Tensor):
    """Pose tensors broadcast to x's batch dims and flattened: R (B,3,3), T (B,3), v/ω (B,3) or None.

    As in :class:`Pose`, the pose's batch dims are a prefix of the particles' batch dims
    (a pose (B, 3, 3) applies to every scene of x (B, C, S, N, 3)).
    """
    if pose is None:
        pose = Pose.identity()
    pose = pose.to(device=x.device, dtype=x.dtype)
    pb = tuple(pose.rotation.shape[:-2])
    extra = len(batch) - len(pb)
    padded = pb + (1,) * max(extra, 0)
    if extra < 0 or any(p not in (1, b) for p, b in zip(padded, batch)):
        raise ValueError(f"collider pose batch shape {pb} does not match the particles' batch "
                         f"shape {tuple(batch)}")
    b = int(math.prod(batch)) if len(batch) else 1

    def flat(t, tail):
        if t is None:
            return None
        own = tuple(t.shape[:t.dim() - len(tail)])  # this field's batch dims (a prefix of x's)
        t = t.reshape(own + (1,) * (len(batch) - len(own)) + tail)
        return t.expand(tuple(batch) + tail).reshape((b,) + tail)

    lin = flat(pose.linear_velocity, (3,)) if pose.has_velocity else None
    ang = flat(pose.angular_velocity, (3,)) if pose.has_velocity else None
    return flat(pose.rotation, (3, 3)), flat(pose.translation, (3,)), lin, ang
