"""Gradient frames at native speed: the fused frame of strand dynamics with its adjoint (SPEC §15).

A frame whose inputs require grad runs its strand dynamics through the registered op
``torch.ops.ams_torch.frame_dynamics_diff`` (:func:`native_frame_dynamics_diff`): the forward is
the fused native frame with its M + 1 substep head poses given as a tensor (computed here in torch
by :func:`~ams_torch.sim.dynamics.substep_poses`, so their gradients reach the frame's head poses
and velocities), and ``register_autograd`` makes its backward the native adjoint kernel
(``csrc/frame/frame_adjoint.h``; libraries ``cpu`` / ``cuda`` of
:mod:`ams_torch.native.build`). The adjoint recomputes the frame (nothing is stored between the
passes) and differentiates it with respect to x, v, ghost_rest, the external force, the per-element
coefficients (mass, drag, edge / bend / torsion stiffness, integrity, angular: the gradients of the
Params fields behind them, per-strand fields too, follow by autograd), the non-Hookean curve
(transition, breaking point, soft ratio) and sag-free offset, and the substep poses.

With ``Params(contact="substep")`` a gradient frame runs :func:`native_frame_contact_diff`: the op
once per substep (M = 1, no follow-the-leader), the collision op and its native adjoint after each
(:func:`~ams_torch.sim.native_collide_grad.substep_contact_diff`), follow-the-leader by the collision op
without colliders and its native adjoint.

Where the adjoint is not native (the one-particle angular form, a callable
external force, a grad-carrying rest shape, another dtype or device, kernels that do not build)
the frame takes the torch definition; of the step's other stages the collisions have their own
native adjoint (:mod:`ams_torch.sim.native_collide_grad`), hair–hair, the frame's end and the plastic yield keep
the torch definition in a gradient frame (``ams_torch.native_status()["gradients"]``).

* default implementation (any device): the torch definition (``frame_dynamics`` with the given
  substep poses); CPU / CUDA: the native kernel; ``register_fake``: shapes.
* backward: the native adjoint where built, else the torch definition's vector-Jacobian product.
"""
from __future__ import annotations

import torch

from ams_torch.geometry.pose import Pose
from ams_torch.sim.dynamics import frame_dynamics, inextensibility, substep_poses
from ams_torch.sim.model import Coefficients, Model
from ams_torch.sim.native import MODEL_FIELDS, _rebuild, op_arguments
from ams_torch.sim.native_collide_grad import native_collisions_diff_supported, native_inextensibility_diff
from ams_torch.sim.op_support import FrameSettings, frame_op_schema
from ams_torch.sim.state import Config, ExternalForce
from ams_torch.native.dispatch import native_available, native_namespace

__all__ = ["frame_dynamics_diff_op", "frame_dynamics_adjoint_op", "native_frame_dynamics_diff", "native_adjoint_supported",
           "native_frame_contact_diff", "substep_pose_tensor"]

_GRAD_FIELDS = ("mass", "drag", "edge", "bend", "torsion", "integrity", "angular")  # adjoint outputs 4 … 10
_LAW_FIELDS = ("transition", "breaking", "soft_ratio")  # the non-Hookean curve: adjoint output 13
_FIXED_FIELDS = ("rest_positions", "transition", "breaking", "soft_ratio", "edge_rest_length", "bend_rest_length",
                 "torsion_rest_length", "segment_length", "gravity")


def substep_pose_tensor(pose0: Pose, pose1: Pose, hermite: bool, substeps: int, dt: float,
                        x: torch.Tensor) -> torch.Tensor:
    """The M + 1 substep head poses (:func:`~ams_torch.sim.dynamics.substep_poses`) as one tensor
    (P, M + 1, 12): R row-major then t (m) per pose, P = 1 or the scenes of x (..., S, N, 3)
    flattened. Differentiable with respect to both poses (and their velocities with ``hermite``)."""
    batch = x.shape[:-3]
    poses = substep_poses(pose0, pose1, hermite, substeps, dt)
    shaped = any(tuple(p.rotation.shape[:-2]) != () for p in poses)
    rows = []
    for p in poses:
        r, t = p.rotation.to(x.dtype), p.translation.to(x.dtype)
        if shaped:
            own = r.shape[:-2]
            r = r.reshape(own + (1,) * (len(batch) - len(own)) + (3, 3)).expand(batch + (3, 3))
            t = t.reshape(own + (1,) * (len(batch) - len(own)) + (3,)).expand(batch + (3,))
        rows.append(torch.cat((r.reshape(r.shape[:-2] + (9,)), t), -1))
    out = torch.stack(rows, -2)
    return out.reshape(-1, substeps + 1, 12)


