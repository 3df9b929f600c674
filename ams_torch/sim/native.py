"""The fused native kernels of the step (SPEC §15): the frame of strand dynamics and the collision
stage, each one registered op with CPU and CUDA kernels.

``native_frame_dynamics`` has the signature of :func:`ams_torch.sim.dynamics.frame_dynamics` and
returns the same ``(x, v)``: M substeps (substep head poses, ghosts and pin targets, assembly of
every term, banded Cholesky solve, position update) and follow-the-leader, for every strand of
every scene, in one call of the registered op ``torch.ops.ams_torch.frame_dynamics``:

* default implementation (any device): the torch definition, ``frame_dynamics`` itself, called
  through a light adapter that rebuilds the model, coefficients, config and poses from the op's
  tensors and numbers;
* CPU and CUDA: the native kernels of ``ams_torch/native/csrc/frame`` (in the libraries ``cpu`` and
  ``cuda`` of :mod:`ams_torch.native.build`), built lazily on first use, float32 and
  float64; otherwise (not built, ``AMS_TORCH_NATIVE=0``, another dtype, an input requiring grad)
  the torch definition, with one :class:`~ams_torch.native.build.NativeBuildWarning` per process
  when a build fails;
* ``register_fake``: shapes for ``torch.compile`` and meta tensors. No autograd formula: the
  entry point sends anything that needs a gradient to the torch definition.

The kernels run the torch definition's arithmetic per strand (``frame.h``, one source for host and
device): the same formulas, branches (``torch.where``) and safe-normalisation thresholds, in the
same operation order wherever practical, so float64 frames agree to about 1e-15 relative in x
and 1e-14 in v (the differences are the order of a few sums inside torch's matmul and einsum
kernels, fused multiply-adds, and atan2/sin/cos to within an ulp, amplified by the solve's
conditioning and by follow-the-leader's correction / Δt). A callable external force ``f(x, v, t)`` is
not supported natively (the caller keeps the torch path for it: :func:`native_frame_supported`).

``torch.ops.ams_torch.frame_assembly`` (and :func:`native_frame_assembly`) returns one substep's
assembled system instead, ``blocks`` (..., S, N, 4, 3, 3) and ``rhs`` (..., S, N, 3) as
:func:`ams_torch.sim.assembly.assemble_system` gives them, for term-by-term parity tests.

``native_collisions`` is the collision stage of :func:`ams_torch.sim.stepping.collisions` for colliders
at given world poses, one registered op ``torch.ops.ams_torch.collisions`` (``csrc/collide``), with
the same structure (torch default, CPU/CUDA kernels, fake); see the second half of this module.
"""
from __future__ import annotations

import itertools
from functools import partial
from math import isnan, nan
from types import SimpleNamespace
from typing import Callable, List, NamedTuple, Optional, Tuple

import torch

from ams_torch.geometry.pose import Pose
from ams_torch.geometry.sdf import SDFGrid
from ams_torch.native.dispatch import native_available, native_inputs, native_kind, native_namespace
from ams_torch.sim.contact import collisions_world
from ams_torch.sim.dynamics import frame_dynamics, substep_system
from ams_torch.sim.finish import _finish_torch, native_finish_supported, pin_and_speed
from ams_torch.sim.op_support import (
    NATIVE_DTYPES,
    FrameSettings,
    as_like as _as,
    frame_op_schema,
    pose_tensors as _pose_tensors,
)
from ams_torch.sim.model import Coefficients, Model
from ams_torch.sim.state import Config, ExternalForce
from ams_torch.stages.collide import (
    CapsuleCollider,
    HollowSphereCollider,
    MeshCollider,
    PlaneCollider,
    SphereCollider,
)

__all__ = ["NATIVE_DTYPES", "native_frame_available", "native_frame_supported", "native_frame_dynamics",
           "native_frame_assembly", "frame_dynamics_op", "frame_assembly_op", "native_collisions_available",
           "native_collisions_supported", "native_collisions", "collisions_world", "collisions_op"]

_SETTINGS = len(FrameSettings._fields) + 1  # the op's scalars: FrameSettings, then hermite

