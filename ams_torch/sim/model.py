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
from typing import Iterable, NamedTuple

import numpy as np
import torch

from ams_torch.sim.params import Params

__all__ = ["Model", "Coefficients", "coefficients", "check_rest_positions", "MIN_PARTICLES", "MATERIAL_FIELDS"]

MIN_PARTICLES = 4  # torsion springs couple i and i+3
MIN_SEGMENT = 1e-9  # m; shorter rest segments are degenerate

#: Params fields that become model coefficients, with the term shape they expand to
#: ("particle": (S, N); "edge"/"bend"/"torsion": (S, N−k); "segment": (S, N−1); "scalar": ()).
MATERIAL_FIELDS = {
    "particle_mass": "particle", "drag": "particle", "stretch_stiffness": "edge", "bend_scale": "bend",
    "torsion_scale": "torsion", "integrity_stiffness": "particle", "angular_stiffness": "segment",
    "integrity_transition": "scalar", "integrity_break": "scalar", "integrity_soft_ratio": "scalar",
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
                 dtype: torch.dtype = torch.float32):
        super().__init__()
        params.validate()
        learnable = tuple(learnable)
        unknown = [f for f in learnable if f not in MATERIAL_FIELDS]
        if unknown:
            raise ValueError(f"learnable: {unknown} are not material fields of Params; choose from "
                             f"{sorted(MATERIAL_FIELDS)}")
        x = check_rest_positions(rest_positions).to(device=device, dtype=dtype)
        s, n, _ = x.shape
        if params.num_pinned >= n:
            raise ValueError(f"Params.num_pinned = {params.num_pinned} must be smaller than the particles per strand "
                             f"({n})")
        self.num_strands, self.num_particles = s, n
        self.learnable = learnable
        self.register_buffer("rest_positions", x)
        for k, name in ((1, "edge"), (2, "bend"), (3, "torsion")):
            self.register_buffer(f"{name}_rest_length", (x[:, k:] - x[:, :-k]).norm(dim=-1))
        e = self.edge_rest_length
        total = torch.nn.functional.pad(e, (0, 1)) + torch.nn.functional.pad(e, (1, 0))
        count = torch.full((n,), 2.0, dtype=dtype, device=x.device)
        count[0] = count[-1] = 1.0
        self.register_buffer("segment_length", total / count)
        counts = torch.full((s,), params.num_pinned, dtype=torch.int64, device=x.device)
        self.register_buffer("num_pinned", counts)
        self.has_pinned = params.num_pinned > 0
        self.register_buffer("pinned", torch.arange(n, device=x.device)[None, :] < counts[:, None])
        self.register_buffer("gravity", torch.as_tensor(params.gravity, dtype=dtype, device=x.device))
        self._raw = {}  # field -> factor buffer name, for coefficients computed per call
        for field, term in MATERIAL_FIELDS.items():
            self._add_coefficient(field, term, getattr(params, field), field in learnable)

    # -- construction ----------------------------------------------------------------------
    def _term_shape(self, term: str) -> tuple:
        s, n = self.num_strands, self.num_particles
        return {"particle": (s, n), "edge": (s, n - 1), "bend": (s, n - 2), "torsion": (s, n - 3),
                "segment": (s, n - 1), "scalar": ()}[term]

    def _add_coefficient(self, field: str, term: str, value, learnable: bool) -> None:
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


def coefficients(model: Model) -> Coefficients:
    """The model's per-term material coefficients (see :class:`Coefficients`).

    Expanded buffers are returned as they are; learnable or grad-carrying raw values are
    broadcast here, so their gradients come back to them. Bending and torsion stiffnesses are
    the edge stiffness times the bend/torsion scale on each pair, and the drag coefficient is
    the drag rate times the particle mass.
    """
    raw = model._raw

    def full(field: str) -> torch.Tensor:
        v = getattr(model, field)
        return v.expand(raw[field]) if field in raw else v

    mass = full("particle_mass")
    edge = full("stretch_stiffness")
    # the bending/torsion pair (i, i+k) uses the stretch stiffness of its first edge (uniform
    # per strand in the per-particle material) times its scale
    bend = edge[..., :-1] * full("bend_scale")
    torsion = edge[..., :-2] * full("torsion_scale")
    return Coefficients(mass=mass, drag=full("drag") * mass, edge=edge, bend=bend, torsion=torsion,
                        integrity=full("integrity_stiffness"), angular=full("angular_stiffness"),
                        transition=full("integrity_transition"), breaking=full("integrity_break"),
                        soft_ratio=full("integrity_soft_ratio"))


def _all_zero(v) -> bool:
    if isinstance(v, torch.Tensor):
        return bool((v == 0).all())
    return float(v) == 0.0


def warn_if_no_sag_offset(params: Params) -> None:
    """SPEC §5: with κ_I = 0 the sag-free offset m g / κ_I is undefined: say so (once per build)."""
    if params.sag_free and _all_zero(params.integrity_stiffness):
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
