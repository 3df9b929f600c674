"""Procedural hair growth (SPEC §9; supplement "Procedural Growth", Eq. 4–7); presets in :mod:`ams_torch.grooms.presets`.

Roots are uniform random samples on the triangles of a mesh region. The initial direction
``p_dir⁰`` of a strand is the barycentric blend of its triangle's vertex normals plus a noise
vector with entries from U(−1, 1) (scaled by ``noise``). Then, for i = 1 … K (K growth steps):

    p_grav^i  = (0, −i p_γ, 0)
    p_dir^i'  = p_dir^{i−1} + p_grav^{i−1} · max(p_Γ, 1 − |p_dir^{i−1} · (0, 1, 0)|)
    H^i       = (p_h cos(i p_freq + φ), 1, p_h sin(i p_freq + φ))
    p_dir^i   = p_dir^i' + p_Ω (p_dir^i' − H^i)
    x_i       = x_{i−1} + p_τ · normalize(p_dir^i)

exactly as written (``p_dir`` is not normalised between steps, as in the paper). φ is a
per-strand helix phase, 0 unless ``phase_jitter`` is set (the paper has none, so every strand
curls in step with the others).

Clumps. Real hair curls and waves in clumps: neighbouring strands run together. With
``clump_radius`` r > 0 the roots are split into clumps by proximity (:func:`~ams_torch.grooms.clumps.clump_labels`:
clump centres are roots taken in farthest-point order until every root lies within r of one;
each root joins its nearest centre), and every per-strand random draw (helix phase, helix-radius
jitter, the noise of p_dir⁰, the length jitter) becomes ``(1 − w) × its clump's draw + w × its
own`` with w = ``clump_jitter``: members of a clump share phase and wave/curl shape up to a
small per-strand jitter. r = 0 (the default) leaves every strand on its own, as in the paper.
Neighbouring clumps are not independent either when ``phase_length`` ℓ > 0: the clumps' phases
are a smooth random field over the roots, φ_c = (phase_jitter/π) arg Σ_d exp(−|c_c − c_d|²/2ℓ²)
e^{iθ_d} over the clump centres c_d with θ_d ~ U(−π, π) (the argument of a sum of random
phasors is uniform, so each φ_c is still uniform in ±phase_jitter), so waves stay coherent over
about ℓ and drift apart beyond it, while clumps stay visible as clumps.

Parameters (keyword names; the paper's symbols are accepted as aliases, see ``ALIASES``):

========================  ===========  ========  =================================================
name                      paper        default   meaning
========================  ===========  ========  =================================================
``step``                  p_τ          0.005     segment length of a growth step, metres
``droop``                 p_γ          0.002     gravity influence (dimensionless)
``helix_radius``          p_h          0.0       helix radius (dimensionless; sets curliness)
``helix_freq``            p_freq       1.0       helix angle per step, radians
``spiral``                p_Ω          0.017     spiral impact factor
``gravity_floor``         p_Γ          0.2       lower bound of the gravity factor
``noise``                 —            1.0       scale of the U(−1, 1)³ noise of p_dir⁰ (paper: 1)
``root_min_cos``          —            0.3       p_dir⁰ makes at least this cosine with the normal
``comb``                  —            None      vector (3,) or ``f(roots, normals) → (S, 3)`` added to p_dir⁰
``phase_jitter``          —            0.0       φ ~ U(−phase_jitter, phase_jitter), radians
``helix_radius_jitter``   —            0.0       p_h · (1 + U(−j, j)) per strand
``length``                —            None      strand length(s) in metres, see below
``length_jitter``         —            0.0       lengths · (1 − U(0, j)) per strand
``clump_radius``          —            0.0       m; clumps of roots within this radius share draws
``clump_jitter``          —            0.05      share w of a clumped strand's own draws, in [0, 1]
``phase_length``          —            0.0       m; correlation length of the clumps' phases (with clumps)
``steps``                 —            None      K; default N − 1, or enough for ``length``
``collide``               —            True      keep grown points out of the mesh (SDF)
``margin``                —            0.002     clearance kept from the mesh when colliding, m
``sdf_resolution``        —            128       resolution of the SDF grid built for collisions
========================  ===========  ========  =================================================

Scale of p_h. ``p_dir`` is not normalised, and both the gravity term (which grows like i²) and
the factor (1 + p_Ω) per step make it longer along the strand, while the helix adds a rotating
part of fixed size ≈ p_Ω p_h / |e^{i p_freq} − (1 + p_Ω)|. So curls are strongest near the root
and relax toward the tip, and visible curls on drooping hair need p_h in the hundreds to
thousands (the presets use 600–3000); with p_γ = 0 a few tens already curl.

Lengths. Without ``length`` a strand grows K = N − 1 steps (N = ``particles``), so its length is
exactly K·p_τ and no resampling happens: p_τ sets the length, as in the paper's Figures 3–4.
With ``length`` (a float, an (S,) array or a callable ``f(roots (S, 3), normals (S, 3)) → (S,)``,
metres) the strands grow ``ceil(max length / p_τ)`` steps at p_τ and are then cut at their
length and resampled to N particles uniformly in arc length, keeping that length (a haircut:
short strands are the first part of a long one, curl scale unchanged). Note that the curl
period is 2π p_τ / p_freq metres of strand; resampling to fewer particles than growth steps
undersamples curls.

Collisions. With ``collide`` (default) every grown point whose signed distance to the mesh
is below ``margin`` is pushed out along the SDF normal, the step length is restored, and the
inward component of ``p_dir`` is removed (the strand slides over the surface instead of
re-entering it). This is needed because droop bends strands back onto the head. Roots lie
on the surface (σ = 0); every other particle ends at σ ≥ ``margin``/2 on the SDF grid
(tested with exact inside/outside queries on the mesh).

Roots. ``per_triangle=p_n`` samples p_n roots per selected triangle (the paper's literal
scheme; S = p_n × triangles). ``strands=S`` instead draws S roots by area-weighted sampling:
each root picks a triangle with probability proportional to its area, then a uniform point
on it — the same distribution as p_n per unit area, with an exact strand count.

Determinism: every random number comes from one ``numpy.random.Generator(PCG64(seed))`` drawn
in a fixed order (the clumps' draws after the strands', so an unclumped groom is the same as
before clumps existed), the clumps are a deterministic function of the roots, and the growth
runs in float64 on the CPU, so a seed gives the same groom bit for bit.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from typing import Any, Dict, Optional

import numpy as np
import torch

from ams_torch.grooms.clumps import clump_labels, neighbour_distance, strand_draws
from ams_torch.grooms.groom import Groom, resample_strands, triangle_frames

__all__ = ["GrowthParams", "ALIASES", "grow", "grow_from_roots", "sample_roots", "clump_labels",
           "neighbour_distance"]


@dataclass(frozen=True)
class GrowthParams:
    """Parameters of procedural growth; see the module docstring for the table of meanings.

    Units: ``step``, ``margin`` and ``length`` metres; ``helix_freq`` and ``phase_jitter``
    radians; the others dimensionless.
    """

    step: float = 0.005
    droop: float = 0.002
    helix_radius: float = 0.0
    helix_freq: float = 1.0
    spiral: float = 0.017
    gravity_floor: float = 0.2
    noise: float = 1.0
    root_min_cos: float = 0.3
    comb: Any = None
    phase_jitter: float = 0.0
    helix_radius_jitter: float = 0.0
    length: Any = None
    length_jitter: float = 0.0
    clump_radius: float = 0.0
    clump_jitter: float = 0.05
    phase_length: float = 0.0
    steps: Optional[int] = None
    collide: bool = True
    margin: float = 0.002
    sdf_resolution: int = 128

    def __post_init__(self):
        if not self.step > 0:
            raise ValueError(f"growth step p_τ must be positive, got {self.step}")
        if self.steps is not None and int(self.steps) < 1:
            raise ValueError(f"steps must be ≥ 1, got {self.steps}")
        if not -1.0 <= self.root_min_cos < 1.0:
            raise ValueError(f"root_min_cos must be in [−1, 1), got {self.root_min_cos}")
        if self.margin < 0:
            raise ValueError(f"margin must be ≥ 0, got {self.margin}")
        if not (isinstance(self.clump_radius, (int, float)) and math.isfinite(self.clump_radius)
                and self.clump_radius >= 0):
            raise ValueError(f"clump_radius must be a finite number ≥ 0 (m), got {self.clump_radius!r}")
        if not (isinstance(self.clump_jitter, (int, float)) and 0.0 <= self.clump_jitter <= 1.0):
            raise ValueError(f"clump_jitter must be in [0, 1], got {self.clump_jitter!r}")
        if not (isinstance(self.phase_length, (int, float)) and math.isfinite(self.phase_length)
                and self.phase_length >= 0):
            raise ValueError(f"phase_length must be a finite number ≥ 0 (m), got {self.phase_length!r}")

    @staticmethod
    def make(**kwargs) -> "GrowthParams":
        """Build from keywords, accepting the paper's symbols (``p_tau``, ``p_h``, …) too."""
        names = {f.name for f in fields(GrowthParams)}
        clean: Dict[str, Any] = {}
        for key, value in kwargs.items():
            name = ALIASES.get(key, key)
            if name not in names:
                raise TypeError(f"unknown growth parameter {key!r}; known: {sorted(names | set(ALIASES))}")
            if name in clean:
                raise TypeError(f"growth parameter {name!r} given twice (as {key!r} too)")
            clean[name] = value
        return GrowthParams(**clean)