# -- the torch definition behind the op --------------------------------------------------------
def _posed_torch(state, external_force, model, poses, dt, substeps, *flags):
    """frame_dynamics with the substep poses of ``poses`` (P, M + 1, 12)."""
    x = state[0]
    batch = x.shape[:-3]
    shape = () if poses.shape[0] == 1 else batch
    first = [poses[:, 0, :9].reshape(shape + (3, 3)), poses[:, 0, 9:].reshape(shape + (3,))]
    ends = first + first[1:] + first + first[1:]
    mview, coeffs, config, _, _ = _rebuild(state, external_force, model, ends, dt, substeps, *flags, False)
    pose_list = [Pose(poses[:, k, :9].reshape(shape + (3, 3)), poses[:, k, 9:].reshape(shape + (3,)), check=False)
                 for k in range(substeps + 1)]
    xo, vo = frame_dynamics(mview, coeffs, config, state[0], state[1], state[2], state[3], pose_list[0],
                            pose_list[-1], False, 0.0, external_force, poses=pose_list)
    return xo.contiguous(), vo.contiguous()


def _namespace(x: torch.Tensor):
    """The adjoint kernels' namespace (inputs keep their gradient: this op has its own adjoint), or None."""
    return native_namespace("frame_adjoint", x)


_POSED_HEAD = "Tensor[] state, Tensor? external_force, Tensor[] model, Tensor poses"


@torch.library.custom_op("ams_torch::frame_dynamics_diff", mutates_args=(),
                         schema=frame_op_schema(_POSED_HEAD, "", "(Tensor, Tensor)"))
def frame_dynamics_diff_op(state, external_force, model, poses, *settings):
    """Registered op ``ams_torch::frame_dynamics_diff``; default (any device): the torch definition.

    state, external_force, model: as ``ams_torch::frame_dynamics`` (:mod:`ams_torch.sim.native`);
    poses: (P, M + 1, 12) the substep head poses (:func:`substep_pose_tensor`); the fields of
    :class:`~ams_torch.sim.op_support.FrameSettings` (the one-particle angular form has no native
    adjoint and takes the torch definition). Returns new
    contiguous (x, v), each (..., S, N, 3). Differentiable (register_autograd: the native adjoint)."""
    return _posed_torch(state, external_force, model, poses, *settings)


def _native_ok(integrity_model: int, angular: bool, angular_reaction: bool) -> bool:
    return angular_reaction or not angular


def _posed_kernel(state, external_force, model, poses, dt, substeps, *flags):
    ns = _namespace(state[0])
    if ns is None or not _native_ok(flags[1], flags[2], flags[3]):
        return _posed_torch(state, external_force, model, poses, dt, substeps, *flags)
    return tuple(ns.frame_posed(state, external_force, model, poses, dt, substeps, *flags))


frame_dynamics_diff_op.register_kernel("cpu")(_posed_kernel)
frame_dynamics_diff_op.register_kernel("cuda")(_posed_kernel)


@frame_dynamics_diff_op.register_fake
def _posed_fake(state, external_force, model, poses, *settings):
    x = state[0]
    return torch.empty_like(x, memory_format=torch.contiguous_format), \
        torch.empty_like(x, memory_format=torch.contiguous_format)


def _setup_context(ctx, inputs, output):
    state, external_force, model, poses, *settings = inputs
    ctx.settings = settings
    ctx.has_ext = external_force is not None
    ctx.n_model = len(model)
    ctx.save_for_backward(*state, *model, poses, *([external_force] if ctx.has_ext else []))


def _torch_vjp(state, external_force, model, poses, settings, gx, gv) -> list:
    """The torch definition's vector-Jacobian product, in the layout of :func:`frame_dynamics_adjoint_op`."""
    leaves = [t.detach().requires_grad_() for t in state]
    ext = external_force.detach().requires_grad_() if external_force is not None else None
    idx = [MODEL_FIELDS.index(f) for f in _GRAD_FIELDS + _LAW_FIELDS]
    mod = [t.detach().requires_grad_(i in idx) for i, t in enumerate(model)]
    ps = poses.detach().requires_grad_()
    with torch.enable_grad():
        xo, vo = _posed_torch(leaves, ext, mod, ps, *settings)
        wrt = leaves + ([ext] if ext is not None else []) + [mod[i] for i in idx] + [ps]
        grads = torch.autograd.grad((xo, vo), wrt, (gx, gv), allow_unused=True)
    grads = [torch.zeros_like(w) if g is None else g for g, w in zip(grads, wrt)]
    g_sag = grads.pop(3)
    if ext is None:
        grads.insert(3, state[0].new_empty(0))
    law = torch.stack([g.reshape(()) for g in grads[11:14]])
    return grads[:11] + [grads[14], g_sag, law]


