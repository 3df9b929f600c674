"""Simulation parameters (SI units) and their validation."""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace
from typing import Tuple, Union

import torch

__all__ = ["Params", "PARAM_PRESETS"]

#: Named speed–accuracy presets for :meth:`Params.preset`, chosen from the measured Pareto fronts
#: of ``scripts/bench_tradeoff.py`` (see docs/tradeoff.md for the numbers and the rule).
#: ``params``: the :class:`Params` fields a preset sets. ``settings``: what goes with it but is
#: not a Params field: particles per strand N (resample the groom to it), the dtype of the
#: :class:`~ams_torch.Simulator`, and the hair–hair grid resolution R (``HairHair(resolution=R)``)
#: where the scene has hair–hair interaction.
PARAM_PRESETS = {
    "fast": {"params": {"substeps": 1},
             "settings": {"particles": 16, "dtype": "float32", "hair_hair_resolution": 32}},
    "balanced": {"params": {"substeps": 2},
                 "settings": {"particles": 64, "dtype": "float32", "hair_hair_resolution": 32}},
    "accurate": {"params": {"substeps": 4},
                 "settings": {"particles": 64, "dtype": "float32", "hair_hair_resolution": 32}},
}

Scalar = Union[float, torch.Tensor]


def _min_value(v) -> float:
    if isinstance(v, torch.Tensor):
        return float(v.detach().min()) if v.numel() else 0.0
    return float(v)


def _is_finite(v) -> bool:
    if isinstance(v, torch.Tensor):
        return bool(torch.isfinite(v.detach()).all())
    return math.isfinite(float(v))


