"""Time integration of one frame (SPEC §4, paper Algorithm 1) as pure functions.

``step(model, params, state, pose)`` returns a new :class:`~ams_torch.sim.model.State`; nothing
is modified in place. Per frame of length Δt with M substeps (Δt' = Δt/M), each substep
assembles and solves the linearised backward-Euler system in its symmetric form

    [(m_i + Δt'γ_i) I + Δt'² Σ_j κ_ij D_ij + Δt'² H_i] v_i − Σ_j Δt'² κ_ij D_ij v_j
        = m_i v_iⁿ + Δt' (f_elastic + f_biphasic + f_ext) + Δt'² (ghost-velocity terms)

then the positions are advanced; after the substeps come inextensibility and the optional
stages (hair–hair, collisions) in the order of SPEC §4.

Profiler labels (``torch.profiler.record_function``; no effect on the results) mark the pieces
of a frame: ``ams_torch.springs`` (edge/bend/torsion forces and Jacobian blocks),
``ams_torch.biphasic`` (integrity and angular couplings to the ghosts), ``ams_torch.assembly``
(the whole :func:`assemble_system`, the two above included), ``ams_torch.solve`` (the banded
solve) and ``ams_torch.inextensibility`` (follow-the-leader). :func:`ams_torch.apps.scene.simulate`
adds ``ams_torch.step``, ``ams_torch.stages.hair_hair`` and ``ams_torch.collisions``.
"""
from __future__ import annotations

from typing import Callable, Optional, Sequence, Union

import torch
import torch.nn.functional as F
from torch.profiler import record_function

from ams_torch.sim import forces
from ams_torch.sim.inextensibility import follow_the_leader
from ams_torch.sim.model import Model, State
from ams_torch.solver.op import solve_banded
from ams_torch.sim.params import Params
from ams_torch.geometry.pose import Pose
from ams_torch.solver.reference import banded_matvec

__all__ = ["assemble_system", "substep", "local_segment_length", "integrity_plastic_update", "inextensibility", "step",
           "SimulationDiverged", "check_state", "resolve_pose"]

ExternalForce = Union[None, torch.Tensor, Callable[[torch.Tensor, torch.Tensor, float], torch.Tensor]]
# a stage: (x, v, pose_at_end_of_frame, dt, state_before) -> (x, v)
Stage = Callable[[torch.Tensor, torch.Tensor, Pose, float, State], tuple]


class SimulationDiverged(FloatingPointError):
    """The state became non-finite or exploded. ``.frame`` and ``.strands`` say where."""

    def __init__(self, message: str, frame: int, strands: list):
        super().__init__(message)
        self.frame = frame
        self.strands = strands


def _is_zero(v) -> bool:
    return (not isinstance(v, torch.Tensor)) and float(v) == 0.0


def _per_particle(k, like: torch.Tensor):
    """A stiffness that may be a tensor (S, 1)/(S, N), shaped to multiply (..., S, N, 3, 3)."""
    k = torch.as_tensor(k, dtype=like.dtype, device=like.device)
    return k[..., None, None] if k.dim() > 0 else k


def _pad_n(t: torch.Tensor, before: int, after: int) -> torch.Tensor:
    """Zero-pad (..., S, M, 3, 3) along the particle dim M."""
    return F.pad(t, (0, 0, 0, 0, before, after))


def assemble_system(model: Model, params: Params, x: torch.Tensor, v: torch.Tensor,
                    ghost: torch.Tensor, ghost_velocity: torch.Tensor, pin_velocity: torch.Tensor,
                    h: float, external_force: Optional[torch.Tensor] = None,
                    ghost_offset: Optional[torch.Tensor] = None):
    """Assemble one substep's SPD block-heptadiagonal system for every strand.

    Args:
        x, v: (..., S, N, 3) positions (m) and velocities (m/s) at the substep start.
        ghost: (..., S, N, 3) m, ghost positions y at the substep start (world).
        ghost_velocity: (..., S, N, 3) m/s, ghost velocities w over the substep.
        pin_velocity: (..., S, N, 3) m/s, prescribed velocities (read on pinned particles).
        h: substep length Δt', s.
        external_force: (..., S, N, 3) N or None.
        ghost_offset: (..., S, N, 3) m, world sag-free offset of the ghosts from the particles'
            rest anchors (only read by the non-Hookean integrity law; None = zero).
    Returns:
        blocks: (..., S, N, 4, 3, 3) lower band, ``blocks[..., i, k] = A[i, i-k]``, kg.
        rhs: (..., S, N, 3), kg·m/s.
    """
    with record_function("ams_torch.assembly"):
        return _assemble_system(model, params, x, v, ghost, ghost_velocity, pin_velocity, h, external_force,
                                ghost_offset)