@torch.library.custom_op("ams_torch::frame_dynamics_adjoint", mutates_args=(),
                         schema=frame_op_schema(_POSED_HEAD, "Tensor x_bar, Tensor v_bar", "Tensor[]"))
def frame_dynamics_adjoint_op(state, external_force, model, poses, *settings_and_seeds):
    """Registered op ``ams_torch::frame_dynamics_adjoint``: the vector-Jacobian product of
    :func:`frame_dynamics_diff_op` for the output adjoints x_bar, v_bar (..., S, N, 3). Default (any
    device): the torch definition's; CPU / CUDA: the native adjoint kernel. Returns [x̄, v̄, ḡhost_rest
    (each like x), external force (like x, or an empty tensor without one), mass (S, N), drag (S, N),
    edge (S, N−1), bend (S, N−2), torsion (S, N−3), integrity (S, N), angular (S, N−1), poses
    (P, M + 1, 12), sag_offset (like x), the non-Hookean transition, breaking point and soft ratio (3,)]."""
    *settings, x_bar, v_bar = settings_and_seeds
    return _torch_vjp(state, external_force, model, poses, settings, x_bar, v_bar)


def _adjoint_kernel(state, external_force, model, poses, *settings_and_seeds):
    *settings, gx, gv = settings_and_seeds
    ns = _namespace(state[0])
    if ns is None or not _native_ok(settings[3], settings[4], settings[5]):
        return _torch_vjp(state, external_force, model, poses, settings, gx, gv)
    out = ns.frame_adjoint(state, external_force, model, poses, *settings, gx, gv)
    g_poses = out[11].sum(1)  # (B, M + 1, 12): every strand's share
    if poses.shape[0] == 1:
        g_poses = g_poses.sum(0, keepdim=True)
    return [out[0], out[1], out[2], out[3]] + [g.sum(0) for g in out[4:11]] + [g_poses, out[12],
                                                                              out[13].sum((0, 1))]


frame_dynamics_adjoint_op.register_kernel("cpu")(_adjoint_kernel)
frame_dynamics_adjoint_op.register_kernel("cuda")(_adjoint_kernel)


@frame_dynamics_adjoint_op.register_fake
def _adjoint_fake(state, external_force, model, poses, *settings_and_seeds):
    x = state[0]
    like = lambda t: torch.empty_like(t, memory_format=torch.contiguous_format)  # noqa: E731
    ext = like(x) if external_force is not None else x.new_empty(0)
    return [like(x), like(x), like(x), ext] + [like(model[MODEL_FIELDS.index(f)]) for f in _GRAD_FIELDS] + \
        [like(poses), like(x), x.new_empty(3)]


def _backward(ctx, gx, gv):
    saved = ctx.saved_tensors
    state = list(saved[:4])
    model = list(saved[4:4 + ctx.n_model])
    poses = saved[4 + ctx.n_model]
    ext = saved[5 + ctx.n_model] if ctx.has_ext else None
    x = state[0]
    gx = torch.zeros_like(x) if gx is None else gx.contiguous()
    gv = torch.zeros_like(x) if gv is None else gv.contiguous()
    out = frame_dynamics_adjoint_op(state, ext, model, poses, *ctx.settings, gx, gv)
    g_model: list = [None] * len(model)
    for j, name in enumerate(_GRAD_FIELDS):
        g_model[MODEL_FIELDS.index(name)] = out[4 + j]
    for j, name in enumerate(_LAW_FIELDS):
        i = MODEL_FIELDS.index(name)
        g_model[i] = out[13][j].reshape(model[i].shape)
    return [out[0], out[1], out[2], out[12]], (out[3] if ctx.has_ext else None), g_model, out[11], \
        *([None] * len(ctx.settings))


frame_dynamics_diff_op.register_autograd(_backward, setup_context=_setup_context)


# -- entry point --------------------------------------------------------------------------------
def native_adjoint_supported(model: Model, coeffs: Coefficients, config: Config, x: torch.Tensor,
                             external_force: ExternalForce = None) -> bool:
    """Whether a gradient frame's dynamics can run the native forward and adjoint: the angular couple
    (or no angular spring), a tensor external force (or none), float32 /
    float64 on CPU / CUDA, a rest shape without gradients, and the adjoint kernels built (built on
    first call; one warning when they cannot be)."""
    if config.angular and not config.angular_reaction:
        return False
    if external_force is not None and not isinstance(external_force, torch.Tensor):
        return False
    if model.rest_positions.dtype != x.dtype:
        return False
    if any(getattr(model, f).requires_grad for f in ("rest_positions", "edge_rest_length", "bend_rest_length",
                                                     "torsion_rest_length", "segment_length", "gravity")):
        return False
    return native_available("frame_adjoint", x.device, x.dtype)


