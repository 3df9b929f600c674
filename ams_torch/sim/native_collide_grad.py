"""The collision stage in gradient frames: the native forward and its native adjoint (SPEC §8, §15).

``ams_torch::collisions`` (:mod:`ams_torch.sim.native`) is differentiable (``register_autograd``
here): its backward is the op ``ams_torch::collisions_adjoint``, whose CPU / CUDA kernel is the
native adjoint (``csrc/collide/collide_adjoint.h``, op group ``collide_adjoint``) and whose default
is the torch definition's vector-Jacobian product. Gradients reach x, v, each collider's world pose
(rotation, translation, linear and angular velocity: through them the head's pose for colliders
that follow the head) and friction, and the head rotation (follow-the-leader's fallback
directions); the colliders' geometry and the rest shape are not differentiated here (when they
require grad the stage keeps the torch definition: :func:`native_collisions_diff_supported`).

A gradient frame of a native simulator runs the collision stage by :func:`native_collisions_diff`
and, with ``Params(contact="substep")``, the contact after every substep by
:func:`substep_contact_diff` (:mod:`ams_torch.sim.stepping`).
"""
from __future__ import annotations

import itertools
from typing import List, Optional

import torch

from ams_torch.geometry.pose import Pose
from ams_torch.native.dispatch import native_available, native_namespace
from ams_torch.sim.model import Model
from ams_torch.sim.native import (MAX_COLLIDERS, NATIVE_COLLIDERS, _collisions_torch, _pose_tensors,
                                  collision_arguments, collisions_op)
from ams_torch.sim.state import Config
from ams_torch.stages.collide import (CapsuleCollider, HollowSphereCollider, MeshCollider, PlaneCollider,
                                      SphereCollider, resolve_world_poses)

__all__ = ["MAX_ADJOINT_PUSHOUT", "ADJOINT_COLLIDERS", "collisions_adjoint_op", "native_collisions_diff_supported",
           "native_collisions_diff", "substep_contact_diff", "native_inextensibility_diff"]

#: push-out passes the native adjoint keeps (``kMaxPushout`` of collide_adjoint.h)
MAX_ADJOINT_PUSHOUT = 16
#: collider classes whose response has a native adjoint (a hollow sphere takes the torch definition)
ADJOINT_COLLIDERS = (SphereCollider, CapsuleCollider, PlaneCollider, MeshCollider)


