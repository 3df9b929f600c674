"""The frame step: one pure function ``step(model, state, control, config) -> State`` (SPEC §4).

Order within a frame: the strand dynamics (M substeps and follow-the-leader,
:mod:`ams_torch.sim.dynamics`), then hair–hair interaction (SPEC §6), then hair–solid
collisions with their edge-length restore (SPEC §8), then the pinned particles take the head's
velocity, the non-Hookean plastic yield (SPEC §7) updates the ghosts, and the divergence flag is
updated. Nothing is modified in place; there is no host synchronisation (no ``.item()``, no
data-dependent branches or shapes): Python branches read ``config`` only, so the step can be
compiled with ``torch.compile(fullgraph=True)`` and captured in a CUDA graph.

The stages are a table, :data:`STAGES` (name, function ``Frame -> Frame``, condition on the
config): the step runs them in order. A study swaps or wraps one through the API instead of
copying the step::

    stages = replace_stage(STAGES, "collisions", my_collisions)       # my_collisions(frame) -> frame
    stages = wrap_stage(stages, "yield", lambda run: lambda f: count(run(f)))
    sim = Simulator(rest, params, stages=stages)                       # or step(..., stages=stages)

Profiler labels (``torch.profiler.record_function``): ``ams_torch.dynamics``,
``ams_torch.hair_hair``, ``ams_torch.collisions`` (and inside the dynamics ``ams_torch.assembly``,
``ams_torch.springs``, ``ams_torch.biphasic``, ``ams_torch.solve``, ``ams_torch.inextensibility``).
"""
from __future__ import annotations

import functools
from contextlib import nullcontext
from typing import Callable, NamedTuple, Optional, Sequence

import torch
from torch.profiler import record_function

from ams_torch.geometry.pose import Pose
from ams_torch.sim import forces
from ams_torch.sim.backends import frame_route
from ams_torch.sim.contact import collisions_world, substep_contact
from ams_torch.sim.dynamics import frame_dynamics
from ams_torch.sim.finish import (finish_op, native_finish, native_finish_diff_supported, native_yield_diff,
                                  pin_and_speed)
from ams_torch.sim.op_support import pose_tensors
from ams_torch.sim.native import native_collisions, native_frame_dynamics
from ams_torch.sim.native_collide_grad import (native_collisions_diff, native_collisions_diff_supported,
                                               substep_contact_diff)
from ams_torch.sim.native_grad import native_frame_contact_diff, native_frame_dynamics_diff
from ams_torch.sim.native_contact import native_frame_contact
from ams_torch.sim.model import Coefficients, Model, coefficients
from ams_torch.sim.state import Config, Control, State
from ams_torch.stages.collide import resolve_world_poses
from ams_torch.stages.hair_hair import hair_hair_stage as hair_hair_interaction

__all__ = ["step", "STAGES", "Stage", "Frame", "replace_stage", "wrap_stage", "begin_frame", "end_frame",
           "dynamics_stage", "hair_hair_stage", "collisions_stage", "finish_stage", "yield_stage", "resolve_pose",
           "collisions", "plastic_update", "check_state", "SimulationDiverged",
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
               collider_poses: Sequence[Optional[Pose]], native: bool = False, diff: bool = False) -> tuple:
    """The collision stage (SPEC §8): the colliders' world poses for this frame
    (:func:`~ams_torch.stages.collide.resolve_world_poses`), then the response and the edge-length
    restore (:func:`~ams_torch.sim.contact.collisions_world`, or its fused native kernel; with
    ``diff``, a gradient frame of a native simulator, the native kernel and its native adjoint
    where :func:`~ams_torch.sim.native_collide_grad.native_collisions_diff_supported` holds).
    x, v: (..., S, N, 3) m, m/s. Returns the new (x, v)."""
    poses = resolve_world_poses(list(model.colliders), head_pose, list(collider_poses) or None)
    if native:
        return native_collisions(model, config, x, v, head_pose, poses)
    if diff and len(model.colliders) and native_collisions_diff_supported(model, x, config):
        return native_collisions_diff(model, config, x, v, head_pose, poses)
    return collisions_world(model, config, x, v, head_pose, poses)