#: The paper's symbols → :class:`GrowthParams` field names.
ALIASES = {
    "p_tau": "step", "p_τ": "step",
    "p_gamma": "droop", "p_γ": "droop",
    "p_h": "helix_radius",
    "p_freq": "helix_freq",
    "p_Omega": "spiral", "p_Ω": "spiral", "p_omega": "spiral",
    "p_Gamma": "gravity_floor", "p_Γ": "gravity_floor",
}


# --------------------------------------------------------------------------------------------
# roots
# --------------------------------------------------------------------------------------------
def _mesh_arrays(mesh):
    if isinstance(mesh, (tuple, list)) and len(mesh) == 2:
        import trimesh
        mesh = trimesh.Trimesh(np.asarray(mesh[0], dtype=np.float64), np.asarray(mesh[1], dtype=np.int64),
                               process=False)
    return mesh, np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)


def _region_faces(mesh, region, n_faces: int) -> np.ndarray:
    if region is None or (isinstance(region, str) and region == "all"):
        return np.arange(n_faces, dtype=np.int64)
    if isinstance(region, str):
        regions = getattr(mesh, "metadata", {}).get("regions", {}) if hasattr(mesh, "metadata") else {}
        if region not in regions:
            raise ValueError(f"mesh has no region {region!r} (known: {sorted(regions)}); pass face indices, "
                             f"'all' or None")
        faces = np.asarray(regions[region], dtype=np.int64)
    else:
        faces = np.asarray(region)
        if faces.dtype == bool:
            if faces.shape != (n_faces,):
                raise ValueError(f"boolean region mask must have shape ({n_faces},), got {faces.shape}")
            faces = np.flatnonzero(faces)
        faces = faces.astype(np.int64).reshape(-1)
    if faces.size == 0:
        raise ValueError(f"region {region if isinstance(region, str) else '(indices)'} selects no faces")
    if faces.min() < 0 or faces.max() >= n_faces:
        raise ValueError(f"region face indices must lie in [0, {n_faces}); got [{faces.min()}, {faces.max()}]")
    return faces


