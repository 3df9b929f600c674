"""The frame step: one pure function ``step(model, state, control, config) -> State`` (SPEC §4).

Order within a frame: the strand dynamics (M substeps and follow-the-leader,
:mod:`ams_torch.sim.dynamics`), then hair–hair interaction (SPEC §6), then hair–solid
collisions with their edge-length restore (SPEC §8), then the pinned particles take the head's
velocity, the non-Hookean plastic yield (SPEC §7) updates the ghosts, and the divergence flag is
updated. Nothing is modified in place; there is no host synchronisation (no ``.item()``, no
data-dependent branches or shapes): Python branches read ``config`` only, so the step can be
compiled with ``torch.compile(fullgraph=True)`` and captured in a CUDA graph.

Profiler labels (``torch.profiler.record_function``): ``ams_torch.dynamics``,
``ams_torch.hair_hair``, ``ams_torch.collisions`` (and inside the dynamics ``ams_torch.assembly``,
``ams_torch.springs``, ``ams_torch.biphasic``, ``ams_torch.solve``, ``ams_torch.inextensibility``).
"""
from __future__ import annotations

import functools
from contextlib import nullcontext
from typing import Optional, Sequence

import torch
from torch.profiler import record_function

from ams_torch.geometry.pose import Pose
from ams_torch.sim import forces
from ams_torch.sim.contact import collisions_world, substep_contact
from ams_torch.sim.dynamics import frame_dynamics
from ams_torch.sim.finish import native_finish, pin_and_speed
from ams_torch.sim.native import native_collisions, native_frame_dynamics
from ams_torch.sim.native_grad import native_frame_dynamics_diff
from ams_torch.sim.native_contact import native_frame_contact
from ams_torch.sim.model import Coefficients, Model, coefficients
from ams_torch.sim.state import Config, Control, State
from ams_torch.stages.collide import resolve_world_poses
from ams_torch.stages.hair_hair import hair_hair_stage

__all__ = ["step", "resolve_pose", "collisions", "plastic_update", "check_state", "SimulationDiverged",
           "GridOverflow"]


class SimulationDiverged(FloatingPointError):
    """The state became non-finite or exploded. ``.frame`` and ``.strands`` say where;
    ``.bad_input`` says whether the data given to the simulator was already non-finite."""

    def __init__(self, message: str, frame: int, strands: list, bad_input: bool = False):
        super().__init__(message)
        self.frame = frame
        self.strands = strands
        self.bad_input = bad_input


class GridOverflow(SimulationDiverged):
    """The hair occupied more blocks than the hair–hair grid holds (a static capacity,
    ``HairHair.max_blocks``): from ``.frame`` on, the blocks beyond it were left out of the
    hair–hair stage. ``.capacity`` is the grid's capacity in blocks of 4³ cells."""

    def __init__(self, message: str, frame: int, capacity: int):
        super().__init__(message, frame=frame, strands=[])
        self.capacity = capacity


def resolve_pose(prev: Pose, pose: Optional[Pose], dt) -> tuple:
    """The end-of-frame pose with velocities, and whether substeps use Hermite interpolation.

    ``pose=None`` keeps the head where it is, at rest. A pose without velocities gets the
    ones implied by the change of pose over the frame (and linear interpolation).
    """
    if pose is None:
        z = torch.zeros_like(prev.translation)
        return Pose(prev.rotation, prev.translation, z, z.clone(), check=False), False
    if pose.has_velocity:
        return pose, prev.has_velocity
    lin = (pose.translation - prev.translation) / dt
    ang = prev.relative_rotvec(pose) / dt
    return pose.with_velocity(lin, ang), False


def collisions(model: Model, config: Config, x: torch.Tensor, v: torch.Tensor, head_pose: Pose,
               collider_poses: Sequence[Optional[Pose]], native: bool = False) -> tuple:
    """The collision stage (SPEC §8): the colliders' world poses for this frame
    (:func:`~ams_torch.stages.collide.resolve_world_poses`), then the response and the edge-length
    restore (:func:`~ams_torch.sim.contact.collisions_world`, or its fused native kernel).
    x, v: (..., S, N, 3) m, m/s. Returns the new (x, v)."""
    poses = resolve_world_poses(list(model.colliders), head_pose, list(collider_poses) or None)
    if native:
        return native_collisions(model, config, x, v, head_pose, poses)
    return collisions_world(model, config, x, v, head_pose, poses)