def plastic_update(model: Model, coeffs: Coefficients, x: torch.Tensor, ghost_rest: torch.Tensor,
                   sag_offset: torch.Tensor, pose: Pose, diff: bool = False) -> torch.Tensor:
    """Yield of the non-Hookean integrity coupling (SPEC §7), once per frame.

    x: (..., S, N, 3) m world positions at the end of the frame; ghost_rest, sag_offset:
    (..., S, N, 3) m head frame; pose: the head pose at the end of the frame. Returns the new
    ghost_rest: where a free particle's elongation (from its anchor ``ghost_rest − sag_offset``)
    exceeds the breaking point, the anchor moves (permanently) so the elongation is exactly it.
    ``diff``: a gradient frame of a native simulator (the yield's native adjoint,
    :func:`~ams_torch.sim.finish.native_yield_diff`).
    """
    anchor = ghost_rest - sag_offset
    yield_ = native_yield_diff if diff else forces.integrity_yield
    new_anchor = yield_(pose.to_local(x), anchor, model.segment_length, coeffs.breaking, ~model.pinned)
    return new_anchor + sag_offset


def _nonfinite(*tensors) -> torch.Tensor:
    """() bool: whether any of the tensors holds NaN/Inf (one sum each: NaN and ±Inf propagate)."""
    total = tensors[0].sum()
    for t in tensors[1:]:
        total = total + t.sum()
    return ~torch.isfinite(total)


def _finish(model: Model, config: Config, state: State, control: Control, x, v, pose: Pose,
            native: bool = False, speed: Optional[torch.Tensor] = None, diff: bool = False) -> tuple:
    """The end of a frame: pinned particles take the head's rigid velocity, and the divergence
    flag is updated (device-side; :mod:`ams_torch.sim.finish`, its fused kernel when ``native``,
    its kernel and native adjoint in a gradient frame of a native simulator (``diff``); ``speed``
    given: v is already finished, fused into the dynamics' kernel).
    Returns (v, diverged_frame, diverged_input)."""
    if speed is None:
        if native:
            v, speed = native_finish(model, x, v, pose)
        elif diff and native_finish_diff_supported(x, v, pose):
            (_, t, lin, ang), _ = pose_tensors(pose, x)
            v, speed = finish_op(x, v, model.num_pinned, [t, lin, ang])
        else:
            v, speed = pin_and_speed(x, v, model.pinned, pose)
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


def stage_backend(config: Config, needs_grad: bool) -> str:
    """The stages after the dynamics: "torch" when the config says so or an input requires grad
    (gradients stay exact on the torch definition), else the config's "native" (SPEC §15). The
    dynamics take their route from :func:`~ams_torch.sim.backends.frame_route`."""
    if config.backend == "torch" or needs_grad:
        return "torch"
    return config.backend


def _label(name: str):
    """The stage's profiler label while a profiler runs (or the step is being compiled); nothing
    otherwise (record_function costs ~10 µs a stage even when no profiler listens)."""
    if torch.compiler.is_compiling() or torch._C._autograd._profiler_enabled():
        return record_function(f"ams_torch.{name}")
    return nullcontext()


class Frame(NamedTuple):
    """What the stages of one frame hand along (immutable: a stage returns ``frame.replace(...)``).

    Fixed for the frame: model, config, state (at its start), control, pose1 (the head at its end,
    with velocities; :func:`resolve_pose`), hermite, coeffs (:func:`~ams_torch.sim.model.coefficients`),
    native (the stages after the dynamics run their native kernels), route (how the dynamics run:
    :func:`~ams_torch.sim.backends.frame_route`, a key of its ``FRAME_ROUTES``). Carried: x, v (..., S, N, 3) m, m/s; ghost_rest (..., S, N, 3) m head
    frame; speed (None, or the finished frame's largest relative speed when the dynamics' kernel
    finished it); overflow_frame, diverged_frame, diverged_input as in :class:`State` (None until
    the stage that sets them ran).
    """

    model: Model
    config: Config
    state: State
    control: Control
    pose1: Pose
    hermite: bool
    coeffs: Coefficients
    native: bool
    route: str
    x: torch.Tensor
    v: torch.Tensor
    ghost_rest: torch.Tensor
    speed: Optional[torch.Tensor] = None
    overflow_frame: Optional[torch.Tensor] = None
    diverged_frame: Optional[torch.Tensor] = None
    diverged_input: Optional[torch.Tensor] = None

    def replace(self, **changes) -> "Frame":
        return self._replace(**changes)