def sample_roots(mesh, region="scalp", strands: Optional[int] = None, per_triangle: Optional[int] = None,
                 rng: Optional[np.random.Generator] = None, seed: int = 0) -> Dict[str, np.ndarray]:
    """Sample root points on a mesh region.

    Args:
        mesh: ``trimesh.Trimesh`` (or ``(vertices (V, 3), faces (F, 3))``), metres.
        region: name in ``mesh.metadata["regions"]``, face indices / bool mask, or
            ``None``/``"all"`` for every face.
        strands: S roots by area-weighted triangle choice, then uniform on the triangle.
        per_triangle: p_n roots on every selected triangle (S = p_n × triangles), the paper's scheme.
        rng / seed: the random generator (default ``numpy.random.default_rng(seed)``).

    Returns a dict of float64/int64 arrays: ``triangles`` (S,), ``barycentrics`` (S, 3),
    ``face_vertices`` (S, 3), ``positions`` (S, 3) metres, ``normals`` (S, 3) unit blended
    vertex normals.
    """
    mesh, v, f = _mesh_arrays(mesh)
    rng = np.random.default_rng(seed) if rng is None else rng
    faces = _region_faces(mesh, region, len(f))
    if (strands is None) == (per_triangle is None):
        raise ValueError("give exactly one of strands= (area-weighted) and per_triangle= (p_n per triangle)")
    if per_triangle is not None:
        p_n = int(per_triangle)
        if p_n < 1:
            raise ValueError(f"per_triangle must be ≥ 1, got {per_triangle}")
        tri = np.repeat(faces, p_n)
    else:
        s = int(strands)
        if s < 1:
            raise ValueError(f"strands must be ≥ 1, got {strands}")
        corners = v[f[faces]]
        area = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
        if not area.sum() > 0:
            raise ValueError("the selected region has zero area")
        cdf = np.cumsum(area)
        cdf /= cdf[-1]
        pick = np.searchsorted(cdf, rng.random(s), side="right")
        tri = faces[np.minimum(pick, len(faces) - 1)]
    r = rng.random((len(tri), 2))
    sq = np.sqrt(r[:, 0])
    bary = np.stack([1.0 - sq, sq * (1.0 - r[:, 1]), sq * r[:, 1]], axis=1)
    fv = f[tri]
    pos = np.einsum("sk,skd->sd", bary, v[fv])
    vn = np.asarray(mesh.vertex_normals, dtype=np.float64)
    nrm = np.einsum("sk,skd->sd", bary, vn[fv])
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-30)
    return dict(triangles=tri, barycentrics=bary, face_vertices=fv, positions=pos, normals=nrm)


