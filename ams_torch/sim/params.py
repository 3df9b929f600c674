"""Simulation parameters (SI units) and their validation."""
from __future__ import annotations

import math
import numbers
from dataclasses import asdict, dataclass, fields, replace
from typing import Tuple, Union

import numpy as np
import torch

__all__ = ["Params", "PARAM_PRESETS", "PAPER_UNITS"]

#: Named speed–accuracy presets for :meth:`Params.preset`, chosen from the measured Pareto fronts
#: of ``scripts/bench_tradeoff.py`` (see docs/tradeoff.md for the numbers and the rule).
#: ``params``: the :class:`Params` fields a preset sets. ``settings``: what goes with it but is
#: not a Params field: particles per strand N (resample the groom to it), the dtype of the
#: :class:`~ams_torch.Simulator`, and the hair–hair grid resolution R (``HairHair(resolution=R)``)
#: where the scene has hair–hair interaction.
PARAM_PRESETS = {
    "fast": {"params": {"substeps": 1},
             "settings": {"particles": 16, "dtype": "float32", "hair_hair_resolution": 32}},
    "balanced": {"params": {"substeps": 4},
                 "settings": {"particles": 32, "dtype": "float32", "hair_hair_resolution": 32}},
    "accurate": {"params": {"substeps": 8},
                 "settings": {"particles": 64, "dtype": "float32", "hair_hair_resolution": 32}},
}

Scalar = Union[float, torch.Tensor]

#: the fields only one material reads (``Params.validate`` refuses a changed field of the other)
MATERIAL_ONLY = {
    "per_particle": ("particle_mass", "stretch_stiffness", "bend_scale", "torsion_scale", "integrity_stiffness",
                     "angular_stiffness", "num_pinned"),
    "per_length": ("linear_density", "stretch_rigidity", "bend_rigidity", "torsion_rigidity", "integrity_rate",
                   "angular_rigidity", "stiffness_cap", "root_length", "integrity_length"),
}
#: the fields that hold κ_I and κ_α in each material
INTEGRITY_FIELD = {"per_particle": "integrity_stiffness", "per_length": "integrity_rate"}
ANGULAR_FIELD = {"per_particle": "angular_stiffness", "per_length": "angular_rigidity"}


def _same(a, b) -> bool:
    if isinstance(a, torch.Tensor) or isinstance(b, torch.Tensor):
        return False
    return a == b


def _min_value(v) -> float:
    if isinstance(v, torch.Tensor):
        return float(v.detach().min()) if v.numel() else 0.0
    return float(v)


def _is_finite(v) -> bool:
    if isinstance(v, torch.Tensor):
        return bool(torch.isfinite(v.detach()).all())
    return math.isfinite(float(v))


#: the Params fields of :meth:`Params.paper`: the paper's per-particle constants (SPEC §10)
PAPER_UNITS = {"material": "per_particle", "particle_mass": 1.0, "stretch_stiffness": 1e6,
               "integrity_stiffness": 1e2, "angular_stiffness": 1e2, "drag": 1.5}