def _adjoint_native_ok(ints) -> bool:
    return all(ints[3 * c] != NATIVE_COLLIDERS[HollowSphereCollider].code and ints[3 * c + 1] <= MAX_ADJOINT_PUSHOUT
               for c in range(len(ints) // 3))


def _collisions_vjp(x, v, model, head_rotation, tensors, poses, ints, floats, settings, gx, gv) -> list:
    """The torch definition's vector-Jacobian product, in the layout of :func:`collisions_adjoint_op`."""
    xs, vs, hr = (t.detach().requires_grad_() for t in (x, v, head_rotation))
    fr = [tensors[4 * c].detach().requires_grad_() for c in range(len(ints) // 3)]
    ts = [fr[i // 4] if i % 4 == 0 else t for i, t in enumerate(tensors)]
    ps = [t.detach().requires_grad_() for t in poses]
    with torch.enable_grad():
        xo, vo = _collisions_torch(xs, vs, model, hr, ts, ps, ints, floats, *settings)
        wrt = [xs, vs, hr] + fr + ps
        grads = torch.autograd.grad((xo, vo), wrt, (gx, gv), allow_unused=True)
    return _unaliased([torch.zeros_like(w) if g is None else g for g, w in zip(grads, wrt)], (gx, gv))


def _unaliased(outs: list, inputs) -> list:
    """``outs`` with a copy of every tensor sharing memory with an input or an earlier output (a
    custom op's outputs may alias neither)."""
    seen = {t.untyped_storage().data_ptr() for t in inputs}
    res = []
    for t in outs:
        ptr = t.untyped_storage().data_ptr()
        if ptr in seen:
            t = t.clone()
            ptr = t.untyped_storage().data_ptr()
        seen.add(ptr)
        res.append(t)
    return res


@torch.library.custom_op("ams_torch::collisions_adjoint", mutates_args=())
def collisions_adjoint_op(x: torch.Tensor, v: torch.Tensor, model: List[torch.Tensor], head_rotation: torch.Tensor,
                          collider_tensors: List[torch.Tensor], collider_poses: List[torch.Tensor],
                          collider_ints: List[int], collider_floats: List[float], dt: float, rounds: int,
                          inextensibility: bool, ftl_damping: float, x_bar: torch.Tensor,
                          v_bar: torch.Tensor) -> List[torch.Tensor]:
    """Registered op ``ams_torch::collisions_adjoint``: the vector-Jacobian product of
    :func:`collisions_op` for output adjoints x_bar, v_bar (..., S, N, 3). Default (any device): the
    torch definition's; CPU / CUDA: the native adjoint kernel (colliders without one, a hollow
    sphere or more than :data:`MAX_ADJOINT_PUSHOUT` push-out passes: the torch definition's).
    Returns [x̄, v̄ (like x), the head rotation's adjoint (like head_rotation), each collider's
    friction adjoint (C of them, like friction), each collider's pose adjoints (4 C, like
    collider_poses)]."""
    return _collisions_vjp(x, v, model, head_rotation, collider_tensors, collider_poses, collider_ints,
                           collider_floats, (dt, rounds, inextensibility, ftl_damping), x_bar, v_bar)


def _collisions_adjoint_kernel(x, v, model, head_rotation, tensors, poses, ints, floats, dt, rounds, inext, damping,
                               gx, gv):
    settings = (dt, rounds, inext, damping)
    ns = native_namespace("collide_adjoint", x) if _adjoint_native_ok(ints) else None
    if ns is None:
        return _collisions_vjp(x, v, model, head_rotation, tensors, poses, ints, floats, settings, gx, gv)
    gxo, gvo, gcol, ghead = ns.collide_adjoint(x, v, model, head_rotation, tensors, poses, ints, floats, *settings,
                                               gx, gv)
    count = len(ints) // 3
    ghead = ghead.sum(1)  # (B, 9): every strand's share
    ghead = (ghead.sum(0) if head_rotation.numel() == 9 else ghead).reshape(head_rotation.shape)
    gcol = gcol.sum(1)  # (B, C, 19)
    friction, pose_grads = [], []
    for c in range(count):
        g = gcol[:, c]
        if poses[4 * c].numel() == 9:
            g = g.sum(0, keepdim=True)
        friction.append(g[:, 18].sum().reshape(tensors[4 * c].shape))
        for q, (lo, hi) in enumerate(((0, 9), (9, 12), (12, 15), (15, 18))):
            pose_grads.append(g[:, lo:hi].reshape(poses[4 * c + q].shape))
    return _unaliased([gxo, gvo, ghead] + friction + pose_grads, (gx, gv))


collisions_adjoint_op.register_kernel("cpu")(_collisions_adjoint_kernel)
collisions_adjoint_op.register_kernel("cuda")(_collisions_adjoint_kernel)


@collisions_adjoint_op.register_fake
def _collisions_adjoint_fake(x, v, model, head_rotation, tensors, poses, ints, floats, *settings_and_seeds):
    like = lambda t: torch.empty_like(t, memory_format=torch.contiguous_format)  # noqa: E731
    count = len(ints) // 3
    return [like(x), like(v), like(head_rotation)] + [like(tensors[4 * c]) for c in range(count)] + \
        [like(p) for p in poses]


def _collisions_setup(ctx, inputs, output):
    x, v, model, head_rotation, tensors, poses, ints, floats, *settings = inputs
    ctx.meta = (list(ints), list(floats), settings, len(model), len(tensors))
    ctx.save_for_backward(x, v, head_rotation, *model, *tensors, *poses)


def _collisions_backward(ctx, gx, gv):
    ints, floats, settings, n_model, n_tensors = ctx.meta
    saved = ctx.saved_tensors
    x, v, head_rotation = saved[:3]
    model = list(saved[3:3 + n_model])
    tensors = list(saved[3 + n_model:3 + n_model + n_tensors])
    poses = list(saved[3 + n_model + n_tensors:])
    gx = torch.zeros_like(x) if gx is None else gx.contiguous()
    gv = torch.zeros_like(v) if gv is None else gv.contiguous()
    out = collisions_adjoint_op(x, v, model, head_rotation, tensors, poses, ints, floats, *settings, gx, gv)
    count = len(ints) // 3
    g_tensors: list = [None] * len(tensors)
    for c in range(count):
        g_tensors[4 * c] = out[3 + c]
    # int / float lists are leaves of the inputs' structure, except empty ones (no colliders: follow-the-leader)
    return (out[0], out[1], [None] * n_model, out[2], g_tensors, list(out[3 + count:]), None if ints else [],
            None if floats else [], None, None, None, None)


collisions_op.register_autograd(_collisions_backward, setup_context=_collisions_setup)


def native_collisions_diff_supported(model: Model, x: torch.Tensor, config: Config) -> bool:
    """Whether a gradient frame's collision stage (or substep contact) can run the native forward
    and adjoint: every collider of :data:`ADJOINT_COLLIDERS` with at most
    :data:`MAX_ADJOINT_PUSHOUT` push-out passes and no geometry requiring grad, a rest shape
    without gradients, float32 / float64 on CPU / CUDA, and the kernels built (on first call)."""
    cols = list(model.colliders)
    if len(cols) > MAX_COLLIDERS or not all(type(c) in ADJOINT_COLLIDERS for c in cols):
        return False
    if any(int(c.projection_iterations) > MAX_ADJOINT_PUSHOUT for c in cols):
        return False
    if any(t.requires_grad for c in cols for name, t in itertools.chain(c.named_parameters(), c.named_buffers())
           if name != "friction" and not name.startswith("pose_")):
        return False
    if model.rest_positions.requires_grad or model.edge_rest_length.requires_grad:
        return False
    if x.dtype not in (torch.float32, torch.float64) or model.rest_positions.dtype != x.dtype:
        return False
    return native_available("collide", x.device, x.dtype) and native_available("collide_adjoint", x.device, x.dtype)


def native_collisions_diff(model: Model, config: Config, x: torch.Tensor, v: torch.Tensor, head_pose: Pose,
                           world_poses, dt: Optional[float] = None, rounds: Optional[int] = None) -> tuple:
    """The collision stage, differentiable, by the native forward (``ams_torch::collisions``) and
    its native adjoint; arguments as :func:`native_collisions`. ``dt`` and ``rounds`` replace the
    config's (the substep contact: the substep's Δt' and no follow-the-leader rounds). Returns the
    new (x, v). Call it where :func:`native_collisions_diff_supported` holds."""
    args = list(collision_arguments(model, config, x, v, head_pose, world_poses))
    if dt is not None:
        args[8] = float(dt)
    if rounds is not None:
        args[9] = int(rounds)
        args[10] = bool(args[10] and rounds > 0)
    return collisions_op(*args)


def substep_contact_diff(model: Model, config: Config, x: torch.Tensor, v: torch.Tensor, head_pose: Pose, h,
                         collider_poses=()) -> tuple:
    """:func:`~ams_torch.sim.contact.substep_contact` (the contact response inside a substep) by the
    native forward and adjoint: every collider at its world pose for the substep's end head pose,
    with the substep's Δt' = ``h`` s and no follow-the-leader rounds. x, v: (..., S, N, 3) m, m/s.
    Returns the new (x, v). Call it where :func:`native_collisions_diff_supported` holds."""
    cols = list(model.colliders)
    poses = resolve_world_poses(cols, head_pose, list(collider_poses) or None)
    return native_collisions_diff(model, config, x, v, head_pose, poses, dt=float(h), rounds=0)


def native_inextensibility_diff(model: Model, config: Config, x: torch.Tensor, v: torch.Tensor, pose: Pose) -> tuple:
    """Follow-the-leader (:func:`~ams_torch.sim.dynamics.inextensibility`: the frame's Δt, fallback
    directions carried by ``pose``'s rotation) by the native forward and adjoint: the collision op
    without colliders and one round (its follow-the-leader is the fused frame's routine, its adjoint
    frame_adjoint.h's). x, v: (..., S, N, 3) m, m/s. Returns the new (x, v); gradients reach x, v
    and the rotation. Call it where :func:`native_collisions_diff_supported` holds."""
    head, _ = _pose_tensors(Pose(pose.rotation, pose.translation, check=False), x)
    model_list = [model.rest_positions, model.edge_rest_length, model.num_pinned]
    return collisions_op(x, v, model_list, head[0], [], [], [], [], float(config.dt), 1, True,
                         float(config.ftl_damping))
