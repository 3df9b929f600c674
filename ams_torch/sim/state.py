"""What changes during a run (:class:`State`), what the user drives per frame (:class:`Control`)
and the frozen settings of the step (:class:`Config`).

One owner per datum (STYLE.md): the fixed per-groom tensors live in
:class:`~ams_torch.sim.model.Model`; everything that differs between scenes of one groom or
between frames lives here. State and Control are frozen dataclasses of tensors (registered as
pytrees), so :func:`ams_torch.sim.stepping.step` is a pure function that ``torch.compile`` and CUDA
graphs can capture; Config holds Python values only, and the step branches on it alone.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable, Optional, Tuple, Union

import torch
import torch.utils._pytree as pytree

from ams_torch.geometry.pose import Pose

__all__ = ["State", "Control", "Config", "ExternalForce"]

#: A force (..., S, N, 3) newtons, held over the frame, or ``f(x, v, t) -> force`` evaluated at
#: every substep (x, v: (..., S, N, 3); t: 0-d tensor, seconds since the start).
ExternalForce = Union[None, torch.Tensor, Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]]


@dataclass(frozen=True)
class State:
    """What changes during a run; tensors may carry leading scene dims ``...`` (B scenes of one groom).

    Fields:
        x: (..., S, N, 3) m, world positions.
        v: (..., S, N, 3) m/s, world velocities.
        ghost_rest: (..., S, N, 3) m, the ghosts' rest shape in the head frame: the groom's rest
            shape plus the plastic offset (non-Hookean yield, SPEC §7) plus ``sag_offset``. The
            ghosts in the world are ``pose.to_world(ghost_rest)``.
        sag_offset: (..., S, N, 3) m, head frame: the sag-free offset of this scene (SPEC §5),
            ``Rᵀ(−m g / κ_I)`` with the head rotation R at t = 0; fixed after
            :meth:`~ams_torch.Simulator.initial_state`. The non-Hookean law measures elongation from
            the anchors ``ghost_rest − sag_offset``.
        pose: the head pose at this state's time, with velocities.
        time: () s since the start (a tensor, so the step never specialises on it).
        frame: () int64, frames simulated so far.
        diverged_frame: () int64, the first frame at which the divergence guard saw a non-finite or
            exploding particle, −1 while none did. Set inside the step without a host sync; the
            simulator reads it every ``check_every`` frames (:func:`ams_torch.sim.stepping.check_state`).
        diverged_input: () bool, whether the input of that frame (state or external force) was
            already non-finite: then the cause is the data given to the simulator, not stability.
        overflow_frame: () int64, the first frame whose hair occupied more blocks than the hair–hair
            grid holds (``HairHair.max_blocks``; those frames left the blocks beyond it out), −1
            while none did; set inside the step like ``diverged_frame`` and read by the same check.
            ``None`` (a state made without it) counts as −1.
    """

    x: torch.Tensor
    v: torch.Tensor
    ghost_rest: torch.Tensor
    sag_offset: torch.Tensor
    pose: Pose
    time: torch.Tensor
    frame: torch.Tensor
    diverged_frame: torch.Tensor
    diverged_input: torch.Tensor
    overflow_frame: Optional[torch.Tensor] = None

    def replace(self, **changes) -> "State":
        """A copy with some fields changed (``time``/``frame`` may be given as numbers)."""
        for name in ("time", "frame", "diverged_frame", "diverged_input", "overflow_frame"):
            if name in changes and changes[name] is not None and not isinstance(changes[name], torch.Tensor):
                old = getattr(self, name) if getattr(self, name) is not None else self.diverged_frame
                changes[name] = torch.as_tensor(changes[name], dtype=old.dtype, device=old.device)
        return replace(self, **changes)

    def ghosts(self) -> torch.Tensor:
        """World positions of the ghosts, (..., S, N, 3) m."""
        return self.pose.to_world(self.ghost_rest)

    def detach(self) -> "State":
        """The same state cut from the autograd graph (e.g. between truncated backprop windows)."""
        return pytree.tree_map(lambda t: t.detach() if isinstance(t, torch.Tensor) else t, self)

    @property
    def batch_shape(self) -> torch.Size:
        """The leading scene dims ``...`` of x."""
        return self.x.shape[:-3]


@dataclass(frozen=True)
class Control:
    """What the user drives for one frame.

    Fields:
        pose: the head pose at the end of the frame; velocities optional (without them they come
            from the change of pose over the frame, and substeps interpolate linearly). ``None``:
            the head stays where it is, at rest.
        collider_poses: one entry per collider (``None`` keeps the collider's own pose): world
            poses, or poses relative to the head for colliders with ``follow_head``.
        time: () s, the time at the start of the frame (the state's time).
        external_force: see :data:`ExternalForce`; ``None`` for none.
    """

    pose: Optional[Pose] = None
    collider_poses: Tuple[Optional[Pose], ...] = ()
    time: Optional[torch.Tensor] = None
    external_force: ExternalForce = None


@dataclass(frozen=True)
class Config:
    """Frozen settings of the step: plain Python values, decided when the simulator is built.
    The step branches on these only, never on data.

    Fields:
        dt: frame length, s. substeps: M (Δt' = dt / M).
        integrity_model: "hookean" or "nonhookean" (SPEC §7); "none" when κ_I is exactly 0.
        angular: the angular spring is on (κ_α not exactly 0).
        angular_reaction, implicit_angular, geometric_stiffness, inextensibility: see
            :class:`~ams_torch.Params`.
        ftl_damping: Müller's velocity-correction factor of follow-the-leader.
        collision_rounds: rounds of edge-length restore + push-out after the contact response.
        contact: "frame" or "substep" (``Params.contact``): whether the contact response also
            runs after every substep.
        hair_hair: the hair–hair stage runs. colliders: number of colliders (0: no collision stage).
        max_relative_speed: m/s, the divergence guard's speed limit relative to the head.
        backend: "torch" (the differentiable definition) or "native" (the fused kernels of
            :mod:`ams_torch.sim.native`; a frame whose inputs require grad runs its dynamics on the
            native forward and adjoint of :mod:`ams_torch.sim.native_grad` and its other stages on
            the torch definition); the simulator resolves its "auto" to one of them when it is built.
    """

    dt: float
    substeps: int = 1
    integrity_model: str = "hookean"
    angular: bool = True
    angular_reaction: bool = True
    implicit_angular: bool = True
    geometric_stiffness: bool = False
    inextensibility: bool = True
    ftl_damping: float = 0.9
    collision_rounds: int = 1
    contact: str = "frame"
    colliders: int = 0
    hair_hair: bool = False
    max_relative_speed: float = 1.0e3
    backend: str = "torch"

    @property
    def substep_dt(self) -> float:
        """Δt' = dt / M, seconds."""
        return self.dt / self.substeps

    @property
    def nonhookean(self) -> bool:
        return self.integrity_model == "nonhookean"


pytree.register_dataclass(State)