def _assemble_system(model: Model, params: Params, x, v, ghost, ghost_velocity, pin_velocity, h: float,
                     external_force=None, ghost_offset=None):
    m = model.particle_mass
    eye = torch.eye(3, dtype=x.dtype, device=x.device)
    gamma = params.drag * m if not _is_zero(params.drag) else None

    force = forces.gravity_force(m, model.gravity).expand_as(x)
    if external_force is not None:
        force = force + external_force
    m_eff = m + h * gamma if gamma is not None else m
    diag = m_eff[..., None, None] * eye
    offdiag = []
    scales = (1.0, params.bend_scale, params.torsion_scale)
    with record_function("ams_torch.springs"):
        for k in (1, 2, 3):
            kappa = params.stretch_stiffness * scales[k - 1]
            f, stiff = forces.spring_forces(x, model.rest_lengths[k - 1], kappa, k, params.geometric_stiffness)
            force = force + f
            hk = (h * h) * stiff  # (..., S, N-k, 3, 3)
            diag = diag + _pad_n(hk, 0, k) + _pad_n(hk, k, 0)
            offdiag.append(_pad_n(-hk, k, 0))
    rhs = m[..., None] * v
    with record_function("ams_torch.biphasic"):
        force, diag, offdiag, rhs = _biphasic_terms(model, params, x, v, ghost, ghost_velocity, h, ghost_offset,
                                                    eye, force, diag, offdiag, rhs)
    return _finish_system(model, x, pin_velocity, h, eye, force, diag, offdiag, rhs)


def _biphasic_terms(model: Model, params: Params, x, v, ghost, ghost_velocity, h: float, ghost_offset, eye,
                    force, diag, offdiag, rhs):
    """Add the integrity and angular couplings (SPEC §3, §7) to the force, the block diagonal,
    the first sub-diagonal and the right-hand side; returns them (unchanged when κ_I = κ_α = 0)."""
    if not _is_zero(params.integrity_stiffness) and params.integrity_model == "nonhookean":
        kappa_i = torch.as_tensor(params.integrity_stiffness, dtype=x.dtype, device=x.device)
        k3 = kappa_i[..., None] if kappa_i.dim() > 0 else kappa_i
        offset = ghost_offset if ghost_offset is not None else torch.zeros_like(x)
        f_i, tangent, _ = forces.integrity_force_nonhookean(
            x, ghost - offset, k3 * offset, kappa_i, local_segment_length(model),
            params.integrity_transition, params.integrity_break, params.integrity_soft_ratio)
        force = force + f_i
        diag = diag + (h * h) * tangent
        rhs = rhs + (h * h) * torch.einsum("...ij,...j->...i", tangent, ghost_velocity)
    elif not _is_zero(params.integrity_stiffness):
        kappa_i = params.integrity_stiffness
        force = force + forces.integrity_force(x, ghost, kappa_i)
        ki = _per_particle(kappa_i, x)
        diag = diag + (h * h) * ki * eye
        rhs = rhs + (h * h) * (ki[..., 0] if ki.dim() > 0 else ki) * ghost_velocity
    if not _is_zero(params.angular_stiffness):
        f_a, tangent = forces.angular_force(x, ghost, params.angular_stiffness, params.angular_reaction)
        force = force + f_a
        if params.implicit_angular:
            ht = (h * h) * tangent
            dw = ghost_velocity[..., 1:, :] - ghost_velocity[..., :-1, :]
            if params.angular_reaction:
                # a couple on (i, i+1): same band structure as an edge spring with D → I − êêᵀ
                diag = diag + _pad_n(ht, 0, 1) + _pad_n(ht, 1, 0)
                offdiag[0] = offdiag[0] - _pad_n(ht, 1, 0)
                g = torch.einsum("...ij,...j->...i", ht, dw)
                rhs = rhs + F.pad(g, (0, 0, 1, 0)) - F.pad(g, (0, 0, 0, 1))
            else:
                # force on i+1 only: diagonal tangent, neighbour velocity taken explicitly
                rel = v[..., :-1, :] + dw
                diag = diag + _pad_n(ht, 1, 0)
                rhs = rhs + F.pad(torch.einsum("...ij,...j->...i", ht, rel), (0, 0, 1, 0))
    return force, diag, offdiag, rhs