def plastic_update(model: Model, coeffs: Coefficients, x: torch.Tensor, ghost_rest: torch.Tensor,
                   sag_offset: torch.Tensor, pose: Pose) -> torch.Tensor:
    """Yield of the non-Hookean integrity coupling (SPEC §7), once per frame.

    x: (..., S, N, 3) m world positions at the end of the frame; ghost_rest, sag_offset:
    (..., S, N, 3) m head frame; pose: the head pose at the end of the frame. Returns the new
    ghost_rest: where a free particle's elongation (from its anchor ``ghost_rest − sag_offset``)
    exceeds the breaking point, the anchor moves (permanently) so the elongation is exactly it.
    """
    anchor = ghost_rest - sag_offset
    new_anchor = forces.integrity_yield(pose.to_local(x), anchor, model.segment_length, coeffs.breaking,
                                        ~model.pinned)
    return new_anchor + sag_offset


def _nonfinite(*tensors) -> torch.Tensor:
    """() bool: whether any of the tensors holds NaN/Inf (one sum each: NaN and ±Inf propagate)."""
    total = tensors[0].sum()
    for t in tensors[1:]:
        total = total + t.sum()
    return ~torch.isfinite(total)


def _finish(model: Model, config: Config, state: State, control: Control, x, v, pose: Pose,
            native: bool = False, speed: Optional[torch.Tensor] = None) -> tuple:
    """The end of a frame: pinned particles take the head's rigid velocity, and the divergence
    flag is updated (device-side; :mod:`ams_torch.sim.finish`, its fused kernel when ``native``;
    ``speed`` given: v is already finished, fused into the dynamics' kernel).
    Returns (v, diverged_frame, diverged_input)."""
    if speed is None:
        v, speed = (native_finish(model, x, v, pose) if native else pin_and_speed(x, v, model.pinned, pose))
    # NaN/Inf in x or v makes the largest relative speed NaN (amax propagates it), and NaN <= limit
    # is False: one comparison catches both non-finite and exploding particles
    bad = ~(speed.amax() <= config.max_relative_speed)
    inputs = [state.x, state.v]
    if isinstance(control.external_force, torch.Tensor):
        inputs.append(control.external_force)
    first = (state.diverged_frame < 0) & bad
    frame = torch.where(first, state.frame + 1, state.diverged_frame)
    bad_input = torch.where(first, _nonfinite(*inputs), state.diverged_input)
    return v, frame, bad_input


def _needs_grad(state: State, coeffs: Coefficients, control: Control, pose: Pose) -> bool:
    """Whether any input of this frame requires grad (metadata only: no host sync)."""
    if not torch.is_grad_enabled():
        return False
    tensors = [state.x, state.v, state.ghost_rest, state.sag_offset, pose.rotation, pose.translation, *coeffs]
    if isinstance(control.external_force, torch.Tensor):
        tensors.append(control.external_force)
    return any(isinstance(t, torch.Tensor) and t.requires_grad for t in tensors)


def stage_backend(config: Config, state: State, coeffs: Coefficients, control: Control, pose: Pose) -> str:
    """"torch" when the config says so or an input requires grad (gradients stay exact on the torch
    definition; a native config's dynamics then run the native forward and adjoint, the other stages
    the torch definition), else the config's "native" (SPEC §15)."""
    if config.backend == "torch" or _needs_grad(state, coeffs, control, pose):
        return "torch"
    return config.backend


def _label(name: str):
    """The stage's profiler label while a profiler runs (or the step is being compiled); nothing
    otherwise (record_function costs ~10 µs a stage even when no profiler listens)."""
    if torch.compiler.is_compiling() or torch._C._autograd._profiler_enabled():
        return record_function(f"ams_torch.{name}")
    return nullcontext()


