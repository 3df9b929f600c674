"""The fixed part of a simulation (rest data, topology) and the changing part (state).

Builder → Model → State (STYLE.md): :func:`build_model` validates a rest groom and makes a
:class:`Model` that never changes during a run and has no scene batch dimension; a
:class:`State` holds only what changes and may carry leading scene dims ``...``.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Optional

import numpy as np
import torch

from ams_torch.sim.params import Params
from ams_torch.geometry.pose import Pose

__all__ = ["Model", "State", "build_model", "check_rest_positions", "MIN_PARTICLES"]

MIN_PARTICLES = 4  # torsion springs couple i and i+3
MIN_SEGMENT = 1e-9  # m; shorter rest segments are degenerate


def _first_index(mask: torch.Tensor) -> tuple:
    idx = torch.nonzero(mask, as_tuple=False)
    return tuple(int(i) for i in idx[0])


def check_rest_positions(x, name: str = "rest_positions") -> torch.Tensor:
    """Validate a groom's rest positions and return them as a tensor.

    x: (S, N, 3) metres (array-like). Raises ``ValueError`` naming the problem and where:
    wrong shape, too few particles, NaN/Inf, zero-length (degenerate) segments.
    """
    if isinstance(x, np.ndarray) or not isinstance(x, torch.Tensor):
        try:
            x = torch.as_tensor(np.asarray(x, dtype=np.float64))
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{name} must be a numeric array of shape (S, N, 3): {exc}") from None
    if x.dim() != 3 or x.shape[-1] != 3:
        raise ValueError(f"{name} must have shape (S, N, 3) (strands, particles, xyz); got {tuple(x.shape)}")
    s, n, _ = x.shape
    if s < 1:
        raise ValueError(f"{name} has no strands (shape {tuple(x.shape)})")
    if n < MIN_PARTICLES:
        raise ValueError(
            f"{name} has {n} particles per strand; at least {MIN_PARTICLES} are needed "
            f"(torsion springs couple particles i and i+3)"
        )
    if not x.is_floating_point():
        x = x.double()
    bad = ~torch.isfinite(x)
    if bad.any():
        si, pi, _ = _first_index(bad)
        count = int(bad.any(-1).any(-1).sum())
        raise ValueError(
            f"{name} contains NaN/Inf: first at strand {si}, particle {pi} ({count} strand(s) affected)"
        )
    seg = (x[:, 1:] - x[:, :-1]).norm(dim=-1)
    degenerate = seg <= MIN_SEGMENT
    if degenerate.any():
        si, pi = _first_index(degenerate)
        raise ValueError(
            f"{name} has a zero-length (degenerate) segment: strand {si}, between particles {pi} and {pi + 1} "
            f"(length {float(seg[si, pi]):.3g} m)"
        )
    return x


@dataclass(frozen=True)
class Model:
    """Fixed data of a groom, no scene batch dimension (all tensors on one device/dtype).

    Fields:
        rest_positions: (S, N, 3) m, rest shape X̄ in the head frame.
        rest_lengths: tuple of 3 tensors, (S, N−k) m, rest lengths of the springs between
            particles i and i+k for k = 1 (edge), 2 (bending), 3 (torsion).
        particle_mass: (S, N) kg.
        pinned: (N,) bool, particles that follow the head rigidly (the first ``num_pinned``).
        ghost_rest: (S, N, 3) m, ghost rest shape in the head frame at t = 0: X̄ plus the
            sag-free offset (SPEC §5) when enabled.
        gravity: (3,) m/s², world frame.
    """

    rest_positions: torch.Tensor
    rest_lengths: tuple
    particle_mass: torch.Tensor
    pinned: torch.Tensor
    ghost_rest: torch.Tensor
    gravity: torch.Tensor

    @property
    def num_strands(self) -> int:
        return self.rest_positions.shape[0]

    @property
    def num_particles(self) -> int:
        return self.rest_positions.shape[1]

    @property
    def edge_rest_length(self) -> torch.Tensor:
        return self.rest_lengths[0]

    @property
    def num_pinned(self) -> int:
        return int(self.pinned.sum())


@dataclass(frozen=True)
class State:
    """What changes during a run. Tensors may carry leading scene dims ``...``.

    Fields:
        x: (..., S, N, 3) m, world positions.
        v: (..., S, N, 3) m/s, world velocities.
        ghost_rest: (..., S, N, 3) m, ghost rest shape in the head frame (the ghosts in the
            world are ``pose.to_world(ghost_rest)``); changes only through plasticity.
        pose: the head pose at this state's time (with velocities).
        time: seconds since the start.
        frame: frames simulated so far.
    """

    x: torch.Tensor
    v: torch.Tensor
    ghost_rest: torch.Tensor
    pose: Pose
    time: float = 0.0
    frame: int = 0

    def replace(self, **changes) -> "State":
        return replace(self, **changes)

    def ghosts(self) -> torch.Tensor:
        """World positions of the ghosts, (..., S, N, 3) m."""
        return self.pose.to_world(self.ghost_rest)

    def detach(self) -> "State":
        return replace(self, x=self.x.detach(), v=self.v.detach(), ghost_rest=self.ghost_rest.detach())


def sag_free_offset(mass: torch.Tensor, gravity: torch.Tensor, integrity_stiffness, rotation: torch.Tensor):
    """Ghost offset that makes the integrity springs hold each particle's weight (SPEC §5).

    ``y_i = x_i − m_i g / κ_I`` (g points down, so the ghost sits above its particle), returned
    in the head frame: ``Rᵀ (−m g / κ_I)``. mass: (S, N) kg; gravity (3,); rotation (3, 3) the
    head's rotation at t = 0. Returns (S, N, 3) m.
    """
    kappa = torch.as_tensor(integrity_stiffness, dtype=mass.dtype, device=mass.device)
    if kappa.dim() > 0:  # per strand (S, 1) or per particle (S, N)
        kappa = kappa[..., None]
    world = -mass[..., None] * gravity / kappa
    return world @ rotation  # row vectors: (Rᵀ w)ᵀ = wᵀ R


def build_model(rest_positions, params: Params, *, device=None, dtype=torch.float32,
                initial_pose: Optional[Pose] = None) -> Model:
    """Validate a rest groom and build its :class:`Model`.

    rest_positions: (S, N, 3) metres in the head frame. ``initial_pose`` is the head pose at
    t = 0 (needed for the world direction of gravity in the sag-free offset).
    """
    params.validate()
    x = check_rest_positions(rest_positions)
    s, n, _ = x.shape
    if params.num_pinned >= n:
        raise ValueError(f"Params.num_pinned = {params.num_pinned} must be smaller than the particles per strand ({n})")
    x = x.to(device=device, dtype=dtype)
    rest_lengths = tuple((x[:, k:] - x[:, :-k]).norm(dim=-1) for k in (1, 2, 3))
    for k, l in zip((2, 3), rest_lengths[1:]):
        if (l <= MIN_SEGMENT).any():
            si, pi = _first_index(l <= MIN_SEGMENT)
            raise ValueError(
                f"rest_positions: particles {pi} and {pi + k} of strand {si} coincide; their "
                f"{'bending' if k == 2 else 'torsion'} spring has zero rest length"
            )
    mass = torch.as_tensor(params.particle_mass, device=device, dtype=dtype)
    mass = mass.expand(s, n).clone() if mass.dim() < 2 else mass.expand(s, n).clone()
    pinned = torch.zeros(n, dtype=torch.bool, device=device)
    pinned[: params.num_pinned] = True
    gravity = torch.as_tensor(params.gravity, device=device, dtype=dtype)
    pose = (initial_pose or Pose.identity(device=device, dtype=dtype)).to(device=device, dtype=dtype)
    ghost = x
    kappa_i = params.integrity_stiffness
    if params.sag_free:
        if _all_zero(kappa_i):
            import warnings

            warnings.warn("Params.sag_free is on but integrity_stiffness is 0: the sag-free offset "
                          "(m g / κ_I) is undefined, so no offset is applied", stacklevel=3)
        else:
            kappa = torch.as_tensor(kappa_i, device=device, dtype=dtype)
            ghost = x + sag_free_offset(mass, gravity, kappa, pose.rotation)
    return Model(rest_positions=x, rest_lengths=rest_lengths, particle_mass=mass, pinned=pinned,
                 ghost_rest=ghost, gravity=gravity)


def _all_zero(v) -> bool:
    if isinstance(v, torch.Tensor):
        return bool((v == 0).all())
    return float(v) == 0.0