@dataclass
class Params:
    """Parameters of the AMS model, SI units throughout (m, kg, s, N).

    Library defaults use a particle mass of 1e-6 kg (one simulated strand stands for a
    small wisp) and the stiffness-to-mass ratios of the paper's Table 1 defaults
    (κ_L/m = 1e6 s⁻², κ_I/m = 1e2 s⁻², κ_α/m = 1e2 s⁻² rad⁻¹), so the dynamics match the
    paper's unit-mass values. :meth:`paper` gives the paper's own units (mass 1).
    Stiffness-type fields may be tensors (e.g. requiring grad, or per strand (S, 1)).

    Fields:
        stretch_stiffness: κ_L, N/m, stiffness of the edge springs (pairs i, i+1).
        bend_scale, torsion_scale: multipliers of κ_L for the bending (i, i+2) and
            torsion (i, i+3) springs (SPEC §2 allows a per-kind scale).
        integrity_stiffness: κ_I, N/m, zero-rest-length spring particle → ghost (SPEC §3).
        integrity_model: "hookean" (default, linear) or "nonhookean" (SPEC §7: Hookean up to
            ``integrity_transition``, softer up to ``integrity_break``, plastic beyond; see
            :func:`forces.integrity_force_nonhookean`).
        integrity_transition: elongation (particle–ghost distance over the local rest segment
            length, dimensionless) where the curve starts to soften; default 0.5 (50 %).
        integrity_break: elongation of the breaking point, > transition; beyond it the ghost's
            rest offset moves (once per frame) so the elongation stays there; default 1.0.
        integrity_soft_ratio: slope of the soft branch at the breaking point relative to κ_I,
            in (0, 1]; default 0.25.
        angular_stiffness: κ_α, N/rad, angular spring toward the ghost segment (SPEC §3).
        particle_mass: kg per particle.
        drag: linear drag rate γ/m, 1/s (force −drag·m·v, world air at rest).
        dt: frame length, s.
        substeps: M, backward-Euler substeps per frame (Δt' = dt / M).
        gravity: (gx, gy, gz), m/s², world frame (+y is up).
        num_pinned: particles from the root that follow the head rigidly (SPEC §1).
        sag_free: offset the ghosts so the integrity springs hold the weight at t = 0 (§5).
        geometric_stiffness: add the positive part of each spring's geometric stiffness,
            ``κ (1 − l/|d|)₊ (I − d̂d̂ᵀ)``, to the matrix (SPEC §4). The frozen-direction
            linearisation alone can gain energy in single steps with transverse motion (measured
            up to +17 % of the current energy); with this option no step gains energy. Off by
            default (the SPEC form); docs/tradeoff.md measures its cost and accuracy.
        implicit_angular: add the angular spring's tangent stiffness κ_α/|e| (I − êêᵀ) to
            the matrix (SPD, keeps stiff angular springs stable at large dt).
        angular_reaction: apply the angular spring as a couple (−κ_α θ t̂ on x_i as well as
            +κ_α θ t̂ on x_{i+1}); False is the paper's one-particle force, which is not
            conservative and makes free wisps flutter (see :func:`forces.angular_force`).
        inextensibility: apply follow-the-leader length projection after the substeps.
        collision_inextensibility: with colliders (and ``inextensibility``), this many rounds
            of edge-length restore (follow-the-leader) + push-out after the collision response,
            so contact does not leave stretched edges (see ``sim.step.collisions``); 0 = none.
        ftl_damping: Müller et al. 2012 velocity-correction factor s_damping ∈ [0, 1].
        max_relative_speed: m/s; a particle faster than this relative to the head's
            rigid motion is reported as divergence.
        check_every: run the divergence guard every this many frames (0 = never; the
            guard costs one host sync per check).
    """

    stretch_stiffness: Scalar = 1.0
    bend_scale: Scalar = 1.0
    torsion_scale: Scalar = 1.0
    integrity_stiffness: Scalar = 1e-4
    integrity_model: str = "hookean"
    integrity_transition: float = 0.5
    integrity_break: float = 1.0
    integrity_soft_ratio: float = 0.25
    angular_stiffness: Scalar = 1e-4
    particle_mass: Scalar = 1e-6
    drag: Scalar = 1.5
    dt: float = 1.0 / 60.0
    substeps: int = 1
    gravity: Tuple[float, float, float] = (0.0, -9.81, 0.0)
    num_pinned: int = 2
    sag_free: bool = True
    geometric_stiffness: bool = False
    implicit_angular: bool = True
    angular_reaction: bool = True  # see forces.angular_force: the one-way form flutters
    inextensibility: bool = True
    collision_inextensibility: int = 1
    ftl_damping: float = 0.9
    max_relative_speed: float = 1.0e3
    check_every: int = 1

    def __post_init__(self) -> None:
        self.validate()

    # -- validation --------------------------------------------------------------------
    def validate(self) -> "Params":
        """Raise ``ValueError`` naming the first invalid field."""
        for name in ("stretch_stiffness", "bend_scale", "torsion_scale", "integrity_stiffness",
                     "angular_stiffness", "drag"):
            v = getattr(self, name)
            if not _is_finite(v):
                raise ValueError(f"Params.{name} must be finite; got {v}")
            if _min_value(v) < 0:
                raise ValueError(f"Params.{name} must be non-negative (stiffness/drag); got {v}")
        if not _is_finite(self.particle_mass) or _min_value(self.particle_mass) <= 0:
            raise ValueError(f"Params.particle_mass must be positive (kg); got {self.particle_mass}")
        if self.integrity_model not in ("hookean", "nonhookean"):
            raise ValueError(f"Params.integrity_model must be 'hookean' or 'nonhookean'; got {self.integrity_model!r}")
        for name in ("integrity_transition", "integrity_break", "integrity_soft_ratio"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ValueError(f"Params.{name} must be a finite number; got {v!r}")
        if not self.integrity_transition > 0:
            raise ValueError(f"Params.integrity_transition must be positive; got {self.integrity_transition}")
        if not self.integrity_break > self.integrity_transition:
            raise ValueError(f"Params.integrity_break must exceed integrity_transition "
                             f"({self.integrity_transition}); got {self.integrity_break}")
        if not 0.0 < self.integrity_soft_ratio <= 1.0:
            raise ValueError(f"Params.integrity_soft_ratio must lie in (0, 1]; got {self.integrity_soft_ratio}")
        if not (isinstance(self.dt, (int, float)) and math.isfinite(self.dt) and self.dt > 0):
            raise ValueError(f"Params.dt must be a positive number of seconds; got {self.dt}")
        if isinstance(self.substeps, bool) or not isinstance(self.substeps, int) or self.substeps < 1:
            raise ValueError(f"Params.substeps must be a positive integer; got {self.substeps!r}")
        if isinstance(self.num_pinned, bool) or not isinstance(self.num_pinned, int) or self.num_pinned < 0:
            raise ValueError(f"Params.num_pinned must be a non-negative integer; got {self.num_pinned!r}")
        if len(tuple(self.gravity)) != 3 or not all(math.isfinite(float(g)) for g in self.gravity):
            raise ValueError(f"Params.gravity must be three finite numbers (m/s²); got {self.gravity}")
        if isinstance(self.collision_inextensibility, bool) or not isinstance(self.collision_inextensibility, int) \
                or self.collision_inextensibility < 0:
            raise ValueError(f"Params.collision_inextensibility must be a non-negative integer; "
                             f"got {self.collision_inextensibility!r}")
        if not 0.0 <= self.ftl_damping <= 1.0:
            raise ValueError(f"Params.ftl_damping must lie in [0, 1]; got {self.ftl_damping}")
        if not self.max_relative_speed > 0:
            raise ValueError(f"Params.max_relative_speed must be positive (m/s); got {self.max_relative_speed}")
        if self.check_every < 0:
            raise ValueError(f"Params.check_every must be >= 0; got {self.check_every}")
        return self

    # -- variants ----------------------------------------------------------------------
    def replace(self, **changes) -> "Params":
        """A copy with some fields changed (validated)."""
        unknown = set(changes) - {f.name for f in fields(self)}
        if unknown:
            raise ValueError(f"unknown Params field(s): {sorted(unknown)}")
        return replace(self, **changes)

    def ms(self) -> "Params":
        """Plain mass-spring (Selle et al.) for comparisons: κ_I = κ_α = 0, no ghost offset."""
        return self.replace(integrity_stiffness=0.0, angular_stiffness=0.0, sag_free=False)

    @staticmethod
    def paper(**changes) -> "Params":
        """The paper's units (SPEC §10): particle mass 1, κ_L = 1e6, κ_I = 1e2, κ_α = 1e2."""
        base = dict(particle_mass=1.0, stretch_stiffness=1e6, integrity_stiffness=1e2,
                    angular_stiffness=1e2, drag=1.5)
        base.update(changes)
        return Params(**base)

    @staticmethod
    def preset(name: str, **changes) -> "Params":
        """A named speed–accuracy preset: ``"fast"``, ``"balanced"`` or ``"accurate"``.

        Returns the library defaults (SI units) with the preset's fields (``PARAM_PRESETS[name]
        ["params"]``, e.g. ``substeps``) and then ``changes`` applied, validated. Use it with the
        settings of :meth:`preset_settings` (particles per strand, dtype, hair–hair grid).
        Raises ``ValueError`` for an unknown name (listing the names) or an invalid field.

        Example: ``Params.preset("balanced", drag=2.0)``.
        """
        if name not in PARAM_PRESETS:
            raise ValueError(f"unknown Params preset {name!r}; choose one of {', '.join(PARAM_PRESETS)}")
        merged = dict(PARAM_PRESETS[name]["params"])
        merged.update(changes)
        return Params().replace(**merged)

    @staticmethod
    def preset_settings(name: str) -> dict:
        """What goes with :meth:`preset` but is not a Params field: ``{"particles": N,
        "dtype": "float32" | "float64", "hair_hair_resolution": R}`` (a copy). Raises
        ``ValueError`` for an unknown name."""
        if name not in PARAM_PRESETS:
            raise ValueError(f"unknown Params preset {name!r}; choose one of {', '.join(PARAM_PRESETS)}")
        return dict(PARAM_PRESETS[name]["settings"])

    @property
    def substep_dt(self) -> float:
        return self.dt / self.substeps

    def to_dict(self) -> dict:
        """JSON-friendly dict (tensors become lists)."""
        out = {}
        for k, v in asdict(self).items():
            out[k] = v.detach().cpu().tolist() if isinstance(v, torch.Tensor) else (list(v) if isinstance(v, tuple) else v)
        return out
