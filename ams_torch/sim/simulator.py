"""The user-facing simulator: a thin ``torch.nn.Module`` over the pure step of :mod:`integrator`."""
from __future__ import annotations

from typing import Iterable, Optional, Sequence

import torch

from ams_torch.sim import integrator
from ams_torch.sim.model import State, build_model
from ams_torch.stages.collide import Collider, CollisionStage
from ams_torch.stages.hair_hair import HairHair, build_hair_hair, make_stage
from ams_torch.sim.params import Params
from ams_torch.geometry.pose import Pose

__all__ = ["Simulator"]


class Simulator(torch.nn.Module):
    """Simulate a groom with the AMS model.

    Args:
        rest_positions: (S, N, 3) metres, rest shape in the head frame (array or tensor).
        params: :class:`Params` (SI units); defaults to ``Params()``.
        device, dtype: where and in what precision to simulate (float32 by default).
        pose: the head pose at t = 0 (default: identity, at rest).
        hair_hair: :class:`HairHair` settings to enable hair–hair interaction (SPEC §6);
            ``None`` (default) allocates no grid and runs no grid code.
        colliders: colliders for the hair–solid stage (SPEC §8), e.g. ``MeshCollider``,
            ``SphereCollider``; an empty list or None builds no SDF and runs no collision code.

    Usage::

        sim = Simulator(rest, Params(), device="cuda")
        state = sim.initial_state()
        for pose in poses:
            state = sim.step(state, pose)      # state.x, state.v: (S, N, 3)
    """

    def __init__(self, rest_positions, params: Optional[Params] = None, *, device=None,
                 dtype: torch.dtype = torch.float32, pose: Optional[Pose] = None,
                 hair_hair: Optional[HairHair] = None, colliders: Optional[Sequence[Collider]] = None):
        super().__init__()
        self.params = params if params is not None else Params()
        self.device = torch.device(device) if device is not None else torch.device("cpu")
        self.dtype = dtype
        self.initial_pose = (pose or Pose.identity()).to(device=self.device, dtype=dtype)
        self.model = build_model(rest_positions, self.params, device=self.device, dtype=dtype,
                                 initial_pose=self.initial_pose)
        self.stages: list = []  # run after inextensibility, in SPEC §4 order
        m = self.model
        self.hair_hair = hair_hair
        self.hair_hair_grid = build_hair_hair(hair_hair, m.rest_positions, m.particle_mass,
                                              device=self.device, dtype=dtype)
        if self.hair_hair_grid is not None:
            self.stages.append(make_stage(self.hair_hair_grid, m.particle_mass, ~m.pinned))
        self.colliders = list(colliders or [])
        restore = None
        if self.params.inextensibility and self.params.collision_inextensibility:
            restore = lambda x, v, pose, dt: integrator.inextensibility(m, self.params, x, v, pose, dt)  # noqa: E731
        self.collision_stage = CollisionStage(self.colliders, free=~m.pinned, restore_lengths=restore,
                                              restore_rounds=self.params.collision_inextensibility) \
            if self.colliders else None
        if self.collision_stage is not None:
            self.stages.append(self.collision_stage)

    # -- state ---------------------------------------------------------------------------
    def initial_state(self, pose: Optional[Pose] = None) -> State:
        """The groom at rest in its grown shape, moving rigidly with ``pose`` (default: the
        simulator's initial pose). The pose may carry scene batch dims (B, 3, 3): the state is
        then (B, S, N, 3). Ghosts get the sag-free offset (SPEC §5) when ``params.sag_free``."""
        pose = (pose or self.initial_pose).to(device=self.device, dtype=self.dtype)
        if not pose.has_velocity:
            z = torch.zeros_like(pose.translation)
            pose = pose.with_velocity(z, z.clone())
        m = self.model
        batch = pose.rotation.shape[:-2]
        rest = m.rest_positions.expand(batch + m.rest_positions.shape)
        x = pose.to_world(rest)
        v = pose.velocity_at(x)
        ghost_rest = rest
        kappa = self.params.integrity_stiffness
        if self.params.sag_free and not (not isinstance(kappa, torch.Tensor) and float(kappa) == 0.0):
            k = torch.as_tensor(kappa, dtype=self.dtype, device=self.device)
            k = k[..., None] if k.dim() > 0 else k
            offset_world = (-m.particle_mass[..., None] * m.gravity / k).expand_as(rest)
            ghost_rest = rest + pose.unrotate(offset_world)
        return State(x=x, v=v, ghost_rest=ghost_rest.clone(), pose=pose)

    # -- dynamics -----------------------------------------------------------------------
    def step(self, state: State, pose: Optional[Pose] = None, external_force=None,
             collider_poses=None) -> State:
        """Advance one frame of ``params.dt`` seconds.

        Args:
            state: current state.
            pose: head pose at the end of the frame (None: the head stays still).
            external_force: (..., S, N, 3) newtons, or ``f(x, v, t) -> force``.
            collider_poses: new poses for the colliders, in force from this frame on (a list
                aligned with ``colliders``; None entries keep a collider's pose). They replace
                each collider's ``pose``: world poses, or poses relative to the head for colliders
                with ``follow_head=True`` (see ``colliders.resolve_world_poses``).
        Returns:
            the new :class:`State` (``.x``, ``.v``: (..., S, N, 3)).
        Raises:
            SimulationDiverged: the state became non-finite or exploded (names frame and strands).
        """
        if collider_poses is not None:
            if self.collision_stage is None:
                raise ValueError("collider_poses given but the simulator has no colliders")
            self.collision_stage.collider_poses = collider_poses
        return integrator.step(self.model, self.params, state, pose, external_force, self.stages)

    forward = step

    def rollout(self, state: State, poses: Iterable[Optional[Pose]], external_force=None,
                progress: bool = False) -> tuple:
        """Run one step per pose. Returns (final state, positions (F, ..., S, N, 3))."""
        poses = list(poses)
        it: Sequence = poses
        if progress:
            from tqdm.auto import tqdm

            it = tqdm(poses, desc="simulating", unit="frame")
        xs = []
        for pose in it:
            state = self.step(state, pose, external_force)
            xs.append(state.x)
        return state, torch.stack(xs) if xs else state.x.new_zeros((0,) + tuple(state.x.shape))