#: Order of the op's tensor lists (shapes: ``frame_binding.h``).
STATE_FIELDS = ("x", "v", "ghost_rest", "sag_offset")
#: The op's model list, the one table of it on the Python side: (field, whose attribute it is:
#: the Coefficients' or the Model's, k for a per-term coefficient expanded to (S, N − k), None to
#: pass as it is). The bindings read it in this order (``kModelNames`` of ``frame_binding.h``;
#: ``tests/test_native_frame.py`` checks the two agree); :func:`op_arguments` and ``_rebuild``
#: are made from it.
MODEL_LAYOUT = (
    ("rest_positions", "model", None), ("mass", "coeffs", 0), ("drag", "coeffs", 0), ("edge", "coeffs", 1),
    ("bend", "coeffs", 2), ("torsion", "coeffs", 3), ("integrity", "coeffs", 0), ("angular", "coeffs", 1),
    ("transition", "coeffs", None), ("breaking", "coeffs", None), ("soft_ratio", "coeffs", None),
    ("edge_rest_length", "model", None), ("bend_rest_length", "model", None), ("torsion_rest_length", "model", None),
    ("segment_length", "model", None), ("num_pinned", "model", None), ("gravity", "model", None),
)
MODEL_FIELDS = tuple(f for f, _, _ in MODEL_LAYOUT)
_SCALAR_COEFFS = tuple(f for f, src, k in MODEL_LAYOUT if src == "coeffs" and k is None)  # () tensors
POSE_FIELDS = ("rotation0", "translation0", "linear_velocity0", "rotation1", "translation1", "linear_velocity1")


def _eager_or_op(op, kernel, x: torch.Tensor, *args):
    """``kernel(*args)`` directly in eager mode on CPU/CUDA (the registered op's own CPU/CUDA
    kernel, skipping ~12 µs of custom-op dispatch; callers reach here only when nothing needs a
    gradient), the registered ``op(*args)`` under torch.compile (its fake, its schema)."""
    if native_kind("frame", x.device) is not None and not torch.compiler.is_compiling():
        return kernel(*args)
    return op(*args)


# -- availability ---------------------------------------------------------------------------
def native_frame_available(device, dtype) -> bool:
    """Whether the native frame kernel runs for tensors of ``device`` and ``dtype`` (builds it on
    first call; False when it cannot be built, when ``AMS_TORCH_NATIVE=0``, or for dtypes other
    than float32/float64). Not traceable: decide it when the simulator is built."""
    return native_available("frame", device, dtype)


def _tensors_of(coeffs: Coefficients, x, v, ghost_rest, sag_offset, pose0: Pose, pose1: Pose, external_force):
    """Every tensor input of a frame (a generator: read only while grad mode is on)."""
    yield from (x, v, ghost_rest, sag_offset)
    yield from (c for c in coeffs if isinstance(c, torch.Tensor))
    for p in (pose0, pose1):
        yield from (p.rotation, p.translation, p.linear_velocity, p.angular_velocity)
    if isinstance(external_force, torch.Tensor):
        yield external_force


def native_frame_supported(model: Model, coeffs: Coefficients, x: torch.Tensor, v: torch.Tensor,
                           ghost_rest: torch.Tensor, sag_offset: torch.Tensor, pose0: Pose, pose1: Pose,
                           external_force: ExternalForce = None) -> bool:
    """Whether :func:`native_frame_dynamics` can use the native op for these inputs (traceable:
    Python checks of types, dtypes, devices and ``requires_grad`` only, no build, no host sync).

    False for a callable external force, a dtype other than float32/float64, a device other than
    CPU/CUDA, or when grad mode is on and any input (state, coefficient, pose, external force)
    requires grad: gradients come from the torch definition.
    """
    if external_force is not None and not isinstance(external_force, torch.Tensor):
        return False
    if model.rest_positions.dtype != x.dtype:
        return False
    return native_inputs(x, _tensors_of(coeffs, x, v, ghost_rest, sag_offset, pose0, pose1, external_force))