def _native_grad(f: Frame) -> bool:
    """Whether this is a gradient frame of a native simulator (its stages with a native adjoint run it)."""
    return f.config.backend == "native" and not f.native


def dynamics_stage(f: Frame) -> Frame:
    """The strand dynamics (SPEC §4): M substeps and follow-the-leader (:mod:`ams_torch.sim.dynamics`,
    or its fused kernel; with ``Params(contact="substep")`` the contact response after every
    substep). When no later stage moves the hair, the native kernel also finishes the frame."""
    model, config, state, control = f.model, f.config, f.state, f.control
    contact = None  # Params(contact="substep"): the contact response after every substep
    if config.contact == "substep" and config.colliders:
        run = substep_contact
        if _native_grad(f) and native_collisions_diff_supported(model, state.x, config):
            run = substep_contact_diff  # a gradient frame: the native collision forward and adjoint
        contact = functools.partial(run, model, config, collider_poses=control.collider_poses)
    args = (model, f.coeffs, config, state.x, state.v, state.ghost_rest, state.sag_offset, state.pose, f.pose1,
            f.hermite, f.state.time if control.time is None else control.time, control.external_force)
    speed = None
    if f.route == "native_adjoint":  # a gradient frame: the fused kernel and its native adjoint
        x, v = native_frame_dynamics_diff(*args)
    elif f.route == "native_adjoint_contact":  # the same, substep by substep, with the contact's adjoint
        x, v = native_frame_contact_diff(*args, contact=contact)
    elif f.route == "torch":
        x, v = frame_dynamics(*args, contact=contact)
    elif f.route == "native_contact":
        x, v = native_frame_contact(*args, collider_poses=control.collider_poses)
    elif f.route == "native":
        x, v = native_frame_dynamics(*args)
    else:  # "native_finish": nothing runs after the dynamics; the frame's end is fused into its kernel
        x, v, speed = native_frame_dynamics(*args, finish=f.pose1, pinned=model.pinned)
    return f.replace(x=x, v=v, speed=speed)


def hair_hair_stage(f: Frame) -> Frame:
    """Hair–hair interaction (SPEC §6) on the model's grid; records the first grid overflow."""
    x, v, overflow = hair_hair_interaction(f.model.hair_hair, f.x, f.v, f.coeffs.mass, f.pose1, f.config.dt,
                                     ~f.model.pinned, backend="auto" if (f.native or _native_grad(f)) else "torch",
                                     with_overflow=True, recompute=_native_grad(f))
    before = f.overflow_frame if f.overflow_frame is not None else torch.full_like(f.state.frame, -1)
    return f.replace(x=x, v=v, overflow_frame=torch.where(overflow & (before < 0), f.state.frame + 1, before))


def collisions_stage(f: Frame) -> Frame:
    """Hair–solid collisions and their edge-length restore (SPEC §8): :func:`collisions`."""
    x, v = collisions(f.model, f.config, f.x, f.v, f.pose1, f.control.collider_poses, f.native, _native_grad(f))
    return f.replace(x=x, v=v)


def finish_stage(f: Frame) -> Frame:
    """Pinned particles take the head's velocity; the divergence flag is updated (:func:`_finish`)."""
    v, frame, bad_input = _finish(f.model, f.config, f.state, f.control, f.x, f.v, f.pose1, f.native, f.speed,
                                  _native_grad(f))
    return f.replace(v=v, diverged_frame=frame, diverged_input=bad_input)


def yield_stage(f: Frame) -> Frame:
    """The non-Hookean plastic yield of the ghosts (SPEC §7): :func:`plastic_update`."""
    return f.replace(ghost_rest=plastic_update(f.model, f.coeffs, f.x, f.ghost_rest, f.state.sag_offset, f.pose1,
                                               _native_grad(f)))


class Stage(NamedTuple):
    """One stage of the frame: ``run(frame) -> frame``; it runs when ``enabled(config)``; ``timed``:
    the step's ``timer`` (or profiler label) wraps it under ``name``."""

    name: str
    run: Callable[[Frame], Frame]
    enabled: Callable[[Config], bool] = lambda config: True
    timed: bool = False


