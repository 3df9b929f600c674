"""The fixed part of a simulation: a groom's rest data, topology, material and stages' fixed data.

Builder → Model (STYLE.md): :class:`Model` validates a rest groom and :class:`~ams_torch.Params`
once and holds every fixed per-groom tensor: rest geometry, masses, stiffnesses and drag as
per-element tensors, pinned masks. It is a ``torch.nn.Module``: registered on the
:class:`~ams_torch.Simulator`, ``.to()``, ``.double()``, ``state_dict()`` and optimizers see it.
It has no scene batch dimension; states do.

Coefficients. Each material field of Params becomes either a buffer already expanded to its
term's shape (the common case: nothing to compute per step), or, when it is learnable
(``Simulator(..., learnable=(...))``: an ``nn.Parameter``) or given as a tensor that requires
grad, its raw value plus a fixed per-element factor; :func:`coefficients` returns the per-term
tensors either way, so gradients reach the raw values.
"""
from __future__ import annotations

import warnings
from typing import Iterable, NamedTuple, Sequence

import numpy as np
import torch

from ams_torch.sim.material import coupled_bending, stretch_coupling_factor
from ams_torch.sim.params import Params
from ams_torch.stages.hair_hair import build_hair_hair

__all__ = ["Model", "Coefficients", "coefficients", "check_rest_positions", "MIN_PARTICLES", "MATERIAL_FIELDS",
           "sag_free_offset", "pinned_counts"]

MIN_PARTICLES = 4  # torsion springs couple i and i+3
MIN_SEGMENT = 1e-9  # m; shorter rest segments are degenerate

#: Params fields that become model coefficients, per material, with the shape each broadcasts
#: to ("particle": (S, N); "edge"/"bend"/"torsion": (S, N−k); "segment": (S, N−1); "scalar": ()).
MATERIAL_FIELDS = {
    "per_particle": {
        "particle_mass": "particle", "drag": "particle", "stretch_stiffness": "edge", "bend_scale": "bend",
        "torsion_scale": "torsion", "integrity_stiffness": "particle", "angular_stiffness": "segment",
        "integrity_transition": "scalar", "integrity_break": "scalar", "integrity_soft_ratio": "scalar"},
    "per_length": {
        "linear_density": "particle", "drag": "particle", "stretch_rigidity": "edge", "bend_rigidity": "bend",
        "torsion_rigidity": "torsion", "integrity_rate": "particle", "angular_rigidity": "segment",
        "integrity_transition": "scalar", "integrity_break": "scalar", "integrity_soft_ratio": "scalar"},
}

#: Coefficient terms and the fields each depends on (see :func:`coefficients`).
_TERM_FIELDS = {
    "per_particle": {"mass": ("particle_mass",), "edge": ("stretch_stiffness",),
                     "bend": ("stretch_stiffness", "bend_scale"), "torsion": ("stretch_stiffness", "torsion_scale"),
                     "integrity": ("integrity_stiffness",), "angular": ("angular_stiffness",),
                     "drag": ("drag", "particle_mass")},
    "per_length": {"mass": ("linear_density",), "edge": ("stretch_rigidity",),
                   "bend": ("bend_rigidity", "torsion_rigidity", "stretch_rigidity"),
                   "torsion": ("bend_rigidity", "torsion_rigidity", "stretch_rigidity"),
                   "integrity": ("integrity_rate", "linear_density"),
                   "angular": ("angular_rigidity",), "drag": ("drag", "linear_density")},
}




def _first_index(mask: torch.Tensor) -> tuple:
    idx = torch.nonzero(mask, as_tuple=False)
    return tuple(int(i) for i in idx[0])