# -- the torch definition behind the op -------------------------------------------------------
def _rebuild(state, external_force, model, poses, *settings):
    """Model-, coefficient-, config- and pose-like objects for the torch definition, from the op's
    arguments (``settings``: the :class:`FrameSettings` fields, then hermite; no host sync)."""
    config, hermite = FrameSettings(*settings[:-1]).config(), settings[-1]
    fields = dict(zip(MODEL_FIELDS, model))
    rest, num_pinned = fields["rest_positions"], fields["num_pinned"]
    l1, l2, l3 = fields["edge_rest_length"], fields["bend_rest_length"], fields["torsion_rest_length"]
    n = rest.shape[-2]
    pinned = torch.arange(n, device=rest.device)[None, :] < num_pinned[:, None]
    # has_pinned=True is exact for a model without pinned particles too (A·0 and blocks·1 change nothing)
    mview = SimpleNamespace(rest_positions=rest, edge_rest_length=l1, bend_rest_length=l2, torsion_rest_length=l3,
                            rest_lengths=(l1, l2, l3), segment_length=fields["segment_length"], pinned=pinned,
                            num_pinned=num_pinned, has_pinned=True, gravity=fields["gravity"])
    coeffs = Coefficients(**{f: fields[f].reshape(()) if f in _SCALAR_COEFFS else fields[f]
                             for f in Coefficients._fields})
    batch = state[0].shape[:-3]
    pose_list = []
    for r, t, u in (poses[:3], poses[3:]):
        shape = () if r.numel() == 9 else batch
        r, t, u = r.reshape(shape + (3, 3)), t.reshape(shape + (3,)), u.reshape(shape + (3,))
        pose_list.append(Pose(r, t, u, u, check=False) if hermite else Pose(r, t, check=False))
    return mview, coeffs, config, pose_list[0], pose_list[1]


def _frame_torch(state, external_force, model, poses, *settings):
    mview, coeffs, config, pose0, pose1 = _rebuild(state, external_force, model, poses, *settings)
    x, v, ghost_rest, sag_offset = state
    return frame_dynamics(mview, coeffs, config, x, v, ghost_rest, sag_offset, pose0, pose1, settings[-1], 0.0,
                          external_force)


def _assembly_torch(state, external_force, model, poses, *settings_and_substep):
    """Substep k's system exactly as ``frame_dynamics`` assembles it, from the state (x, v) given."""
    *settings, k = settings_and_substep
    mview, coeffs, config, pose0, pose1 = _rebuild(state, external_force, model, poses, *settings)
    x, v, ghost_rest, sag_offset = state
    return substep_system(mview, coeffs, config, x, v, ghost_rest, sag_offset, pose0, pose1, settings[-1], k,
                          external_force)


def _namespace(x: torch.Tensor, tensors) -> Optional[object]:
    """The native namespace for x's device, or None (torch definition)."""
    return native_namespace("frame", x, tensors)


def _all_tensors(state, external_force, model, poses):
    return list(state) + list(model) + list(poses) + ([] if external_force is None else [external_force])


# -- the registered ops --------------------------------------------------------------------------
_FRAME_HEAD = "Tensor[] state, Tensor? external_force, Tensor[] model, Tensor[] poses"


@torch.library.custom_op("ams_torch::frame_dynamics", mutates_args=(), schema=frame_op_schema(
    _FRAME_HEAD, "bool hermite, Tensor[] finish_pose", "(Tensor, Tensor, Tensor)"))
def frame_dynamics_op(state, external_force, model, poses, *settings_and_finish):
    """Registered op ``ams_torch::frame_dynamics``; default (any device): the torch definition.

    state: [x, v, ghost_rest, sag_offset], each (..., S, N, 3) m, m/s, m (head frame), m (head
    frame); external_force: (..., S, N, 3) N or None; model: the tensors of ``MODEL_FIELDS``
    (``frame_binding.h`` has their shapes: per-term coefficients (S, N−k), rest data, num_pinned
    (S,) int64, gravity (3,) m/s²); poses: [R0 (P0, 3, 3), t0 (P0, 3) m, u0 (P0, 3) m/s, R1, t1,
    u1] with P_j = 1 or the number of scenes (u read only with ``hermite``); the fields of
    :class:`~ams_torch.sim.op_support.FrameSettings` (dt s, substeps M, ftl_damping,
    integrity_model 0 none / 1 Hookean / 2 non-Hookean, the Config flags); hermite; finish_pose:
    [] (none), or the frame's end fused in (``sim/finish.py``): [translation (P, 3) m, linear
    (P, 3) m/s, angular velocity (P, 3) rad/s] of the head at the end of the frame.
    Returns new contiguous (x, v, speed): x, v (..., S, N, 3); with ``finish_pose``, v has the
    pinned particles at the head's rigid velocity and speed (..., S, N) m/s is |v − rigid
    velocity|; without, v is the dynamics' and speed an empty (0,) tensor.
    """
    return _frame_finish_torch(state, external_force, model, poses, *settings_and_finish)