#: The frame's stages in order (SPEC §4): the step runs each enabled one. A study swaps or wraps a
#: stage through :func:`replace_stage` / :func:`wrap_stage` and gives the sequence to
#: :func:`step` (``stages=``) or to the simulator (``Simulator(..., stages=...)``).
STAGES = (
    Stage("dynamics", dynamics_stage, timed=True),
    Stage("hair_hair", hair_hair_stage, lambda config: config.hair_hair, timed=True),
    Stage("collisions", collisions_stage, lambda config: config.colliders > 0, timed=True),
    Stage("finish", finish_stage),
    Stage("yield", yield_stage, lambda config: config.nonhookean),
)


def replace_stage(stages: Sequence[Stage], name: str, run: Callable[[Frame], Frame]) -> tuple:
    """The sequence with stage ``name``'s function replaced by ``run`` (its condition and label kept)."""
    names = [s.name for s in stages]
    if name not in names:
        raise ValueError(f"no stage named {name!r}; the stages are {names}")
    return tuple(s._replace(run=run) if s.name == name else s for s in stages)


def wrap_stage(stages: Sequence[Stage], name: str, wrapper: Callable) -> tuple:
    """The sequence with stage ``name`` run through ``wrapper(run) -> run`` (e.g. to count or log)."""
    run = next((s.run for s in stages if s.name == name), None)
    if run is None:
        raise ValueError(f"no stage named {name!r}; the stages are {[s.name for s in stages]}")
    return replace_stage(stages, name, wrapper(run))


def begin_frame(model: Model, state: State, control: Control, config: Config) -> Frame:
    """The frame's fixed inputs: end pose, coefficients, backend choice (:func:`stage_backend`)."""
    pose1, hermite = resolve_pose(state.pose, control.pose, config.dt)
    coeffs = coefficients(model)
    needs_grad = _needs_grad(state, coeffs, control, pose1)
    native = stage_backend(config, needs_grad) == "native"
    # the one decision for the dynamics (a gradient frame of a native simulator keeps the fused
    # kernel with its native adjoint, sim/native_grad.py; the other stages take the torch definition)
    route = frame_route(config, needs_grad)
    return Frame(model=model, config=config, state=state, control=control, pose1=pose1, hermite=hermite,
                 coeffs=coeffs, native=native, route=route, x=state.x, v=state.v, ghost_rest=state.ghost_rest,
                 overflow_frame=state.overflow_frame)


def end_frame(f: Frame) -> State:
    """The new :class:`State` from a frame whose stages ran."""
    s = f.state
    time = s.time if f.control.time is None else f.control.time
    return State(x=f.x, v=f.v, ghost_rest=f.ghost_rest, sag_offset=s.sag_offset, pose=f.pose1,
                 time=time + f.config.dt, frame=s.frame + 1, diverged_frame=f.diverged_frame,
                 diverged_input=f.diverged_input, overflow_frame=f.overflow_frame)


def step(model: Model, state: State, control: Control, config: Config, timer=None,
         stages: Sequence[Stage] = STAGES) -> State:
    """Advance one frame of ``config.dt`` seconds (SPEC §4). Pure: returns a new state.

    Args:
        model: the groom's fixed data (and the stages' fixed data: ``model.hair_hair`` grid,
            ``model.colliders``).
        state: the current state (x, v: (..., S, N, 3)).
        control: the frame's head pose, collider poses, time and external force.
        config: the frozen settings (the only thing Python branches on).
        timer: optional ``timer(stage_name)`` returning a context manager around each timed stage
            ("dynamics", "hair_hair", "collisions"), e.g. to measure wall time per stage
            (``ams_torch.apps.scene.simulate``); default: profiler labels only.
        stages: the frame's stages (default :data:`STAGES`: dynamics, hair–hair, collisions,
            finish, yield), each run when its condition on ``config`` holds.
    Returns:
        the new :class:`State`.
    """
    label = timer or _label
    f = begin_frame(model, state, control, config)
    for s in stages:
        if s.enabled(config):
            if s.timed:
                with label(s.name):
                    f = s.run(f)
            else:
                f = s.run(f)
    return end_frame(f)


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