def check_rest_positions(x, name: str = "rest_positions") -> torch.Tensor:
    """Validate a groom's rest positions and return them as a tensor.

    x: (S, N, 3) metres (array-like). Raises ``ValueError`` naming the problem and where:
    wrong shape, too few particles, NaN/Inf, zero-length (degenerate) segments, coincident
    particles two or three apart (zero-length bending/torsion springs).
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
        raise ValueError(f"{name} has {n} particles per strand; at least {MIN_PARTICLES} are needed "
                         f"(torsion springs couple particles i and i+3)")
    if not x.is_floating_point():
        x = x.double()
    bad = ~torch.isfinite(x)
    if bad.any():
        si, pi, _ = _first_index(bad)
        count = int(bad.any(-1).any(-1).sum())
        raise ValueError(f"{name} contains NaN/Inf: first at strand {si}, particle {pi} ({count} strand(s) affected)")
    for k, what in ((1, None), (2, "bending"), (3, "torsion")):
        seg = (x[:, k:] - x[:, :-k]).norm(dim=-1)
        degenerate = seg <= MIN_SEGMENT
        if degenerate.any():
            si, pi = _first_index(degenerate)
            if what is None:
                raise ValueError(f"{name} has a zero-length (degenerate) segment: strand {si}, between particles "
                                 f"{pi} and {pi + 1} (length {float(seg[si, pi]):.3g} m)")
            raise ValueError(f"{name}: particles {pi} and {pi + k} of strand {si} coincide; their {what} spring "
                             f"has zero rest length")
    return x


class Coefficients(NamedTuple):
    """Per-term material coefficients of a model (tensors on the model's device and dtype).

    mass (S, N) kg; drag (S, N) kg/s (γ_i = drag rate × m_i); edge, bend, torsion (S, N−k) N/m,
    the spring stiffnesses κ of pairs (i, i+k); integrity (S, N) N/m, κ_I; angular (S, N−1) N/rad,
    κ_α of segment (i, i+1); transition, breaking, soft_ratio () dimensionless (SPEC §7).
    """

    mass: torch.Tensor
    drag: torch.Tensor
    edge: torch.Tensor
    bend: torch.Tensor
    torsion: torch.Tensor
    integrity: torch.Tensor
    angular: torch.Tensor
    transition: torch.Tensor
    breaking: torch.Tensor
    soft_ratio: torch.Tensor


def _requires_value(v) -> bool:
    return isinstance(v, torch.Tensor) and v.requires_grad


class Model(torch.nn.Module):
    """Fixed data of a groom, no scene batch dimension (built from rest positions and Params).

    Buffers (all on one device/dtype):
        rest_positions: (S, N, 3) m, rest shape X̄ in the head frame.
        edge_rest_length, bend_rest_length, torsion_rest_length: (S, N−k) m, rest lengths of the
            springs between particles i and i+k for k = 1, 2, 3.
        segment_length: (S, N) m, each particle's local rest segment length (mean of its adjacent
            edges), the length unit of the non-Hookean elongation (SPEC §7).
        pinned: (S, N) bool, particles that follow the head rigidly (a prefix of each strand).
        num_pinned: (S,) int64, the length of that prefix.
        gravity: (3,) m/s², world frame.
        one coefficient per entry of :data:`MATERIAL_FIELDS` (see :func:`coefficients`).

    Args:
        rest_positions: (S, N, 3) metres in the head frame (array or tensor), validated.
        params: the :class:`~ams_torch.Params` (validated).
        learnable: names of Params material fields to make ``nn.Parameter`` s (raw values in the
            shape given: a number → 0-d, or a tensor (S, 1)/(S, N)).
        device, dtype: of every tensor (float32 by default).
    """

    def __init__(self, rest_positions, params: Params, *, learnable: Iterable[str] = (), device=None,
                 dtype: torch.dtype = torch.float32, hair_hair=None, colliders: Sequence = ()):
        super().__init__()
        params.validate()
        self.params = params if params.is_frozen else params.frozen()
        self.sag_free = bool(params.sag_free)
        learnable = tuple(learnable)
        fields = MATERIAL_FIELDS[params.material]
        unknown = [f for f in learnable if f not in fields]
        if unknown:
            raise ValueError(f"learnable: {unknown} are not material fields of the {params.material} Params; "
                             f"choose from {sorted(fields)}")
        x = check_rest_positions(rest_positions).to(device=device, dtype=dtype, copy=True)  # never the caller's tensor
        s, n, _ = x.shape
        self.num_strands, self.num_particles = s, n
        self.material = params.material
        self.stiffness_cap = float(params.stiffness_cap)
        self.learnable = learnable
        self.register_buffer("rest_positions", x)
        for k, name in ((1, "edge"), (2, "bend"), (3, "torsion")):
            self.register_buffer(f"{name}_rest_length", (x[:, k:] - x[:, :-k]).norm(dim=-1))
        e = self.edge_rest_length
        total = torch.nn.functional.pad(e, (0, 1)) + torch.nn.functional.pad(e, (1, 0))
        count = torch.full((n,), 2.0, dtype=dtype, device=x.device)
        count[0] = count[-1] = 1.0
        if params.material == "per_length":  # the non-Hookean elongation's length unit (SPEC §7, §13)
            self.register_buffer("segment_length", torch.full((s, n), params.integrity_length, dtype=dtype,
                                                              device=x.device))
            self.register_buffer("length_share", total / 2)  # each particle's share of rest length, m
            self.register_buffer("inverse_edge", 1.0 / e)  # 1/l_i
            for k, name in ((2, "bend"), (3, "torsion")):  # 1/ℓ⁵, ℓ = the spring's rest length over its span
                self.register_buffer(f"{name}_span_length", getattr(self, f"{name}_rest_length") / k)
                self.register_buffer(f"inverse_{name}5", getattr(self, f"{name}_span_length") ** -5)
        else:
            self.register_buffer("segment_length", total / count)
        counts = pinned_counts(params, x)
        if int(counts.max()) >= n:
            raise ValueError(f"{int(counts.max())} pinned particles (Params.num_pinned / root_length) must be fewer "
                             f"than the particles per strand ({n})")
        self.register_buffer("num_pinned", counts)
        self.has_pinned = bool(int(counts.max()) > 0)
        self.register_buffer("pinned", torch.arange(n, device=x.device)[None, :] < counts[:, None])
        self.register_buffer("gravity", torch.as_tensor(params.gravity, dtype=dtype, device=x.device))
        self._raw = {}  # field -> the shape it broadcasts to, for raw (learnable / grad) fields
        for field, term in fields.items():
            self._add_field(field, term, getattr(params, field), field in learnable)
        self._fixed_terms = [t for t, deps in _TERM_FIELDS[self.material].items()
                             if not any(d in self._raw for d in deps)]
        self._watched_fields = tuple(f for f in fields if f not in self._raw)
        self._geometry = tuple(n for n in self._buffers if n not in fields and n != "gravity")
        self._build_fixed_terms()
        self.hair_hair_settings = hair_hair
        self.hair_hair = None if hair_hair is None else build_hair_hair(
            hair_hair, self.rest_positions, coefficients(self).mass.detach(), device=x.device, dtype=dtype)
        self.colliders = torch.nn.ModuleList(colliders)

    # -- construction ----------------------------------------------------------------------
    def _term_shape(self, term: str) -> tuple:
        s, n = self.num_strands, self.num_particles
        return {"particle": (s, n), "edge": (s, n - 1), "bend": (s, n - 2), "torsion": (s, n - 3),
                "segment": (s, n - 1), "scalar": ()}[term]

    def _add_field(self, field: str, term: str, value, learnable: bool) -> None:
        dev, dtype = self.rest_positions.device, self.rest_positions.dtype
        shape = self._term_shape(term)
        raw = torch.as_tensor(value, device=dev, dtype=dtype) if not isinstance(value, torch.Tensor) \
            else value.to(device=dev, dtype=dtype)
        try:
            torch.broadcast_shapes(raw.shape, shape)
        except RuntimeError:
            raise ValueError(f"Params.{field} of shape {tuple(raw.shape)} does not broadcast to {shape} "
                             f"(the {term} term of this groom)") from None
        if learnable:
            self.register_parameter(field, torch.nn.Parameter(raw.detach().clone()))
            self._raw[field] = shape
        elif _requires_value(value):
            self.register_buffer(field, raw, persistent=False)  # keeps the user's autograd graph
            self._raw[field] = shape
        else:
            self.register_buffer(field, raw.expand(shape).clone())

    def _build_fixed_terms(self) -> None:
        """Coefficient terms that depend on no raw field are computed once, here, as buffers
        (``coefficient_<term>``), so a step of a fixed material computes none of them."""
        terms = _compute_terms(self, set(self._fixed_terms))
        for t in self._fixed_terms:
            self.register_buffer(f"coefficient_{t}", terms[t].contiguous(), persistent=False)
        self._seen = self._snapshot()

    def _snapshot(self) -> list:
        """(name, tensor, in-place version) of every watched buffer, the rest geometry first."""
        b = self._buffers
        return [(n, b[n], b[n]._version) for n in self._geometry + self._watched_fields]

    def update(self) -> "Model":
        """Take in-place edits of the fixed fields into account (cheap: compares each field's
        version counter; called by :func:`coefficients`, so by every eager step).

        A material field edited in place or replaced (``model.drag.mul_(10)``) recomputes the
        coefficient terms derived from it, so the next step uses it. The rest geometry
        (``rest_positions``, rest lengths, pinned particles, …) is fixed once built: an edit raises
        ``ValueError`` (build a new model from the new rest positions: :class:`ModelBuilder`).
        Under ``torch.compile`` nothing is checked inside the compiled region: after editing a
        field, call ``update()`` before the next compiled step.
        """
        b = self._buffers
        for n, t, v in self._seen:
            if b[n] is not t or t._version != v:
                break
        else:
            return self  # nothing edited (the common case: one pass over the version counters)
        changed = [n for n, t, v in self._seen if n in self._geometry and (b[n] is not t or t._version != v)]
        if changed:
            raise ValueError(f"Model.{', Model.'.join(changed)} changed after the model was built: the rest geometry "
                             f"and what is derived from it (rest lengths, segment lengths, pinned particles) are "
                             f"fixed; build a new model from the new rest positions (ModelBuilder / Simulator)")
        self._build_fixed_terms()
        return self

    def set_pinned(self, counts) -> "Model":
        """Pin the first ``counts[s]`` particles of strand s (an int: every strand), whatever the
        Params chose: ``num_pinned``, ``pinned`` and ``has_pinned`` change together (the one
        sanctioned edit of the fixed geometry; the stages' fixed data keep their rest groom)."""
        s, n = self.num_strands, self.num_particles
        counts = torch.as_tensor(counts, dtype=torch.int64, device=self.device).expand(s).clone()
        if int(counts.min()) < 0 or int(counts.max()) >= n:
            raise ValueError(f"pinned counts must be in [0, {n - 1}] (fewer than the particles per strand); got "
                             f"{counts.tolist()}")
        self.num_pinned = counts
        self.pinned = torch.arange(n, device=self.device)[None, :] < counts[:, None]
        self.has_pinned = bool(int(counts.max()) > 0)
        self._seen = self._snapshot()
        return self

    def _apply(self, fn, *args, **kwargs):
        if hasattr(self, "_seen"):
            self.update()  # an edited rest geometry raises here too, not silently accepted by .to()
        out = super()._apply(fn, *args, **kwargs)
        self._build_fixed_terms()  # recomputed in the new dtype from the converted fields
        return out

    def _load_from_state_dict(self, *args, **kwargs):
        super()._load_from_state_dict(*args, **kwargs)
        self._build_fixed_terms()

    # -- sizes and views -------------------------------------------------------------------
    @property
    def rest_lengths(self) -> tuple:
        """(edge, bend, torsion) rest lengths, (S, N−k) m each."""
        return self.edge_rest_length, self.bend_rest_length, self.torsion_rest_length

    @property
    def dtype(self) -> torch.dtype:
        return self.rest_positions.dtype

    @property
    def device(self) -> torch.device:
        return self.rest_positions.device

    def extra_repr(self) -> str:
        return f"strands={self.num_strands}, particles={self.num_particles}, learnable={self.learnable}"


def _compute_terms(model: Model, terms: set) -> dict:
    """The requested coefficient terms from the fields (buffers or raw values) and the geometry."""
    raw = model._raw

    def full(field: str) -> torch.Tensor:
        v = getattr(model, field)
        return v.expand(raw[field]) if field in raw else v

    out = {}
    if model.material == "per_particle":
        mass = full("particle_mass")
        edge = full("stretch_stiffness")
        out["mass"], out["edge"] = mass, edge
        # the pair (i, i+k) uses the stretch stiffness of its first edge times its scale
        if "bend" in terms:
            out["bend"] = edge[..., :-1] * full("bend_scale")
        if "torsion" in terms:
            out["torsion"] = edge[..., :-2] * full("torsion_scale")
        out["integrity"], out["angular"] = full("integrity_stiffness"), full("angular_stiffness")
    else:
        mass = full("linear_density") * model.length_share
        out["mass"] = mass
        if "edge" in terms:
            out["edge"] = full("stretch_rigidity") * model.inverse_edge
        cap = model.stiffness_cap * full("stretch_rigidity") * model.inverse_edge  # cap × κ_L per edge
        # κ = s B / ℓ⁵: s corrects for the springs' coupling with stretch (stretch_coupling_factor)
        for name, k in (("bend", 1), ("torsion", 2)):
            if name in terms:
                ell = getattr(model, f"{name}_span_length")
                ea = _pairs(full("stretch_rigidity"), k)
                s = stretch_coupling_factor(ell, ea, _pairs(full("bend_rigidity"), k, ell.shape[-1]),
                                            _pairs(full("torsion_rigidity"), k, ell.shape[-1]))
                kappa = full(f"{name}_rigidity") * s * getattr(model, f"inverse_{name}5")
                out[name] = torch.minimum(kappa, cap[..., :-k])
        if "integrity" in terms:
            out["integrity"] = full("integrity_rate") * mass
        if "angular" in terms:
            out["angular"] = full("angular_rigidity").expand(model.edge_rest_length.shape)
    if "drag" in terms:
        out["drag"] = full("drag") * mass
    return out


def _pairs(v: torch.Tensor, k: int, count: int = None) -> torch.Tensor:
    """A per-edge (S, N−1) value on the springs that start at each particle ((S, N−1−k): the first
    edge of each spring), or a per-spring value of another kind cut or padded to ``count`` springs
    (the bending springs' value read at the torsion springs, or the reverse; the last spring repeats)."""
    if v.dim() == 0 or v.shape[-1] == 1:
        return v
    if count is None:
        return v[..., :v.shape[-1] - k]
    if v.shape[-1] >= count:
        return v[..., :count]
    return torch.cat([v, v[..., -1:].expand(v.shape[:-1] + (count - v.shape[-1],))], -1)


def coefficients(model: Model) -> Coefficients:
    """The model's per-term material coefficients (see :class:`Coefficients`).

    Terms that depend only on fixed fields are buffers computed when the model was built (and
    after ``.to()`` / ``load_state_dict``); terms of learnable or grad-carrying fields are
    computed here, so gradients come back to those fields. Per particle: bending/torsion are
    the edge stiffness times their scale, drag the rate times the mass. Per length (SPEC §13):
    m_i = λ × share, κ_L = EA/l, κ_bend = s B_b/ℓ⁵, κ_torsion = s B_t/ℓ⁵ (s: :func:`stretch_coupling_factor`,
    capped at ``stiffness_cap`` × κ_L), κ_I = ω_I² m, κ_α = A (the angular
    rigidity: the same on every segment, since the potential ½ κ_α |e| θ² is per length already).
    """
    if not torch.compiler.is_compiling():
        model.update()
    fixed = model._fixed_terms
    terms = {t: getattr(model, f"coefficient_{t}") for t in fixed}
    missing = set(_TERM_FIELDS[model.material]) - set(fixed)
    if missing:
        terms.update({k: v for k, v in _compute_terms(model, missing).items() if k in missing})
    raw = model._raw

    def scalar(field):
        v = getattr(model, field)
        return v.expand(raw[field]) if field in raw else v

    return Coefficients(mass=terms["mass"], drag=terms["drag"], edge=terms["edge"], bend=terms["bend"],
                        torsion=terms["torsion"], integrity=terms["integrity"], angular=terms["angular"],
                        transition=scalar("integrity_transition"), breaking=scalar("integrity_break"),
                        soft_ratio=scalar("integrity_soft_ratio"))


def pinned_counts(params: Params, rest: torch.Tensor) -> torch.Tensor:
    """(S,) int64: each strand's pinned prefix. Per particle: ``num_pinned``. Per length: every
    particle within ``root_length`` of rest arc length from the root, at least 2 (the root and
    its direction), so the clamped root does not shrink as N grows (SPEC §13)."""
    s, n = rest.shape[:2]
    if params.material == "per_particle":
        return torch.full((s,), params.num_pinned, dtype=torch.int64, device=rest.device)
    arc = torch.nn.functional.pad((rest[:, 1:] - rest[:, :-1]).norm(dim=-1).cumsum(-1), (1, 0))
    within = (arc <= params.root_length * (1 + 1e-9) + 1e-12).sum(-1)
    return within.clamp_min(2).to(torch.int64)


def _all_zero(v) -> bool:
    if isinstance(v, torch.Tensor):
        return bool((v == 0).all())
    return float(v) == 0.0


def warn_if_no_sag_offset(params: Params) -> None:
    """SPEC §5: with κ_I = 0 the sag-free offset m g / κ_I is undefined: say so (once per build)."""
    from ams_torch.sim.params import INTEGRITY_FIELD

    if params.sag_free and _all_zero(getattr(params, INTEGRITY_FIELD[params.material])):
        warnings.warn("Params.sag_free is on but integrity_stiffness is 0: the sag-free offset (m g / κ_I) is "
                      "undefined, so no offset is applied", stacklevel=3)


def sag_free_offset(mass: torch.Tensor, gravity: torch.Tensor, integrity: torch.Tensor) -> torch.Tensor:
    """Ghost offset that makes the integrity springs hold each particle's weight (SPEC §5), world frame.

    ``y_i = x_i − m_i g / κ_I``: g points down, so the ghost sits above its particle by
    m_i |g| / κ_I; zero where κ_I = 0 (the offset is undefined there). mass, integrity: (S, N)
    kg, N/m; gravity (3,) m/s². Returns (S, N, 3) m; the state stores it in the head frame at
    t = 0 (``pose.unrotate``), computed once per scene by ``Simulator.initial_state``.
    """
    positive = integrity > 0
    safe = torch.where(positive, integrity, torch.ones_like(integrity))
    world = -mass[..., None] * gravity / safe[..., None]
    return torch.where(positive[..., None], world, torch.zeros_like(world))