def _split(settings_and_finish) -> tuple:
    """(settings, finish_pose or None for [])."""
    finish = settings_and_finish[_SETTINGS] if len(settings_and_finish) > _SETTINGS else None
    return settings_and_finish[:_SETTINGS], (list(finish) if finish else None)


def _frame_finish_torch(state, external_force, model, poses, *settings_and_finish):
    settings, finish_pose = _split(settings_and_finish)
    x, v = _frame_torch(state, external_force, model, poses, *settings)
    if finish_pose is None:
        return x, v, x.new_empty(0)
    return (x,) + _finish_torch(x, v, model[MODEL_FIELDS.index("num_pinned")], finish_pose)


def _frame_kernel(state, external_force, model, poses, *settings_and_finish):
    ns = _namespace(state[0], _all_tensors(state, external_force, model, poses))
    if ns is None:
        return _frame_finish_torch(state, external_force, model, poses, *settings_and_finish)
    settings, finish_pose = _split(settings_and_finish)
    if finish_pose is None:
        x, v = ns.frame(state, external_force, model, poses, *settings, -1)
        return x, v, x.new_empty(0)
    return tuple(ns.frame_finish(state, external_force, model, poses, *settings, -1, finish_pose))


frame_dynamics_op.register_kernel("cpu")(_frame_kernel)
frame_dynamics_op.register_kernel("cuda")(_frame_kernel)


@frame_dynamics_op.register_fake
def _frame_fake(state, external_force, model, poses, *settings_and_finish):
    x = state[0]
    speed = x.new_empty(0) if _split(settings_and_finish)[1] is None else x.new_empty(x.shape[:-1])
    return torch.empty_like(x, memory_format=torch.contiguous_format), \
        torch.empty_like(x, memory_format=torch.contiguous_format), speed


@torch.library.custom_op("ams_torch::frame_assembly", mutates_args=(), schema=frame_op_schema(
    _FRAME_HEAD, "bool hermite, SymInt substep", "(Tensor, Tensor)"))
def frame_assembly_op(state, external_force, model, poses, *settings_and_substep):
    """Registered op ``ams_torch::frame_assembly`` (debug, parity tests): the system of substep
    ``substep`` ∈ [0, M) assembled at the given (x, v) as the frame would assemble it there.
    Arguments as :func:`frame_dynamics_op`. Returns blocks (..., S, N, 4, 3, 3) kg (lower band,
    ``blocks[..., i, k] = A[i, i−k]``, full diagonal blocks) and rhs (..., S, N, 3) kg·m/s.
    """
    return _assembly_torch(state, external_force, model, poses, *settings_and_substep)


def _assembly_kernel(state, external_force, model, poses, *settings_and_substep):
    ns = _namespace(state[0], _all_tensors(state, external_force, model, poses))
    if ns is None:
        return _assembly_torch(state, external_force, model, poses, *settings_and_substep)
    return tuple(ns.frame(state, external_force, model, poses, *settings_and_substep))


frame_assembly_op.register_kernel("cpu")(_assembly_kernel)
frame_assembly_op.register_kernel("cuda")(_assembly_kernel)


@frame_assembly_op.register_fake
def _assembly_fake(state, external_force, model, poses, *settings_and_substep):
    x = state[0]
    return x.new_empty(x.shape[:-1] + (4, 3, 3)), torch.empty_like(x, memory_format=torch.contiguous_format)