def step(model: Model, state: State, control: Control, config: Config, timer=None) -> State:
    """Advance one frame of ``config.dt`` seconds (SPEC §4). Pure: returns a new state.

    Args:
        model: the groom's fixed data (and the stages' fixed data: ``model.hair_hair`` grid,
            ``model.colliders``).
        state: the current state (x, v: (..., S, N, 3)).
        control: the frame's head pose, collider poses, time and external force.
        config: the frozen settings (the only thing Python branches on).
        timer: optional ``timer(stage_name)`` returning a context manager around each stage
            ("dynamics", "hair_hair", "collisions"), e.g. to measure wall time per stage
            (``ams_torch.apps.scene.simulate``); default: profiler labels only.
    Returns:
        the new :class:`State`.
    """
    stage = timer or _label
    dt = config.dt
    pose0 = state.pose
    pose1, hermite = resolve_pose(pose0, control.pose, dt)
    coeffs = coefficients(model)
    time = state.time if control.time is None else control.time
    backend = stage_backend(config, state, coeffs, control, pose1)
    native = backend == "native"  # the fused kernels (they keep the torch definition for what they cannot run)
    # a gradient frame of a native simulator: the dynamics keep their fused kernel, with its native
    # adjoint (sim/native_grad.py); the other stages take the torch definition
    adjoint = not native and config.backend == "native"
    speed = None
    contact = None  # Params(contact="substep"): the contact response after every substep
    if config.contact == "substep" and config.colliders:
        contact = functools.partial(substep_contact, model, config, collider_poses=control.collider_poses)
    with stage("dynamics"):
        args = (model, coeffs, config, state.x, state.v, state.ghost_rest, state.sag_offset, pose0, pose1, hermite,
                time, control.external_force)
        if adjoint and contact is None:  # the native adjoint covers the dynamics without substep contact
            x, v = native_frame_dynamics_diff(*args)
        elif not native:
            x, v = frame_dynamics(*args, contact=contact)
        elif contact is not None:
            x, v = native_frame_contact(*args, collider_poses=control.collider_poses)
        elif config.hair_hair or config.colliders:
            x, v = native_frame_dynamics(*args)
        else:  # nothing runs after the dynamics: the frame's end is fused into its kernel
            x, v, speed = native_frame_dynamics(*args, finish=pose1, pinned=model.pinned)
    overflow_frame, next_frame = state.overflow_frame, state.frame + 1
    if config.hair_hair:
        with stage("hair_hair"):
            x, v, overflow = hair_hair_stage(model.hair_hair, x, v, coeffs.mass, pose1, dt, ~model.pinned,
                                             backend="auto" if native else "torch", with_overflow=True)
        before = overflow_frame if overflow_frame is not None else torch.full_like(state.frame, -1)
        overflow_frame = torch.where(overflow & (before < 0), next_frame, before)
    if config.colliders:
        with stage("collisions"):
            x, v = collisions(model, config, x, v, pose1, control.collider_poses, native)
    v, diverged_frame, diverged_input = _finish(model, config, state, control, x, v, pose1, native, speed)
    ghost_rest = state.ghost_rest
    if config.nonhookean:
        ghost_rest = plastic_update(model, coeffs, x, ghost_rest, state.sag_offset, pose1)
    return State(x=x, v=v, ghost_rest=ghost_rest, sag_offset=state.sag_offset, pose=pose1, time=time + dt,
                 frame=next_frame, diverged_frame=diverged_frame, diverged_input=diverged_input,
                 overflow_frame=overflow_frame)


def check_state(state: State, config: Config, grid=None) -> None:
    """Divergence guard, outside the step (one host sync): raise :class:`SimulationDiverged`
    naming the first bad frame and the strands now non-finite or faster than
    ``config.max_relative_speed`` relative to the head, if the state's flag is set; or
    :class:`GridOverflow` if the hair–hair grid overflowed first (``grid``: the model's
    :class:`~ams_torch.stages.hair_hair.HairHairGrid`, for the message)."""
    frame = int(state.diverged_frame)
    overflow = -1 if state.overflow_frame is None else int(state.overflow_frame)  # on a GPU: synced already
    if overflow >= 0 and (frame < 0 or overflow <= frame):
        _raise_overflow(overflow, grid)
    if frame < 0:
        return
    x, v = state.x, state.v
    finite = torch.isfinite(x).all(-1).all(-1) & torch.isfinite(v).all(-1).all(-1)
    rel = torch.nan_to_num(v - state.pose.velocity_at(x), nan=0.0, posinf=0.0, neginf=0.0)
    fast = rel.norm(dim=-1).amax(-1) > config.max_relative_speed
    idx = torch.nonzero(~finite | fast, as_tuple=False).tolist()
    kind = "non-finite positions/velocities" if bool((~finite).any()) else \
        f"speeds above max_relative_speed = {config.max_relative_speed:g} m/s"
    bad_input = bool(state.diverged_input)
    where = f" in {len(idx)} strand(s); first (index: [scene..., strand]) {idx[:8]}" if idx else ""
    if bad_input:
        advice = ("The input of that frame (the state or the external force) already held NaN/Inf: "
                  "check the initial state and the controls given to the simulator.")
    else:
        advice = "Try more substeps, a smaller dt or lower stiffness."
    raise SimulationDiverged(f"simulation diverged at frame {frame}: {kind}{where}. {advice}", frame=frame,
                             strands=idx, bad_input=bad_input)


def _raise_overflow(frame: int, grid) -> None:
    capacity = getattr(grid, "capacity", -1)
    if capacity > 0:
        whole = grid.blocks_per_axis ** 3
        held = (f"the grid's static capacities (max_blocks: {capacity} blocks of 4³ cells, of {whole} in the whole "
                f"grid; max_active_cells: {grid.active_capacity} cells that carry the pressure)")
    else:
        held = "the grid's static capacities (max_blocks, max_active_cells)"
    raise GridOverflow(f"hair–hair grid overflow at frame {frame}: the hair needed more than {held}, and from that "
                       f"frame on what did not fit was left out of the hair–hair stage. Give the grid more room: "
                       f"HairHair(max_blocks=..., max_active_cells=...), or a larger block_margin (the automatic "
                       f"capacities are block_margin × what the rest groom needs).", frame=frame, capacity=capacity)