def _finish_system(model: Model, x, pin_velocity, h: float, eye, force, diag, offdiag, rhs):
    """Add the forces to the right-hand side, stack the band and impose the pinned rows."""
    m = model.particle_mass
    rhs = rhs + h * force
    blocks = torch.stack([diag] + [o.expand_as(diag) for o in offdiag], -3)

    pinned = model.pinned
    if model.num_pinned:
        # Pinned rows become m_i I v_i = m_i v_pin; their coupling to free particles moves to
        # the right-hand side, so the matrix stays symmetric positive definite (SPEC §4).
        pmask = pinned[:, None].to(x.dtype)
        vp = pin_velocity * pmask
        rhs = rhs - banded_matvec(blocks, vp)
        free = ~pinned
        keep = [free]
        for k in (1, 2, 3):
            shifted = torch.cat((torch.zeros(k, dtype=torch.bool, device=x.device), free[:-k]))
            keep.append(free & shifted)
        keep = torch.stack(keep, -1)[:, :, None, None].to(x.dtype)  # (N, 4, 1, 1)
        pin_diag = (m[..., None, None] * eye)[..., None, :, :]
        pin_diag = F.pad(pin_diag, (0, 0, 0, 0, 0, 3))  # (..., S, N, 4, 3, 3), only k = 0 set
        blocks = blocks * keep + pin_diag * (pinned[:, None, None, None].to(x.dtype))
        rhs = torch.where(pinned[:, None], m[..., None] * pin_velocity, rhs)
    return blocks, rhs


def local_segment_length(model: Model) -> torch.Tensor:
    """(S, N) m: each particle's local rest segment length, the mean of its (one or two)
    adjacent edge rest lengths; the length unit of the integrity elongation (SPEC §7)."""
    e = model.edge_rest_length
    total = F.pad(e, (0, 1)) + F.pad(e, (1, 0))
    count = F.pad(torch.ones_like(e), (0, 1)) + F.pad(torch.ones_like(e), (1, 0))
    return total / count


def sag_offset_local(model: Model) -> torch.Tensor:
    """(S, N, 3) m: the sag-free ghost offset in the head frame (zero without sag-free)."""
    return model.ghost_rest - model.rest_positions


def integrity_plastic_update(model: Model, params: Params, x: torch.Tensor, ghost_rest: torch.Tensor,
                             pose: Pose) -> torch.Tensor:
    """Yield of the non-Hookean integrity coupling (SPEC §7), applied once per frame.

    x: (..., S, N, 3) m world positions at the end of the frame; ghost_rest: (..., S, N, 3) m
    head frame; pose: the head pose at the end of the frame. Returns the new ghost_rest: where
    a free particle's elongation exceeds ``params.integrity_break``, its ghost's rest offset moves
    (permanently) so the elongation is exactly the breaking point.
    """
    offset = sag_offset_local(model)
    anchor = ghost_rest - offset
    new_anchor = forces.integrity_yield(pose.to_local(x), anchor, local_segment_length(model),
                                        params.integrity_break, ~model.pinned)
    return new_anchor + offset


def substep(model: Model, params: Params, x, v, ghost, ghost_velocity, pin_velocity, h, external_force=None,
            ghost_offset=None):
    """One linearised backward-Euler substep: returns the new velocities (..., S, N, 3) m/s."""
    blocks, rhs = assemble_system(model, params, x, v, ghost, ghost_velocity, pin_velocity, h, external_force,
                                  ghost_offset)
    with record_function("ams_torch.solve"):
        return solve_banded(blocks, rhs)


def resolve_pose(prev: Pose, pose: Optional[Pose], dt: float, device, dtype) -> tuple:
    """The end-of-frame pose with velocities, and whether substeps use Hermite interpolation.

    ``pose=None`` keeps the head where it is, at rest. A pose without velocities gets the
    ones implied by the change of pose over the frame (and linear interpolation).
    """
    if pose is None:
        z = torch.zeros_like(prev.translation)
        return Pose(prev.rotation, prev.translation, z, z.clone()), False
    pose = pose.to(device=device, dtype=dtype)
    if pose.has_velocity:
        return pose, prev.has_velocity
    lin = (pose.translation - prev.translation) / dt
    ang = prev.relative_rotvec(pose) / dt
    return pose.with_velocity(lin, ang), False


def _external(external_force: ExternalForce, x, v, t):
    if external_force is None or isinstance(external_force, torch.Tensor):
        return external_force
    return external_force(x, v, t)


def inextensibility(model: Model, params: Params, x: torch.Tensor, v: torch.Tensor, pose: Pose, dt: float) -> tuple:
    """Restore every edge to its rest length (SPEC §4): follow-the-leader with Müller's velocity
    correction (``params.ftl_damping``); a collapsed edge takes its rest direction carried by
    ``pose`` (the head at the end of the frame). x, v: (..., S, N, 3) m, m/s; dt: the frame, s.
    Returns the new (x, v)."""
    with record_function("ams_torch.inextensibility"):
        rest = model.rest_positions.expand(x.shape[:-3] + model.rest_positions.shape)
        fallback = forces.safe_normalize(pose.rotate(rest[..., 1:, :] - rest[..., :-1, :]))[0]
        return follow_the_leader(x, v, model.edge_rest_length, model.pinned, dt, params.ftl_damping, fallback)