# -- entry points ------------------------------------------------------------------------------
def op_arguments(model: Model, coeffs: Coefficients, config: Config, x: torch.Tensor, v: torch.Tensor,
                 ghost_rest: torch.Tensor, sag_offset: torch.Tensor, pose0: Pose, pose1: Pose, hermite: bool,
                 external_force: Optional[torch.Tensor] = None) -> tuple:
    """The op's arguments ``(state, external_force, model, poses, *settings)`` for these inputs.
    No torch op runs unless a pose or the external force must be broadcast, or a coefficient
    expanded to its term's shape."""
    batch = x.shape[:-3]
    s, n = x.shape[-3], x.shape[-2]
    hermite = bool(hermite and pose0.has_velocity and pose1.has_velocity)
    poses = []
    for p in (pose0, pose1):
        r, t = p.rotation, p.translation
        u = p.linear_velocity if hermite else t
        if tuple(r.shape[:-2]) not in ((), tuple(batch)):
            r, t, u = (a.expand(batch + a.shape[-k:]).contiguous() for a, k in ((r, 2), (t, 1), (u, 1)))
        poses += [a if a.dtype == x.dtype else a.to(x.dtype) for a in (r, t, u)]
    if external_force is not None:
        if external_force.dtype != x.dtype or external_force.device != x.device:
            external_force = external_force.to(device=x.device, dtype=x.dtype)
        if external_force.shape != x.shape:
            external_force = external_force.expand(x.shape).contiguous()
    model_list = []
    for name, owner, k in MODEL_LAYOUT:
        t = getattr(coeffs if owner == "coeffs" else model, name)
        model_list.append(t if k is None or tuple(t.shape) == (s, n - k) else t.expand((s, n - k)))
    return ([x, v, ghost_rest, sag_offset], external_force, model_list, poses) + FrameSettings.of(config) + (hermite,)


def native_frame_dynamics(model: Model, coeffs: Coefficients, config: Config, x: torch.Tensor, v: torch.Tensor,
                          ghost_rest: torch.Tensor, sag_offset: torch.Tensor, pose0: Pose, pose1: Pose, hermite: bool,
                          time: torch.Tensor, external_force: ExternalForce = None,
                          finish: Optional[Pose] = None, pinned: Optional[torch.Tensor] = None) -> tuple:
    """One frame of strand dynamics by the fused native kernel; same arguments and result as
    :func:`ams_torch.sim.dynamics.frame_dynamics` (x, v, ghost_rest, sag_offset: (..., S, N, 3) m,
    m/s, m, m; poses with velocities; time () s, unused natively; external_force (..., S, N, 3) N,
    or broadcastable to it). Returns (x, v), each (..., S, N, 3).

    ``finish``: the head at the end of the frame, to fuse the frame's end in (when nothing runs
    after the dynamics: :func:`ams_torch.sim.finish.pin_and_speed` with ``pinned`` (S, N) bool):
    returns (x, v, speed) as ``pin_and_speed`` gives them after the dynamics.

    Inputs that :func:`native_frame_supported` rejects (a callable external force, a gradient to
    keep, another dtype or device) go to ``frame_dynamics`` itself. One registered op per frame:
    traceable by ``torch.compile(fullgraph=True)``, no host synchronisation.
    """
    fused = finish is not None and native_finish_supported(x, v, finish)
    if not native_frame_supported(model, coeffs, x, v, ghost_rest, sag_offset, pose0, pose1, external_force):
        out = frame_dynamics(model, coeffs, config, x, v, ghost_rest, sag_offset, pose0, pose1, hermite, time,
                             external_force)
        return out if finish is None else (out[0],) + pin_and_speed(*out, pinned, finish)
    args = op_arguments(model, coeffs, config, x, v, ghost_rest, sag_offset, pose0, pose1, hermite, external_force)
    if not fused:
        x, v, _ = _eager_or_op(frame_dynamics_op, _frame_kernel, x, *args, [])
        return (x, v) if finish is None else (x,) + pin_and_speed(x, v, pinned, finish)
    (_, t, lin, ang), _ = _pose_tensors(finish, x)
    return _eager_or_op(frame_dynamics_op, _frame_kernel, x, *args, [t, lin, ang])