def native_frame_dynamics_diff(model: Model, coeffs: Coefficients, config: Config, x: torch.Tensor,
                               v: torch.Tensor, ghost_rest: torch.Tensor, sag_offset: torch.Tensor, pose0: Pose,
                               pose1: Pose, hermite: bool, time: torch.Tensor,
                               external_force: ExternalForce = None) -> tuple:
    """One frame of strand dynamics, differentiable, by the native forward and adjoint; arguments and
    result as :func:`ams_torch.sim.dynamics.frame_dynamics` (x, v, ghost_rest, sag_offset (..., S, N, 3);
    returns (x, v)). Inputs :func:`native_adjoint_supported` rejects take ``frame_dynamics`` itself."""
    if not native_adjoint_supported(model, coeffs, config, x, external_force):
        return frame_dynamics(model, coeffs, config, x, v, ghost_rest, sag_offset, pose0, pose1, hermite, time,
                              external_force)
    state, ext, model_list, _, *settings = op_arguments(model, coeffs, config, x, v, ghost_rest, sag_offset, pose0,
                                                        pose1, hermite, external_force)
    hermite = bool(hermite and pose0.has_velocity and pose1.has_velocity)
    poses = substep_pose_tensor(pose0, pose1, hermite, config.substeps, config.dt, x)
    return frame_dynamics_diff_op(state, ext, model_list, poses, *settings[:-1])


def native_frame_contact_diff(model: Model, coeffs: Coefficients, config: Config, x: torch.Tensor,
                              v: torch.Tensor, ghost_rest: torch.Tensor, sag_offset: torch.Tensor, pose0: Pose,
                              pose1: Pose, hermite: bool, time: torch.Tensor, external_force: ExternalForce = None,
                              contact=None) -> tuple:
    """One frame of strand dynamics with the contact response after every substep
    (``Params(contact="substep")``), differentiable: substep by substep, the fused frame kernel of one
    substep (its M + 1 substep poses sliced from the frame's, no follow-the-leader) with its native
    adjoint (:func:`frame_dynamics_diff_op`), then ``contact(x, v, pose, h)`` (the collision op and its
    native adjoint: :func:`~ams_torch.sim.native_collide_grad.substep_contact_diff`), and follow-the-leader at the
    frame's end on the torch definition. The same arithmetic as
    :func:`~ams_torch.sim.dynamics.frame_dynamics` with ``contact``: one substep of M depends on the
    frame only through its two poses (ghosts, pin targets, the sag-free offset are recomputed from
    them). Arguments and result as that function; inputs :func:`native_adjoint_supported` rejects take
    it itself."""
    if not native_adjoint_supported(model, coeffs, config, x, external_force):
        return frame_dynamics(model, coeffs, config, x, v, ghost_rest, sag_offset, pose0, pose1, hermite, time,
                              external_force, contact=contact)
    state, ext, model_list, _, *settings = op_arguments(model, coeffs, config, x, v, ghost_rest, sag_offset, pose0,
                                                        pose1, hermite, external_force)
    hermite = bool(hermite and pose0.has_velocity and pose1.has_velocity)
    m_sub = config.substeps
    poses = substep_pose_tensor(pose0, pose1, hermite, m_sub, config.dt, x)
    pose_list = substep_poses(pose0, pose1, hermite, m_sub, config.dt)
    h = config.dt / m_sub
    one = list(settings[:-1])
    one[FrameSettings._fields.index("dt")] = h
    one[FrameSettings._fields.index("substeps")] = 1
    one[FrameSettings._fields.index("inextensibility")] = False
    rest_of_state = list(state[2:])
    for s in range(m_sub):
        x, v = frame_dynamics_diff_op([x, v] + rest_of_state, ext, model_list, poses[:, s:s + 2].contiguous(), *one)
        if contact is not None:
            x, v = contact(x, v, pose1 if s + 1 == m_sub else pose_list[s + 1], h)
    if config.inextensibility:  # pose1's rotation carries the fallback directions
        if native_collisions_diff_supported(model, x, config):
            x, v = native_inextensibility_diff(model, config, x, v, pose_list[-1])
        else:
            x, v = inextensibility(model, config, x, v, pose_list[-1], config.dt)
    return x, v