# --------------------------------------------------------------------------------------------
# the growth recurrence
# --------------------------------------------------------------------------------------------
class _Collider:
    """Signed distance + outward normal of the mesh for float64 numpy points (wraps an SDFGrid).

    Queries run in the grid's own dtype (float32 for ``SDFGrid.from_mesh``) on the CPU.
    """

    def __init__(self, sdf):
        self.sdf = sdf
        self.dtype = getattr(sdf, "dtype", torch.float32)

    def distance(self, x: np.ndarray) -> np.ndarray:
        return self.sdf.distance(torch.from_numpy(x).to(self.dtype)).double().numpy()

    def distance_and_normal(self, x: np.ndarray):
        sigma, normal = self.sdf.distance_and_normal(torch.from_numpy(x).to(self.dtype))
        return sigma.double().numpy(), normal.double().numpy()

    def push_out(self, x: np.ndarray, margin: float):
        """Move points (M, 3) with σ < margin out along the normal to σ ≈ margin → (x, moved (M,) bool)."""
        x = np.array(x, dtype=np.float64)
        idx = np.flatnonzero(self.distance(x) < margin)
        if idx.size:
            sigma, normal = self.distance_and_normal(x[idx])
            x[idx] += np.maximum(margin - sigma, 0.0)[:, None] * normal
        moved = np.zeros(len(x), dtype=bool)
        moved[idx] = True
        return x, moved


def _normalize(a: np.ndarray) -> np.ndarray:
    return a / np.maximum(np.linalg.norm(a, axis=-1, keepdims=True), 1e-300)


def grow_from_roots(roots, directions, steps: int, params: Optional[GrowthParams] = None, *,
                    phase=None, helix_radius=None, collider=None) -> np.ndarray:
    """Run the growth recurrence of SPEC §9 from given roots and initial directions.

    Args:
        roots: (S, 3) metres, particle 0 of every strand.
        directions: (S, 3) p_dir⁰ (not necessarily unit; its length matters, as in the paper).
        steps: K, growth steps; the strands get K + 1 points.
        params: :class:`GrowthParams` (``step``, ``droop``, ``helix_radius``, ``helix_freq``,
            ``spiral``, ``gravity_floor``, ``margin`` are used here).
        phase: optional (S,) helix phase φ, radians (default 0).
        helix_radius: optional (S,) per-strand p_h (default ``params.helix_radius``).
        collider: optional object with ``distance_and_normal(points (M, 3) tensor)`` (e.g. an
            ``SDFGrid``); grown points are then kept at σ ≥ ``params.margin`` as described in
            the module docstring.

    Returns:
        (S, K + 1, 3) float64 array, metres; consecutive points are ``step`` apart (up to the
        rare final push-out of a point the step-preserving projection could not free).
    """
    p = GrowthParams() if params is None else params
    x0 = np.asarray(roots, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3).copy()
    s = x0.shape[0]
    k_steps = int(steps)
    phi = np.zeros(s) if phase is None else np.asarray(phase, dtype=np.float64).reshape(s)
    ph = np.full(s, float(p.helix_radius)) if helix_radius is None else np.asarray(helix_radius, np.float64).reshape(s)
    col = None if collider is None else (collider if isinstance(collider, _Collider) else _Collider(collider))
    out = np.empty((s, k_steps + 1, 3), dtype=np.float64)
    out[:, 0] = x0
    x = x0
    tau, omega = float(p.step), float(p.spiral)
    for i in range(1, k_steps + 1):
        grav_y = -(i - 1) * p.droop  # p_grav^{i−1} = (0, −(i−1) p_γ, 0)
        factor = np.maximum(p.gravity_floor, 1.0 - np.abs(d[:, 1]))
        dp = d.copy()
        dp[:, 1] += grav_y * factor
        ang = i * p.helix_freq + phi
        h = np.stack([ph * np.cos(ang), np.ones(s), ph * np.sin(ang)], axis=1)
        d = dp + omega * (dp - h)
        step_dir = _normalize(d)
        xn = x + tau * step_dir
        if col is not None:
            _collide_step(col, x, xn, d, tau, p.margin)
        out[:, i] = xn
        x = xn
    return out