def check_state(state: State, model: Model, params: Params, where: str = "") -> None:
    """Divergence guard: raise :class:`SimulationDiverged` naming the frame and first bad strands
    if any position/velocity is non-finite or moves faster than ``params.max_relative_speed``
    relative to the head. Costs one host sync."""
    x, v = state.x, state.v
    finite = torch.isfinite(x).all(-1).all(-1) & torch.isfinite(v).all(-1).all(-1)
    rel = torch.nan_to_num(v - state.pose.velocity_at(x), nan=0.0, posinf=0.0, neginf=0.0)
    fast = rel.norm(dim=-1).amax(-1) > params.max_relative_speed
    bad = ~finite | fast
    if bool(bad.any()):
        idx = torch.nonzero(bad, as_tuple=False).tolist()
        first = idx[:8]
        kind = "non-finite positions/velocities" if bool((~finite).any()) else \
            f"speeds above max_relative_speed = {params.max_relative_speed:g} m/s"
        raise SimulationDiverged(
            f"simulation diverged at frame {state.frame}{where}: {kind} in {len(idx)} strand(s); "
            f"first (index: [scene..., strand]) {first}. Try more substeps, a smaller dt or lower stiffness.",
            frame=state.frame, strands=idx,
        )


def step(model: Model, params: Params, state: State, pose: Optional[Pose] = None,
         external_force: ExternalForce = None, stages: Sequence[Stage] = ()) -> State:
    """Advance one frame (SPEC §4). Pure: returns a new state.

    Args:
        model, params: the fixed data and parameters.
        state: the current state (x, v: (..., S, N, 3)).
        pose: head pose at the end of the frame (None: the head stays still).
        external_force: (..., S, N, 3) newtons, or a callable ``f(x, v, t) -> force``
            evaluated at each substep (wind, user forces).
        stages: callables ``(x, v, pose, dt, state) -> (x, v)`` run after inextensibility
            in order (hair–hair, then collisions).
    """
    dt = params.dt
    msub = params.substeps
    h = dt / msub
    x, v = state.x, state.v
    if x.shape[-3:] != model.rest_positions.shape or v.shape != x.shape:
        raise ValueError(f"state.x/v must have shape (..., {model.num_strands}, {model.num_particles}, 3); "
                         f"got x {tuple(x.shape)}, v {tuple(v.shape)}")
    pose0 = state.pose
    pose1, hermite = resolve_pose(pose0, pose, dt, x.device, x.dtype)
    start = pose0 if hermite else Pose(pose0.rotation, pose0.translation)
    end = pose1 if hermite else Pose(pose1.rotation, pose1.translation)
    pinned = model.pinned[:, None]
    rest = model.rest_positions
    batch = x.shape[:-3]
    if batch:
        rest = rest.expand(batch + rest.shape)
    pa = start
    y_a = pa.to_world(state.ghost_rest)
    nonhookean = params.integrity_model == "nonhookean" and not _is_zero(params.integrity_stiffness)
    offset_local = sag_offset_local(model) if nonhookean else None
    offset = pa.rotate(offset_local.expand(x.shape)) if nonhookean else None
    for s in range(msub):
        pb = start.interpolate(end, (s + 1) / msub, dt)
        y_b = pb.to_world(state.ghost_rest)
        w = (y_b - y_a) / h
        target = pb.to_world(rest)
        pin_v = torch.where(pinned, (target - x) / h, torch.zeros_like(x))
        f_ext = _external(external_force, x, v, state.time + s * h)
        v = substep(model, params, x, v, y_a, w, pin_v, h, f_ext, offset)
        x = torch.where(pinned, target, x + h * v)
        y_a = y_b
        if nonhookean:
            offset = pb.rotate(offset_local.expand(x.shape))
    if params.inextensibility:
        x, v = inextensibility(model, params, x, v, pose1, dt)
    for stage in stages:
        x, v = stage(x, v, pose1, dt, state)
    v = torch.where(pinned, pose1.velocity_at(x), v)
    ghost_rest = state.ghost_rest
    if nonhookean:
        ghost_rest = integrity_plastic_update(model, params, x, ghost_rest, pose1)
    new = State(x=x, v=v, ghost_rest=ghost_rest, pose=pose1, time=state.time + dt, frame=state.frame + 1)
    if params.check_every and new.frame % params.check_every == 0:
        check_state(new, model, params)
    return new