def native_frame_assembly(model: Model, coeffs: Coefficients, config: Config, x: torch.Tensor, v: torch.Tensor,
                          ghost_rest: torch.Tensor, sag_offset: torch.Tensor, pose0: Pose, pose1: Pose, hermite: bool,
                          substep: int, external_force: Optional[torch.Tensor] = None) -> tuple:
    """The system of substep ``substep`` (0 ≤ k < M) of a frame from pose0 to pose1, assembled at
    (x, v) by the registered op (native kernel when available). Arguments as
    :func:`native_frame_dynamics`. Returns blocks (..., S, N, 4, 3, 3) kg and rhs (..., S, N, 3)
    kg·m/s, the layout of :func:`ams_torch.sim.assembly.assemble_system`."""
    args = op_arguments(model, coeffs, config, x, v, ghost_rest, sag_offset, pose0, pose1, hermite, external_force)
    return frame_assembly_op(*args, int(substep))


# ==============================================================================================
# The collision stage (SPEC §8, §15): ams_torch::collisions
# ==============================================================================================
#
# ``native_collisions(model, config, x, v, head_pose, world_poses)`` is the collision stage of
# :func:`ams_torch.sim.stepping.collisions` for colliders already placed in the world
# (:func:`~ams_torch.stages.collide.resolve_world_poses`): the contact response of every collider
# in order, then ``config.collision_rounds`` rounds of follow-the-leader and push-out, fused per
# strand (``csrc/collide``; the follow-the-leader routine is the fused frame's). Colliders of
# the five library classes are native (sphere, capsule, plane, hollow sphere, mesh); any other
# (e.g. a subclass with its own distance) keeps the whole stage on the torch path.

MAX_COLLIDERS = 16


def _mesh_view(g0, g1, g2, f0, f1, f2):
    grid = SDFGrid.__new__(SDFGrid)
    grid._volume_last, grid.origin, grid.upper = g0, g1, g2  # g0: (nz, ny, nx, 4)
    grid._volume = g0.permute(3, 0, 1, 2)[None]
    grid.values, grid.spacing = g0[..., 0].permute(2, 1, 0), nan
    return grid.distance_and_normal


class NativeCollider(NamedTuple):
    """How a collider class crosses to the collision kernels: ``code``, the kernel's type
    (``csrc/collide/collide.h``: ``kSphere`` 0 … ``kMesh`` 4); ``pack(collider, friction)``, its
    three geometry tensors and three numbers (the op's collider_tensors / collider_floats);
    ``view(g0, g1, g2, f0, f1, f2)``, its ``distance_and_normal`` rebuilt from them by the class's
    own code (the torch definition behind the op)."""
    code: int
    pack: Callable
    view: Callable


#: The one collider registry of both paths: class -> kernel code, parameters, torch view. A collider
#: of a class not here (e.g. a subclass with its own distance) keeps its stage on the torch path.
NATIVE_COLLIDERS = {
    SphereCollider: NativeCollider(
        0, lambda c, f: ((c.center, f, f), (c.radius, 0.0, 0.0)),
        lambda g0, g1, g2, f0, f1, f2: partial(SphereCollider.distance_and_normal,
                                               SimpleNamespace(center=g0, radius=f0))),
    CapsuleCollider: NativeCollider(
        1, lambda c, f: ((c.a, c.b, f), (c.radius, 0.0, 0.0)),
        lambda g0, g1, g2, f0, f1, f2: partial(CapsuleCollider.distance_and_normal,
                                               SimpleNamespace(a=g0, b=g1, radius=f0))),
    PlaneCollider: NativeCollider(
        2, lambda c, f: ((c.point, c.normal, f), (0.0, 0.0, 0.0)),
        lambda g0, g1, g2, f0, f1, f2: partial(PlaneCollider.distance_and_normal,
                                               SimpleNamespace(point=g0, normal=g1))),
    HollowSphereCollider: NativeCollider(
        3, lambda c, f: ((c.center, c._frame, f), (c.radius, c.thickness, nan if c.cut_height is None else c.cut_height)),
        lambda g0, g1, g2, f0, f1, f2: partial(HollowSphereCollider.distance_and_normal, SimpleNamespace(
            center=g0, _frame=g1, radius=f0, thickness=f1, cut_height=None if isnan(f2) else f2))),
    MeshCollider: NativeCollider(
        4, lambda c, f: ((c.sdf._volume_last, c.sdf.origin, c.sdf.upper), (0.0, 0.0, 0.0)), _mesh_view),
}
_BY_CODE = {spec.code: spec for spec in NATIVE_COLLIDERS.values()}