def _collide_step(col: _Collider, x: np.ndarray, xn: np.ndarray, d: np.ndarray, tau: float, margin: float):
    """Keep the new points ``xn`` (S, 3) at σ ≥ margin, in place; update ``d`` (S, 3) in place.

    Points below the margin are pushed out along the SDF normal and put back at distance
    ``tau`` from their predecessor ``x``, up to four times; a point still below margin/2
    after that is pushed out without restoring the step. Where a strand touched the
    surface, the inward normal component of p_dir is removed (the strand slides).
    """
    active = np.flatnonzero(col.distance(xn) < margin)
    if not active.size:
        return
    hit = active
    normals = np.zeros((len(hit), 3))
    where = np.arange(len(hit))  # position of each active point in ``hit``
    for _ in range(4):
        sigma, normal = col.distance_and_normal(xn[active])
        below = sigma < margin
        active, where, sigma, normal = active[below], where[below], sigma[below], normal[below]
        if not active.size:
            break
        normals[where] = normal
        pushed = xn[active] + (margin - sigma)[:, None] * normal
        xn[active] = x[active] + tau * _normalize(pushed - x[active])
    if active.size:  # a point the step-preserving projection could not free
        sigma, normal = col.distance_and_normal(xn[active])
        low = sigma < 0.5 * margin
        xn[active[low]] += (0.5 * margin - sigma[low])[:, None] * normal[low]
    inward = np.minimum((d[hit] * normals).sum(1), 0.0)
    d[hit] -= inward[:, None] * normals


def _initial_directions(normals: np.ndarray, noise: np.ndarray, min_cos: float) -> np.ndarray:
    """p_dir⁰ = n + noise, with the normal component raised so that cos(p_dir⁰, n) ≥ min_cos."""
    d = normals + noise
    a = (d * normals).sum(1)
    t = d - a[:, None] * normals
    tn = np.linalg.norm(t, axis=1)
    need = min_cos * tn / math.sqrt(1.0 - min_cos * min_cos)
    a_new = np.where(a < need, need, a)
    return t + a_new[:, None] * normals


def _sdf_for(mesh, resolution: int):
    from ams_torch.geometry.sdf import SDFGrid
    return SDFGrid.from_mesh(mesh, resolution=int(resolution))


def _describe(value):
    """A growth parameter as it is kept in metadata (callables and arrays summarised)."""
    if callable(value):
        return f"callable {getattr(value, '__qualname__', type(value).__name__)}"
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    arr = np.asarray(value)
    return arr.item() if arr.ndim == 0 else (arr.tolist() if arr.size <= 3 else f"array {arr.shape}")


def _resolve_lengths(length, roots: np.ndarray, normals: np.ndarray) -> Optional[np.ndarray]:
    if length is None:
        return None
    if callable(length):
        out = np.asarray(length(roots, normals), dtype=np.float64)
    else:
        out = np.asarray(length, dtype=np.float64)
    out = np.broadcast_to(out, (roots.shape[0],)).copy()
    if not np.all(np.isfinite(out)) or out.min() <= 0:
        raise ValueError("strand lengths must be finite and positive (metres)")
    return out