@dataclass
class Params:
    """Parameters of the AMS model, SI units throughout (m, kg, s, N).

    Two materials (SPEC §13; derivation and conversions in docs/material.md):

    - ``material="per_particle"``: the paper's constants, per particle and per spring
      (``particle_mass``, ``stretch_stiffness``, ``bend_scale``, ``torsion_scale``,
      ``integrity_stiffness``, ``angular_stiffness``, ``num_pinned``). Refining a strand from N to
      2N particles with them makes a different material (heavier, softer in stretch).
    - ``material="per_length"``: a parametrisation per unit length, converted per segment when
      the model is built (``linear_density``, ``stretch_rigidity``, ``bend_rigidity``,
      ``torsion_rigidity``, ``integrity_rate``, ``angular_rigidity``, ``root_length``,
      ``integrity_length``), so that N is a resolution knob: the simulated material does not
      change with it.

    The per-particle defaults use a particle mass of 1e-6 kg (one simulated strand stands for
    a small wisp) and the stiffness-to-mass ratios of the paper's Table 1 defaults
    (κ_L/m = 1e6 s⁻², κ_I/m = 1e2 s⁻², κ_α/m = 1e2 s⁻² rad⁻¹); the per-length defaults are the same
    material for 8 mm segments (32 particles on a 25 cm strand), but for the bending and torsion
    springs (off in the per-length default, see ``bend_rigidity``). :meth:`paper` gives the paper's
    own units (mass 1, per particle). Stiffness-type fields may be tensors (requiring grad, or
    per strand (S, 1)).

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
        drag: linear drag rate γ/m, 1/s (force −drag·m·v, world air at rest); both materials.
        material: "per_particle" or "per_length" (see above).
        linear_density: λ, kg/m: m_i = λ × the particle's share of rest length (half of each
            adjacent edge).
        stretch_rigidity: EA, N: κ_L,i = EA / l_i for edge i.
        bend_rigidity, torsion_rigidity: N·m⁴, rigidity proxies B_b, B_t of the springs
            (i, i+2) and (i, i+3): κ_i = s B / ℓ_i⁵ with ℓ_i the spring's rest length over its span
            (2 or 3 edges) and s the stretch-coupling factor (``sim.material.stretch_coupling_factor``),
            which makes the small-deflection bending stiffness per unit length of a curved rest
            shape of curvature c, c² (B_b/4 + 4 B_t), independent of N (docs/material.md; tested
            against an Euler–Bernoulli cantilever). Default 0: under large deformation the springs'
            response does not converge in N (measured in docs/material.md), and the biphasic
            couplings keep the shape.
        integrity_rate: ω_I², s⁻²: κ_I,i = ω_I² m_i (a rate per unit mass).
        angular_rigidity: A, N (= N·m per rad² per metre): κ_α,i = A on every segment. The angular
            spring's potential ½ κ_α |e| θ² is already per unit length (|e| = l_i), so a constant
            κ_α is an N-independent energy density ½ A θ². (The rate-per-mass form κ_α = ω² m l
            makes that density ∝ l², vanishing as N grows; measured in docs/material.md, it does
            not converge.)
        stiffness_cap: per-length material: a bending or torsion spring is never stiffer than this
            many times the stretch stiffness of its first edge. B / ℓ⁵ grows without bound on short
            segments (a 2 cm strand of 32 particles would get springs 1e5× its edges: a step float64
            resolves but float32 does not); with B_b = B_t = 3.2768e-11 N·m⁴ (the per-particle
            default's springs at 8 mm) the cap of 1000 binds on segments shorter than about 2.4 mm.
        root_length: m, per-length material: pin every particle within this rest arc length of
            the root (at least two: the root and its direction), instead of ``num_pinned``.
        integrity_length: m, per-length material: the length unit of the non-Hookean
            elongation (particle–ghost distance over it) instead of the local segment length,
            so the curve's transition and breaking points are N-independent.
        dt: frame length, s.
        substeps: M, backward-Euler substeps per frame (Δt' = dt / M).
        gravity: (gx, gy, gz), m/s², world frame (+y is up).
        num_pinned: particles from the root that follow the head rigidly (SPEC §1).
        sag_free: offset the ghosts so the integrity springs hold the weight at t = 0 (§5).
        geometric_stiffness: add the positive part of each spring's geometric stiffness,
            ``κ (1 − l/|d|)₊ (I − d̂d̂ᵀ)``, to the matrix (SPEC §4). The frozen-direction
            linearisation alone can gain energy in single steps with transverse motion (measured
            up to +17 % of the current energy); with this option no step gains energy. On by
            default, by measurement: it halves the errors of the convergence study in N and makes
            it first order (docs/material.md; False is the SPEC form).
        implicit_angular: add the angular spring's tangent stiffness κ_α/|e| (I − êêᵀ) to
            the matrix (SPD, keeps stiff angular springs stable at large dt).
        angular_reaction: apply the angular spring as a couple (−κ_α θ t̂ on x_i as well as
            +κ_α θ t̂ on x_{i+1}); False is the paper's one-particle force, which is not
            conservative and makes free wisps flutter (see :func:`forces.angular_force`).
        inextensibility: apply follow-the-leader length projection after the substeps.
        collision_inextensibility: with colliders (and ``inextensibility``), this many rounds
            of edge-length restore (follow-the-leader) + push-out after the collision response,
            so contact does not leave stretched edges (see ``ams_torch.sim.stepping.collisions``); 0 = none.
        contact: when the hair–solid contact response runs (SPEC §8): ``"substep"`` (the default:
            also after each substep's position update, with Δt' and the colliders at that
            substep's pose, before the frame's own collision stage) or ``"frame"`` (the SPEC's
            order only: once per frame, after the substeps, follow-the-leader and hair–hair).
            Chosen by measurement: with head collisions it makes the errors in N fall at first
            order (docs/material.md), and the contact itself converge in M
            (docs/roller_coaster.md); it costs one contact pass per substep.
        ftl_damping: Müller et al. 2012 velocity-correction factor s_damping ∈ [0, 1]: the
            velocities gain (d_i − s d_{i+1}) / Δt from the corrections d. The local part
            s (d_{i+1} − d_i) vanishes only like the edge length, so it sets a first-order error in
            N; 0.8 (Müller: 0.9) keeps the convergence study in N at order ≥ 0.9 and an N = 16 → 64
            error ratio ≥ 4 for the straight, wavy and curly presets (docs/material.md). Lower
            values widen a known instability of short frames (dt ≤ 1/500 s with κ_L/m ≈ 1e5–5e6 s⁻²
            and M ≥ 2, present at 0.9 too): use 0.9 or more there.
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
    integrity_transition: Scalar = 0.5
    integrity_break: Scalar = 1.0
    integrity_soft_ratio: Scalar = 0.25
    angular_stiffness: Scalar = 1e-4
    particle_mass: Scalar = 1e-6
    drag: Scalar = 1.5
    material: str = "per_length"
    linear_density: Scalar = 1.25e-4
    stretch_rigidity: Scalar = 8e-3
    bend_rigidity: Scalar = 0.0
    torsion_rigidity: Scalar = 0.0
    integrity_rate: Scalar = 1e2
    angular_rigidity: Scalar = 1e-4
    stiffness_cap: float = 1e3
    root_length: float = 0.0
    integrity_length: float = 8e-3
    dt: float = 1.0 / 60.0
    substeps: int = 1
    gravity: Tuple[float, float, float] = (0.0, -9.81, 0.0)
    num_pinned: int = 2
    sag_free: bool = True
    geometric_stiffness: bool = True
    implicit_angular: bool = True
    angular_reaction: bool = True  # see forces.angular_force: the one-way form flutters
    inextensibility: bool = True
    collision_inextensibility: int = 1
    contact: str = "substep"
    ftl_damping: float = 0.8
    max_relative_speed: float = 1.0e3
    check_every: int = 1

    def __post_init__(self) -> None:
        self.validate()

    def __setattr__(self, name, value) -> None:
        if self.__dict__.get("_frozen", False):
            raise AttributeError(f"Params.{name}: these Params belong to a built model and are frozen (the model's "
                                 f"coefficients and the step's Config were made from them); make new Params with "
                                 f"params.replace({name}=...) and build a new Simulator / ModelBuilder")
        super().__setattr__(name, value)

    def frozen(self) -> "Params":
        """A validated copy that refuses every later assignment (``AttributeError``): the Params a
        built :class:`~ams_torch.sim.model.Model` keeps. ``replace`` still makes new, unfrozen Params.
        Tensor fields are shared, not copied (a grad-carrying value keeps its graph)."""
        out = replace(self)
        object.__setattr__(out, "_frozen", True)
        return out

    @property
    def is_frozen(self) -> bool:
        """Whether these Params belong to a built model (see :meth:`frozen`)."""
        return self.__dict__.get("_frozen", False)

    # -- validation --------------------------------------------------------------------
    def validate(self) -> "Params":
        """Raise ``ValueError`` naming the first invalid field."""
        _check_kinds(self)
        if self.material not in ("per_particle", "per_length"):
            raise ValueError(f"Params.material must be 'per_particle' or 'per_length'; got {self.material!r}")
        for name in ("stretch_stiffness", "bend_scale", "torsion_scale", "integrity_stiffness",
                     "angular_stiffness", "drag", "stretch_rigidity", "bend_rigidity", "torsion_rigidity",
                     "integrity_rate", "angular_rigidity"):
            v = getattr(self, name)
            if not _is_finite(v):
                raise ValueError(f"Params.{name} must be finite; got {v}")
            if _min_value(v) < 0:
                raise ValueError(f"Params.{name} must be non-negative (stiffness/drag); got {v}")
        if not _is_finite(self.particle_mass) or _min_value(self.particle_mass) <= 0:
            raise ValueError(f"Params.particle_mass must be positive (kg); got {self.particle_mass}")
        if not _is_finite(self.linear_density) or _min_value(self.linear_density) <= 0:
            raise ValueError(f"Params.linear_density must be positive (kg/m); got {self.linear_density}")
        for name in ("root_length", "integrity_length", "stiffness_cap"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0 or \
                    (name != "root_length" and v == 0):
                raise ValueError(f"Params.{name} must be a {'non-negative' if name == 'root_length' else 'positive'} "
                                 f"number{'' if name == 'stiffness_cap' else ' of metres'}; got {v!r}")
        if self.integrity_model not in ("hookean", "nonhookean"):
            raise ValueError(f"Params.integrity_model must be 'hookean' or 'nonhookean'; got {self.integrity_model!r}")
        curve = {}
        for name in ("integrity_transition", "integrity_break", "integrity_soft_ratio"):
            v = getattr(self, name)
            if isinstance(v, torch.Tensor):
                if v.numel() != 1 or not _is_finite(v):
                    raise ValueError(f"Params.{name} must be one finite number; got {v!r}")
                curve[name] = float(v.detach())
            elif isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ValueError(f"Params.{name} must be a finite number; got {v!r}")
            else:
                curve[name] = float(v)
        if not curve["integrity_transition"] > 0:
            raise ValueError(f"Params.integrity_transition must be positive; got {self.integrity_transition}")
        if not curve["integrity_break"] > curve["integrity_transition"]:
            raise ValueError(f"Params.integrity_break must exceed integrity_transition "
                             f"({self.integrity_transition}); got {self.integrity_break}")
        if not 0.0 < curve["integrity_soft_ratio"] <= 1.0:
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
        if self.contact not in ("frame", "substep"):
            raise ValueError(f"Params.contact must be 'frame' or 'substep'; got {self.contact!r}")
        if not 0.0 <= self.ftl_damping <= 1.0:
            raise ValueError(f"Params.ftl_damping must lie in [0, 1]; got {self.ftl_damping}")
        if not self.max_relative_speed > 0:
            raise ValueError(f"Params.max_relative_speed must be positive (m/s); got {self.max_relative_speed}")
        if self.check_every < 0:
            raise ValueError(f"Params.check_every must be >= 0; got {self.check_every}")
        if self.dt / self.substeps < MIN_SUBSTEP:
            raise ValueError(f"Params.dt = {self.dt!r} s over {self.substeps} substep(s) is a substep of "
                             f"{self.dt / self.substeps:.3g} s, below {MIN_SUBSTEP:g} s: the step divides by it and "
                             f"overflows; use a frame of at least {MIN_SUBSTEP * self.substeps:g} s")
        other = "per_particle" if self.material == "per_length" else "per_length"
        for name in MATERIAL_ONLY[other]:
            if not _same(getattr(self, name), _DEFAULTS[name]):
                hint = ", ".join(MATERIAL_ONLY[self.material])
                raise ValueError(f"Params.{name} is a field of the {other} material, but material = {self.material!r} "
                                 f"ignores it: set material={other!r} to use it, or the {self.material} fields ({hint})")
        return self

    def check_dtype(self, dtype: torch.dtype) -> None:
        """Raise ``ValueError`` naming the first field whose value does not fit ``dtype`` with room
        for the step's products (above its largest value / 1e6: gravity 1e308 in float32 or
        float64), which would otherwise overflow and surface as a divergence."""
        big = torch.finfo(dtype).max / 1e6
        for f in fields(self):
            v = getattr(self, f.name)
            values = v.detach().reshape(-1).tolist() if isinstance(v, torch.Tensor) else \
                list(v) if isinstance(v, tuple) else [v]
            for x in values:
                if isinstance(x, (int, float)) and not isinstance(x, bool) and abs(float(x)) > big:
                    raise ValueError(f"Params.{f.name} = {v!r} does not fit in {dtype} with room for the step's "
                                     f"products (at most {big:.3g}); the simulation would overflow")

    # -- variants ----------------------------------------------------------------------
    def replace(self, **changes) -> "Params":
        """A copy with some fields changed (validated)."""
        unknown = set(changes) - {f.name for f in fields(self)}
        if unknown:
            raise ValueError(f"unknown Params field(s): {sorted(unknown)}")
        return replace(self, **changes)

    def ms(self) -> "Params":
        """Plain mass-spring (Selle et al.) for comparisons: κ_I = κ_α = 0, no ghost offset."""
        return self.replace(**{INTEGRITY_FIELD[self.material]: 0.0, ANGULAR_FIELD[self.material]: 0.0}, sag_free=False)

    def to_per_length(self, segment_length: float) -> "Params":
        """The per-length material that equals this per-particle one on a strand of segments of
        ``segment_length`` metres (docs/material.md): λ = m/l, EA = κ_L l, B = κ_L × scale × l⁵ / s
        (s the stretch-coupling factor of the per-length springs, :func:`~ams_torch.sim.material.
        stretch_coupling_factor`, here from the springs' coupled bending stiffness), ω_I² = κ_I/m,
        A = κ_α, root length (num_pinned − 1) l, integrity length l.
        Interior particles match exactly; the two end particles carry half a segment's mass in
        the per-length material. Tensor fields are converted elementwise."""
        from ams_torch.sim.material import coupled_bending

        if self.material != "per_particle":
            raise ValueError("to_per_length converts a per_particle Params")
        ell = float(segment_length)
        if not ell > 0:
            raise ValueError(f"segment_length must be positive (m); got {segment_length!r}")
        m, k = self.particle_mass, self.stretch_stiffness
        kb, kt = k * self.bend_scale, k * self.torsion_scale
        target = kb / 4 + 4 * kt  # the inextensible-edge stiffness that the per-length springs reproduce
        coupled = coupled_bending(kb, kt, k)
        s = target / coupled if _min_value(target) > 0 else 1.0
        return replace(self, **{f: _DEFAULTS[f] for f in MATERIAL_ONLY["per_particle"]}).replace(
            material="per_length", linear_density=m / ell, stretch_rigidity=k * ell,
            bend_rigidity=kb * ell ** 5 / s, torsion_rigidity=kt * ell ** 5 / s,
            integrity_rate=self.integrity_stiffness / m, angular_rigidity=self.angular_stiffness,
            root_length=(self.num_pinned - 1) * ell, integrity_length=ell)

    def to_per_particle(self, segment_length: float) -> "Params":
        """The per-particle material that equals this per-length one on segments of
        ``segment_length`` metres (the inverse of :meth:`to_per_length`; the pinned count is the
        particles within ``root_length``, at least 2; the stiffness cap is not applied)."""
        from ams_torch.sim.material import stretch_coupling_factor

        if self.material != "per_length":
            raise ValueError("to_per_particle converts a per_length Params")
        ell = float(segment_length)
        if not ell > 0:
            raise ValueError(f"segment_length must be positive (m); got {segment_length!r}")
        m = self.linear_density * ell
        k = self.stretch_rigidity / ell
        s = stretch_coupling_factor(torch.tensor(ell, dtype=torch.float64), self.stretch_rigidity,
                                    self.bend_rigidity, self.torsion_rigidity)
        if not any(isinstance(v, torch.Tensor) for v in (self.stretch_rigidity, self.bend_rigidity,
                                                         self.torsion_rigidity)):
            s = float(s)
        return replace(self, **{f: _DEFAULTS[f] for f in MATERIAL_ONLY["per_length"]}).replace(
            material="per_particle", particle_mass=m, stretch_stiffness=k,
            bend_scale=s * self.bend_rigidity / (ell ** 5 * k), torsion_scale=s * self.torsion_rigidity / (ell ** 5 * k),
            integrity_stiffness=self.integrity_rate * m, angular_stiffness=self.angular_rigidity,
            num_pinned=max(2, 1 + int(math.floor(self.root_length / ell + 1e-9))))

    @staticmethod
    def paper(**changes) -> "Params":
        """The paper's units (SPEC §10): particle mass 1, κ_L = 1e6, κ_I = 1e2, κ_α = 1e2."""
        return Params(**dict(PAPER_UNITS, **changes))

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


_DEFAULTS = {f.name: f.default for f in fields(Params)}
#: s, the shortest substep (dt / substeps) Params accepts: the step divides by it
MIN_SUBSTEP = 1e-9


def _check_kinds(p: "Params") -> None:
    """Each field of the kind its default is (a number or a tensor, a whole number, a bool, a
    string, three numbers), so a string or None gives a ValueError naming the field, not a raw
    TypeError later."""
    for f in fields(p):
        v, d = getattr(p, f.name), _DEFAULTS[f.name]
        if isinstance(d, bool):
            ok, what = isinstance(v, bool), "true or false"
        elif isinstance(d, str):
            ok, what = isinstance(v, str), "a string"
        elif isinstance(d, tuple):
            ok = isinstance(v, (tuple, list)) and len(v) == 3 and all(
                isinstance(c, (int, float)) and not isinstance(c, bool) for c in v)
            what = "three numbers"
        elif isinstance(d, int):
            ok = isinstance(v, int) and not isinstance(v, bool)
            what = "a positive integer" if f.name == "substeps" else "a non-negative integer"
        else:
            ok = isinstance(v, torch.Tensor) and v.is_floating_point() or (
                isinstance(v, numbers.Real) and not isinstance(v, (bool, np.bool_)))
            what = "a number or a floating-point tensor"
        if not ok:
            raise ValueError(f"Params.{f.name} must be {what}; got {v!r} ({type(v).__name__})")