def native_colliders(cols) -> bool:
    """Whether every collider of ``cols`` has native kernels (its class in :data:`NATIVE_COLLIDERS`,
    at most :data:`MAX_COLLIDERS`)."""
    cols = list(cols)
    return len(cols) <= MAX_COLLIDERS and all(type(c) in NATIVE_COLLIDERS for c in cols)


def native_collisions_available(device, dtype) -> bool:
    """Whether the native collision kernel runs for tensors of ``device`` and ``dtype`` (builds it
    on first call; not traceable: decide it when the simulator is built)."""
    return native_available("collide", device, dtype)


def native_collisions_supported(model: Model, x: torch.Tensor, v: torch.Tensor, head_pose: Pose,
                                world_poses) -> bool:
    """Whether :func:`native_collisions` can use the native op (traceable checks only): every
    collider one of the five library classes (at most 16), float32/float64 on CPU/CUDA, and no
    gradient to keep."""
    cols = list(model.colliders)
    if not native_colliders(cols):
        return False
    tensors = itertools.chain((x, v, head_pose.rotation),
                              (t for p in world_poses if p is not None for t in
                               (p.rotation, p.translation, p.linear_velocity, p.angular_velocity)),
                              (t for c in cols for t in c.parameters()))
    return native_inputs(x, tensors)


def collision_arguments(model: Model, config: Config, x: torch.Tensor, v: torch.Tensor, head_pose: Pose,
                        world_poses) -> tuple:
    """The op's arguments for these inputs (no torch op unless a pose must be broadcast or a
    collider's data converted to x's dtype)."""
    tensors, poses, ints, floats = [], [], [], []
    for col, pose in zip(model.colliders, world_poses):
        spec = NATIVE_COLLIDERS[type(col)]
        f = _as(col.friction, x)
        geom, nums = spec.pack(col, f)
        tensors += [f] + [_as(g, x) for g in geom]
        pose_list, vel = _pose_tensors(pose, x)
        poses += pose_list
        ints += [spec.code, int(col.projection_iterations), int(vel)]
        floats += [float(n) for n in nums]
    head, _ = _pose_tensors(Pose(head_pose.rotation, head_pose.translation, check=False), x)
    model_list = [model.rest_positions, model.edge_rest_length, model.num_pinned]
    return (x, v, model_list, head[0], tensors, poses, ints, floats, float(config.dt),
            int(config.collision_rounds), bool(config.inextensibility), float(config.ftl_damping))