def grow(mesh, region="scalp", strands: Optional[int] = None, particles: int = 32, seed: int = 0, *,
         per_triangle: Optional[int] = None, sdf=None, **growth_params) -> Groom:
    """Grow a groom on a mesh region with the procedural scheme of SPEC §9.

    Args:
        mesh: ``trimesh.Trimesh`` in metres, head frame (+y up), e.g.
            ``ams_torch.grooms.head.default_head()``; or ``(vertices (V, 3), faces (F, 3))``.
        region: ``mesh.metadata["regions"]`` name (``"scalp"``, ``"beard"``), face indices or
            bool mask (F,), or ``None``/``"all"``.
        strands: S, number of strands (area-weighted root sampling). Default 1000 when
            neither ``strands`` nor ``per_triangle`` is given.
        particles: N, particles per output strand (≥ 2).
        seed: random seed; the same seed gives the same groom bit for bit.
        per_triangle: p_n roots per selected triangle (the paper's scheme) instead of ``strands``.
        sdf: collision field to reuse (``SDFGrid`` of this mesh); built from the mesh with
            ``sdf_resolution`` (and cached on disk by :mod:`ams_torch.geometry.sdf`) when ``collide``.
        **growth_params: :class:`GrowthParams` fields or the paper's symbols (``p_tau``,
            ``p_gamma``, ``p_h``, ``p_freq``, ``p_Omega``, ``p_Gamma``).

    Returns:
        :class:`Groom` with ``rest_positions`` (S, N, 3) float32 metres in the mesh frame,
        roots bound to their triangles, and ``metadata`` holding the parameters and seed.
    """
    params = GrowthParams.make(**growth_params)
    particles = int(particles)
    if particles < 2:
        raise ValueError(f"particles must be ≥ 2, got {particles}")
    if strands is None and per_triangle is None:
        strands = 1000
    mesh, verts, faces = _mesh_arrays(mesh)
    rng = np.random.default_rng(seed)
    root = sample_roots(mesh, region, strands=strands, per_triangle=per_triangle, rng=rng)
    s = root["positions"].shape[0]
    draws, clumps = strand_draws(rng, root["positions"], params)
    noise, phase, length_u = draws["noise"], draws["phase"], draws["length_u"]
    radius = params.helix_radius * (1.0 + draws["radius_u"] * params.helix_radius_jitter)
    if params.comb is not None:
        comb = params.comb(root["positions"], root["normals"]) if callable(params.comb) else params.comb
        noise = noise + np.broadcast_to(np.asarray(comb, dtype=np.float64), (s, 3))
    dirs = _initial_directions(root["normals"], noise, params.root_min_cos)

    lengths = _resolve_lengths(params.length, root["positions"], root["normals"])
    if lengths is not None:
        lengths = lengths * (1.0 - params.length_jitter * length_u)
    elif params.length_jitter > 0:
        k_nat = params.steps if params.steps is not None else particles - 1
        lengths = k_nat * params.step * (1.0 - params.length_jitter * length_u)
    if params.steps is not None:
        k_steps = int(params.steps)
    elif lengths is None:
        k_steps = particles - 1
    else:
        k_steps = max(1, int(math.ceil(float(lengths.max()) / params.step - 1e-9)))

    collider = None
    if params.collide:
        collider = _Collider(sdf if sdf is not None else _sdf_for(mesh, params.sdf_resolution))
    pts = grow_from_roots(root["positions"], dirs, k_steps, params, phase=phase, helix_radius=radius,
                          collider=collider)
    if lengths is not None or k_steps + 1 != particles:
        pts = resample_strands(pts, particles, keep_length=True, lengths=lengths)
        if collider is not None:  # resampling moves points by ~chord error: keep them out
            body, _ = collider.push_out(pts[:, 1:].reshape(-1, 3), 0.5 * params.margin)
            pts[:, 1:] = body.reshape(s, particles - 1, 3)
    corners = torch.as_tensor(verts[root["face_vertices"]])
    meta = dict(
        generator="ams_torch.grow",
        seed=int(seed),
        region=region if isinstance(region, str) or region is None else "custom",
        strands=int(s),
        particles=particles,
        per_triangle=None if per_triangle is None else int(per_triangle),
        growth_steps=k_steps,
        clumps=0 if clumps is None else int(clumps.max()) + 1,
        params={k: _describe(v) for k, v in asdict(params).items()},
        mesh=str(getattr(mesh, "metadata", {}).get("name", "")),
    )
    return Groom(
        rest_positions=torch.as_tensor(pts, dtype=torch.float32),
        root_triangles=torch.as_tensor(root["triangles"]),
        root_barycentrics=torch.as_tensor(root["barycentrics"], dtype=torch.float32),
        root_face_vertices=torch.as_tensor(root["face_vertices"]),
        root_rest_frames=triangle_frames(corners).float(),
        metadata=meta,
    )