def _collider_views(tensors, ints, floats) -> list:
    """Collider-like objects (distance_and_normal, friction, projection_iterations) from the op's
    arguments, evaluating the library classes' own distance code."""
    out = []
    for c in range(len(ints) // 3):
        kind, iters = ints[3 * c], ints[3 * c + 1]
        friction, g0, g1, g2 = tensors[4 * c:4 * c + 4]
        fn = _BY_CODE[kind].view(g0, g1, g2, *floats[3 * c:3 * c + 3])
        out.append(SimpleNamespace(distance_and_normal=fn, friction=friction, projection_iterations=iters))
    return out


def _collisions_torch(x, v, model, head_rotation, tensors, poses, ints, floats, dt, rounds, inext, damping):
    rest, edge, num_pinned = model
    n = rest.shape[-2]
    mview = SimpleNamespace(rest_positions=rest, edge_rest_length=edge,
                            pinned=torch.arange(n, device=rest.device)[None, :] < num_pinned[:, None])
    config = Config(dt=dt, inextensibility=inext, ftl_damping=damping, collision_rounds=rounds)
    batch = x.shape[:-3]

    def shaped(t, tail):
        return t.reshape((() if t.numel() == tail[0] * (tail[1] if len(tail) > 1 else 1) else batch) + tail)

    world = []
    for c in range(len(ints) // 3):
        r, t, lin, ang = poses[4 * c:4 * c + 4]
        r, t = shaped(r, (3, 3)), shaped(t, (3,))
        world.append(Pose(r, t, shaped(lin, (3,)), shaped(ang, (3,)), check=False) if ints[3 * c + 2]
                     else Pose(r, t, check=False))
    head_r = shaped(head_rotation, (3, 3))
    head = Pose(head_r, head_r[..., 0], check=False)
    xo, vo = collisions_world(mview, config, x, v, head, world, _collider_views(tensors, ints, floats))
    return (xo.clone() if xo is x else xo), (vo.clone() if vo is v else vo)


@torch.library.custom_op("ams_torch::collisions", mutates_args=())
def collisions_op(x: torch.Tensor, v: torch.Tensor, model: List[torch.Tensor], head_rotation: torch.Tensor,
                  collider_tensors: List[torch.Tensor], collider_poses: List[torch.Tensor], collider_ints: List[int],
                  collider_floats: List[float], dt: float, rounds: int, inextensibility: bool,
                  ftl_damping: float) -> Tuple[torch.Tensor, torch.Tensor]:
    """Registered op ``ams_torch::collisions``; default (any device): the torch definition.

    x, v: (..., S, N, 3) m, m/s; model: [rest_positions (S, N, 3) m, edge_rest_length (S, N−1) m,
    num_pinned (S,) int64]; head_rotation (P, 3, 3) (follow-the-leader's fallback directions);
    per collider c: collider_tensors[4c:4c+4] = friction () and its geometry tensors,
    collider_poses[4c:4c+4] = world R (P, 3, 3), t (P, 3) m, linear (m/s) and angular (rad/s)
    velocity (P, 3), collider_ints[3c:3c+3] = type (sphere 0, capsule 1, plane 2, hollow sphere
    3, mesh 4), push-out passes, has velocity; collider_floats[3c:3c+3] = the shape's numbers
    (``collide_binding.h``). P = 1 or the number of scenes. dt s; rounds of follow-the-leader
    and push-out when ``inextensibility``. Returns new (x, v), each (..., S, N, 3).
    """
    return _collisions_torch(x, v, model, head_rotation, collider_tensors, collider_poses, collider_ints,
                             collider_floats, dt, rounds, inextensibility, ftl_damping)


def _collisions_kernel(x, v, model, head_rotation, tensors, poses, ints, floats, *settings):
    ns = native_namespace("collide", x)  # inputs may keep their gradient: this op has its own adjoint
    if ns is None:
        return _collisions_torch(x, v, model, head_rotation, tensors, poses, ints, floats, *settings)
    return tuple(ns.collide(x, v, model, head_rotation, tensors, poses, ints, floats, *settings))


collisions_op.register_kernel("cpu")(_collisions_kernel)
collisions_op.register_kernel("cuda")(_collisions_kernel)


@collisions_op.register_fake
def _collisions_fake(x, v, model, head_rotation, tensors, poses, ints, floats, *settings):
    return torch.empty_like(x, memory_format=torch.contiguous_format), \
        torch.empty_like(v, memory_format=torch.contiguous_format)


def native_collisions(model: Model, config: Config, x: torch.Tensor, v: torch.Tensor, head_pose: Pose,
                      world_poses) -> tuple:
    """The collision stage by the fused native kernel: ``step.collisions`` for colliders at the
    given world poses (one per ``model.colliders``, from ``resolve_world_poses``; batch () or the
    scenes'). x, v: (..., S, N, 3) m, m/s; head_pose: the head at the end of the frame. Returns
    the new (x, v). Inputs :func:`native_collisions_supported` rejects take the torch definition
    (:func:`collisions_world`); without colliders nothing is done."""
    if len(model.colliders) == 0 and not (config.inextensibility and config.collision_rounds):
        return x, v
    if not native_collisions_supported(model, x, v, head_pose, world_poses):
        return collisions_world(model, config, x, v, head_pose, world_poses)
    return _eager_or_op(collisions_op, _collisions_kernel, x, *collision_arguments(model, config, x, v, head_pose,
                                                                                   world_poses))
