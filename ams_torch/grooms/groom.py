"""A groom: the rest shape of a set of strands, and how their roots sit on the head mesh.

A :class:`Groom` holds ``S`` strands of ``N`` particles each, ``rest_positions`` (S, N, 3)
float32 metres in the head frame, particle 0 the root (SPEC §1). Grooms read from files may
have strands of different point counts; those keep the raw polylines in ``strands`` (a list of
(n_i, 3) arrays) until they are resampled with :meth:`Groom.resampled` or
:func:`resample_strands`.

Root binding (grooms grown on a mesh): the root of strand s lies on triangle
``root_triangles[s]`` of the mesh, with barycentric coordinates ``root_barycentrics[s]`` over
its corners ``root_face_vertices[s]`` (vertex indices, in the order of the face). With it,
:meth:`Groom.root_positions` re-attaches the roots to a moved or deformed copy of the mesh and
:meth:`Groom.reattach` carries whole strands along with their triangles. Grooms read from files
have no binding until :meth:`Groom.bind_to` binds their roots to the nearest triangles of a
head mesh (SPEC §14), reporting the root–surface distances.

``Groom.width`` is the strand diameter in metres (default 70 µm), written by the formats that
store a thickness.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Sequence, Union

import numpy as np
import torch

__all__ = ["Groom", "resample_strands", "strand_lengths", "triangle_frames", "fps_order", "DEFAULT_WIDTH"]

log = logging.getLogger(__name__)

ArrayLike = Union[np.ndarray, torch.Tensor]

#: default strand diameter, metres (70 µm)
DEFAULT_WIDTH = 7e-5


# --------------------------------------------------------------------------------------------
# polyline helpers
# --------------------------------------------------------------------------------------------
def _pad_polylines(strands: Sequence[np.ndarray]) -> tuple:
    """Ragged list of (n_i, 3) → padded (S, M, 3) float64 (last point repeated) and counts (S,)."""
    counts = np.fromiter((len(s) for s in strands), dtype=np.int64, count=len(strands))
    if len(strands) == 0:
        return np.zeros((0, 1, 3)), counts
    if counts.min() < 1:
        raise ValueError("resample_strands: every strand needs at least one point")
    m = int(counts.max())
    out = np.empty((len(strands), m, 3), dtype=np.float64)
    for i, s in enumerate(strands):
        a = np.asarray(s, dtype=np.float64).reshape(-1, 3)
        out[i, : len(a)] = a
        out[i, len(a):] = a[-1]
    return out, counts


def _length_buckets(strands: Sequence[np.ndarray]):
    """Indices of ragged strands grouped by point count in [2^k, 2^(k+1)): padding each group
    costs at most twice its points (one very long strand does not pad every other one)."""
    counts = np.fromiter((len(s) for s in strands), dtype=np.int64, count=len(strands))
    if len(counts) and counts.min() < 1:
        raise ValueError("resample_strands: every strand needs at least one point")
    key = np.floor(np.log2(np.maximum(counts, 1))).astype(np.int64)
    return [np.flatnonzero(key == k) for k in np.unique(key)]


def strand_lengths(strands) -> np.ndarray:
    """Arc length of every strand, metres.

    strands: (S, N, 3) array/tensor or a list of (n_i, 3) arrays, metres → (S,) float64 array.
    """
    if isinstance(strands, torch.Tensor):
        strands = strands.detach().cpu().numpy()
    if isinstance(strands, np.ndarray) and strands.ndim == 3:
        p = strands.astype(np.float64, copy=False)
        if p.shape[1] < 2:
            return np.zeros(p.shape[0])
        return np.linalg.norm(np.diff(p, axis=1), axis=-1).sum(1)
    strands = [np.asarray(x).reshape(-1, 3) for x in strands]
    out = np.zeros(len(strands))
    sizes = np.fromiter((len(x) for x in strands), dtype=np.int64, count=len(strands))
    # vectorised blocks of about 8192 points: temporaries stay small for huge grooms
    cuts = np.searchsorted(np.cumsum(sizes), np.arange(8192, int(sizes.sum()) + 8192, 8192), side="right")
    bounds = np.unique(np.concatenate([[0], np.minimum(cuts, len(strands)), [len(strands)]]))
    for first, last in zip(bounds[:-1], bounds[1:]):
        block = strands[first:last]
        counts = sizes[first:last]
        pts = np.concatenate(block, 0).astype(np.float64) if int(counts.sum()) else np.zeros((0, 3))
        d = np.diff(pts, axis=0)
        seg = np.concatenate([np.sqrt(np.einsum("ij,ij->i", d, d)), [0.0]])
        ends = np.cumsum(counts)
        seg[ends[ends > 0] - 1] = 0.0  # the step from a strand's last point to the next strand's root
        nonempty = counts > 0
        out[first:last][nonempty] = np.add.reduceat(seg, (ends - counts)[nonempty])
    return out


def _resample_padded(p: np.ndarray, n: int, upto: Optional[np.ndarray], keep_length: bool) -> np.ndarray:
    """Arc-length uniform resampling of padded polylines p (S, M, 3) float64 to (S, n, 3).

    ``upto`` (S,) metres: sample [0, upto_s] of each strand instead of the whole strand (a cut;
    values beyond a strand's length are clamped to it).
    """
    s_count, m, _ = p.shape
    if m == 1:
        return np.repeat(p, n, axis=1)
    seg = np.linalg.norm(np.diff(p, axis=1), axis=-1)  # (S, M-1)
    cum = np.concatenate([np.zeros((s_count, 1)), np.cumsum(seg, axis=1)], axis=1)  # (S, M)
    total = cum[:, -1]
    target = total if upto is None else np.minimum(np.asarray(upto, dtype=np.float64), total)
    t = np.linspace(0.0, 1.0, n)
    s = target[:, None] * t[None, :]  # (S, n)
    s[:, -1] = target  # exact end (linspace rounding)
    # last index j with cum[j] <= s, limited to a valid segment start
    j = torch.searchsorted(torch.from_numpy(cum), torch.from_numpy(s), right=True).numpy() - 1
    j = np.clip(j, 0, m - 2)
    c0 = np.take_along_axis(cum, j, 1)
    sl = np.take_along_axis(seg, j, 1)
    frac = np.where(sl > 0, (s - c0) / np.where(sl > 0, sl, 1.0), 0.0)
    frac = np.clip(frac, 0.0, 1.0)[..., None]
    a = np.take_along_axis(p, j[..., None], 1)
    b = np.take_along_axis(p, (j + 1)[..., None], 1)
    out = a + frac * (b - a)
    if keep_length and n > 1:
        d = np.diff(out, axis=1)
        new_len = np.linalg.norm(d, axis=-1).sum(1)
        scale = np.where(new_len > 0, target / np.where(new_len > 0, new_len, 1.0), 1.0)
        out = np.concatenate([out[:, :1], out[:, :1] + np.cumsum(d * scale[:, None, None], axis=1)], axis=1)
    return out


def resample_strands(strands, n: int, keep_length: bool = True, lengths=None):
    """Resample polylines to ``n`` points each, uniformly in arc length.

    Args:
        strands: (S, M, 3) array or tensor, or a list of (n_i, 3) arrays (ragged), metres.
            Point 0 is the root and stays where it is.
        n: points per output strand (≥ 2).
        keep_length: sampling a polyline at uniform arc length cuts its corners, so the new
            polyline is slightly shorter (relative loss ≈ (turning angle per new segment)² / 24).
            With ``keep_length`` (default) the new segment vectors are scaled by one factor per
            strand so that each strand keeps its length exactly; points then move off the
            original polyline by at most that relative loss times their distance to the root.
            With ``keep_length=False`` the points lie exactly on the input polyline at arc
            lengths ``L · k / (n − 1)``.
        lengths: optional (S,) metres: take only the first ``lengths[s]`` metres of each strand
            (a haircut; lengths beyond a strand's own are clamped to it).

    Returns:
        (S, n, 3) positions, metres: a float64 ``np.ndarray`` for array/list input, a tensor
        of the input's dtype and device for tensor input.
    """
    n = int(n)
    if n < 2:
        raise ValueError(f"resample_strands: n must be at least 2, got {n}")
    as_tensor = isinstance(strands, torch.Tensor)
    if as_tensor:
        ref = strands
        p = strands.detach().cpu().double().numpy()
    elif isinstance(strands, np.ndarray) and strands.ndim == 3:
        p = strands.astype(np.float64, copy=False)
    else:
        strands = list(strands)
        for i, x in enumerate(strands):
            if np.ndim(x) != 2 or np.shape(x)[-1] != 3:
                raise ValueError(f"resample_strands: strand {i} must be (n, 3); got shape {np.shape(x)}")
        upto = None if lengths is None else np.broadcast_to(np.asarray(lengths, dtype=np.float64), (len(strands),))
        out = np.empty((len(strands), n, 3), dtype=np.float64)
        for idx in _length_buckets(strands):
            p, _ = _pad_polylines([strands[i] for i in idx])
            out[idx] = _resample_padded(p, n, None if upto is None else upto[idx], keep_length)
        return out
    if p.ndim != 3 or p.shape[-1] != 3:
        raise ValueError(f"resample_strands: strands must be (S, M, 3) or a list of (n_i, 3); got {p.shape}")
    if lengths is not None:
        lengths = np.broadcast_to(np.asarray(lengths, dtype=np.float64), (p.shape[0],))
    out = _resample_padded(p, n, lengths, keep_length)
    if as_tensor:
        return torch.as_tensor(out, dtype=ref.dtype if ref.is_floating_point() else torch.float32, device=ref.device)
    return out


# --------------------------------------------------------------------------------------------
# triangle frames
# --------------------------------------------------------------------------------------------
def triangle_frames(corners: torch.Tensor) -> torch.Tensor:
    """Orthonormal frame of each triangle: columns (edge tangent, bitangent, normal).

    corners: (..., 3, 3) metres, the corners (v0, v1, v2) of each triangle (rows) →
    (..., 3, 3) rotation whose columns are t = (v1 − v0)/|v1 − v0|, b = n × t and the unit
    normal n ∝ (v1 − v0) × (v2 − v0).
    """
    e1 = corners[..., 1, :] - corners[..., 0, :]
    e2 = corners[..., 2, :] - corners[..., 0, :]
    t = e1 / e1.norm(dim=-1, keepdim=True).clamp_min(1e-30)
    nrm = torch.linalg.cross(e1, e2, dim=-1)
    nrm = nrm / nrm.norm(dim=-1, keepdim=True).clamp_min(1e-30)
    b = torch.linalg.cross(nrm, t, dim=-1)
    return torch.stack((t, b, nrm), dim=-1)


# --------------------------------------------------------------------------------------------
# Groom
# --------------------------------------------------------------------------------------------
def _as_tensor(x, dtype) -> Optional[torch.Tensor]:
    if x is None:
        return None
    if isinstance(x, torch.Tensor):
        return x.to(dtype)
    return torch.as_tensor(np.asarray(x), dtype=dtype)


@dataclass
class Groom:
    """Rest shape of a groom in the head frame, with the binding of its roots to the mesh.

    Fields:
        rest_positions: (S, N, 3) float32 tensor, metres, head frame; particle 0 is the root.
            ``None`` for a ragged groom (strands of different point counts, see ``strands``).
        root_triangles: (S,) int64 tensor, face index of each root's triangle, or ``None``
            (grooms read from files that carry no binding).
        root_barycentrics: (S, 3) float32 tensor, barycentric coordinates of each root over
            the corners ``root_face_vertices`` (rows sum to 1), or ``None``.
        root_face_vertices: (S, 3) int64 tensor, vertex indices of each root's triangle (the
            mesh's ``faces[root_triangles]``), or ``None``.
        root_rest_frames: (S, 3, 3) float32 tensor, :func:`triangle_frames` of each root's
            triangle on the mesh the groom was grown on (used by :meth:`reattach`), or ``None``.
        strands: optional list of S float32 arrays (n_i, 3), metres: the raw polylines of a
            groom whose strands have different point counts (read from a file); converted to
            float32 on construction.
        metadata: free-form dict (growth parameters, seed, source file, format extras).
        width: strand diameter, metres (default 7e-5 = 70 µm, a typical human hair; the range
            is about 17–180 µm). Written by the file formats that store a thickness (``.hair``
            thickness, USD ``widths``); set from files that carry one (USD widths, a plausible
            ``.hair`` default thickness). Not used by the dynamics.
    """

    rest_positions: Optional[torch.Tensor] = None
    root_triangles: Optional[torch.Tensor] = None
    root_barycentrics: Optional[torch.Tensor] = None
    root_face_vertices: Optional[torch.Tensor] = None
    root_rest_frames: Optional[torch.Tensor] = None
    strands: Optional[List[np.ndarray]] = None
    metadata: Dict[str, Any] = field(default_factory=dict)
    width: float = DEFAULT_WIDTH

    def __post_init__(self):
        try:
            self.width = float(self.width)
        except (TypeError, ValueError):
            raise ValueError(f"Groom.width must be a positive number of metres; got {self.width!r}") from None
        if not (math.isfinite(self.width) and self.width > 0):
            raise ValueError(f"Groom.width must be a positive finite number of metres; got {self.width!r}")
        self.rest_positions = _as_tensor(self.rest_positions, torch.float32)
        self.root_triangles = _as_tensor(self.root_triangles, torch.int64)
        self.root_barycentrics = _as_tensor(self.root_barycentrics, torch.float32)
        self.root_face_vertices = _as_tensor(self.root_face_vertices, torch.int64)
        self.root_rest_frames = _as_tensor(self.root_rest_frames, torch.float32)
        if self.strands is not None:
            self.strands = [np.asarray(s, dtype=np.float32).reshape(-1, 3) for s in self.strands]
        if self.rest_positions is None and self.strands is None:
            raise ValueError("Groom needs rest_positions (S, N, 3) or a list of strands")
        if self.rest_positions is not None:
            if self.rest_positions.dim() != 3 or self.rest_positions.shape[-1] != 3:
                raise ValueError(f"Groom.rest_positions must be (S, N, 3); got {tuple(self.rest_positions.shape)}")
            if self.strands is not None and len(self.strands) != self.rest_positions.shape[0]:
                raise ValueError("Groom.strands and rest_positions disagree on the number of strands")
        s = self.num_strands
        for name, shape in (("root_triangles", (s,)), ("root_barycentrics", (s, 3)),
                            ("root_face_vertices", (s, 3)), ("root_rest_frames", (s, 3, 3))):
            v = getattr(self, name)
            if v is not None and tuple(v.shape) != shape:
                raise ValueError(f"Groom.{name} must have shape {shape}; got {tuple(v.shape)}")

    # -- sizes -----------------------------------------------------------------------------
    @property
    def num_strands(self) -> int:
        """S, the number of strands."""
        return int(self.rest_positions.shape[0]) if self.rest_positions is not None else len(self.strands)

    @property
    def num_particles(self) -> Optional[int]:
        """N, particles per strand; ``None`` for a ragged groom."""
        return int(self.rest_positions.shape[1]) if self.rest_positions is not None else None

    def __len__(self) -> int:
        return self.num_strands

    @property
    def has_binding(self) -> bool:
        """Whether the roots are bound to mesh triangles (needed by :meth:`root_positions`)."""
        return self.root_barycentrics is not None and self.root_face_vertices is not None

    def polylines(self) -> List[np.ndarray]:
        """The strands as a list of S float32 arrays (n_i, 3), metres."""
        if self.strands is not None:
            return self.strands
        return list(self.rest_positions.detach().cpu().numpy())

    def lengths(self) -> np.ndarray:
        """Arc length of every strand, (S,) float64 metres."""
        if self.rest_positions is not None:
            return strand_lengths(self.rest_positions)
        return strand_lengths(self.strands)

    # -- reshaping -------------------------------------------------------------------------
    def resampled(self, n: int, keep_length: bool = True) -> "Groom":
        """A copy with every strand resampled to ``n`` particles, uniformly in arc length.

        Strand lengths are kept (see :func:`resample_strands`); the root binding is kept.
        Returns a Groom with ``rest_positions`` (S, n, 3) float32 and ``strands=None``.
        """
        src = self.rest_positions.double() if self.strands is None else self.strands
        pos = resample_strands(src, n, keep_length=keep_length)
        meta = dict(self.metadata)
        meta["resampled_to"] = int(n)
        return Groom(torch.as_tensor(np.asarray(pos), dtype=torch.float32), self.root_triangles,
                     self.root_barycentrics, self.root_face_vertices, self.root_rest_frames, None, meta, self.width)

    def subset(self, index) -> "Groom":
        """The strands selected by ``index`` (slice, int array or bool mask over S), as a Groom."""
        if isinstance(index, torch.Tensor):
            index = index.detach().cpu().numpy()
        idx = torch.from_numpy(np.atleast_1d(np.arange(self.num_strands)[index]).astype(np.int64))

        def pick(t):
            return None if t is None else t[idx]
        strands = None if self.strands is None else [self.strands[int(i)] for i in idx]
        return Groom(pick(self.rest_positions), pick(self.root_triangles), pick(self.root_barycentrics),
                     pick(self.root_face_vertices), pick(self.root_rest_frames), strands, dict(self.metadata),
                     self.width)

    # -- binding to the mesh ---------------------------------------------------------------
    def _need_binding(self):
        if not self.has_binding:
            raise ValueError("this groom has no root binding (root_barycentrics/root_face_vertices); "
                             "grooms read from strand-only files cannot be re-attached")

    def _corners(self, mesh_vertices) -> torch.Tensor:
        v = mesh_vertices if isinstance(mesh_vertices, torch.Tensor) else torch.as_tensor(np.asarray(mesh_vertices))
        if not v.is_floating_point():
            v = v.double()
        if v.dim() < 2 or v.shape[-1] != 3:
            raise ValueError(f"mesh_vertices must be (..., V, 3); got {tuple(v.shape)}")
        fv = self.root_face_vertices.to(v.device)
        if int(fv.max()) >= v.shape[-2]:
            raise ValueError(f"mesh_vertices has {v.shape[-2]} vertices but the groom refers to vertex {int(fv.max())}")
        return v[..., fv, :]  # (..., S, 3 corners, 3)

    def root_positions(self, mesh_vertices) -> torch.Tensor:
        """Roots re-attached to a (moved or deformed) copy of the mesh the groom was grown on.

        mesh_vertices: (..., V, 3) metres, same vertex order as the growth mesh (tensor or
        array; leading batch dims allowed). Returns (..., S, 3) metres, dtype of the input
        (float64 for integer/array input): ``Σ_k b_k v[f_k]``. Differentiable w.r.t. tensors.
        """
        self._need_binding()
        corners = self._corners(mesh_vertices)
        b = self.root_barycentrics.to(device=corners.device, dtype=corners.dtype)
        return (b[..., None] * corners).sum(-2)

    def reattach(self, mesh_vertices) -> torch.Tensor:
        """Rest strands carried along with their root triangles on a moved/deformed mesh.

        Each strand moves rigidly with the frame of its root triangle:
        ``x' = r' + F' Fᵀ (x − r)``, where r, F are the root and triangle frame on the growth
        mesh and r', F' on ``mesh_vertices``. For a rigid motion of the mesh this is exactly
        that motion.

        mesh_vertices: (..., V, 3) metres, vertex order of the growth mesh.
        Returns (..., S, N, 3) metres in the dtype of the input (float64 for arrays).
        """
        self._need_binding()
        if self.rest_positions is None:
            raise ValueError("reattach needs rest_positions; resample the ragged groom first (Groom.resampled)")
        if self.root_rest_frames is None:
            raise ValueError("this groom has no root_rest_frames; it cannot be re-attached by frames")
        corners = self._corners(mesh_vertices)
        dt, dev = corners.dtype, corners.device
        new_frames = triangle_frames(corners)  # (..., S, 3, 3)
        new_roots = (self.root_barycentrics.to(dev, dt)[..., None] * corners).sum(-2)
        x = self.rest_positions.to(dev, dt)
        local = torch.einsum("sji,snj->sni", self.root_rest_frames.to(dev, dt), x - x[:, :1])
        return new_roots[..., None, :] + torch.einsum("...sij,snj->...sni", new_frames, local)

    def bind_to(self, mesh, max_distance: float = 5e-3, *, snap: bool = False) -> "Groom":
        """A copy whose roots are bound to the nearest triangles of ``mesh`` (SPEC §14).

        Every root (particle 0) is matched to the closest point of the mesh (point-cloud-utils'
        AABB closest-point query), which gives its triangle and barycentric coordinates; the
        copy then carries ``root_triangles``, ``root_barycentrics``, ``root_face_vertices`` and
        ``root_rest_frames`` like a grown groom, so :meth:`root_positions` and :meth:`reattach`
        make the roots follow the mesh.

        Args:
            mesh: ``trimesh.Trimesh`` (or anything with ``vertices`` (V, 3) and ``faces``
                (F, 3)) in metres, in the groom's frame (import both with the same units,
                up axis and transform). Open meshes are fine.
            max_distance: metres; a root farther than this from the surface is an error
                (default 5 mm: real grooms sit within a millimetre of their scalp).
            snap: move each strand rigidly by (closest point − root) so that its root lies on
                the surface; by default the strands are kept as they are, and
                :meth:`root_positions` on the same mesh returns the closest points (they differ
                from the stored roots by the reported distances).

        Returns:
            The bound copy. ``metadata["binding"]`` holds ``median_distance`` and
            ``max_distance`` (metres, root–surface, before snapping), ``mean_distance``,
            ``max_allowed``, ``mesh`` (its ``metadata["source"]`` or name), ``snapped``; the same
            numbers are logged at INFO level.

        Raises:
            ValueError: roots beyond ``max_distance`` (the message names the count, the first
            strand indices and the farthest distance), a bad mesh or ``max_distance``.
        """
        from ams_torch.geometry.mesh import closest_points

        max_distance = float(max_distance)
        if not (math.isfinite(max_distance) and max_distance >= 0):
            raise ValueError(f"bind_to: max_distance must be a non-negative number of metres; got {max_distance!r}")
        name = str(getattr(mesh, "metadata", {}).get("source") or getattr(mesh, "metadata", {}).get("name") or "mesh")
        roots = np.stack([np.asarray(p[0], dtype=np.float64) for p in self.polylines()]) if self.num_strands \
            else np.zeros((0, 3))
        dist, fid, bary, surface = closest_points(mesh, roots)
        verts, faces = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)
        far = np.flatnonzero(dist > max_distance)
        if len(far):
            shown = ", ".join(str(int(i)) for i in far[:10]) + (", ..." if len(far) > 10 else "")
            raise ValueError(f"bind_to: {len(far)} of {len(roots)} roots are farther than max_distance = "
                             f"{max_distance * 1e3:.4g} mm from {name} (farthest: strand {int(far[np.argmax(dist[far])])} "
                             f"at {dist.max() * 1e3:.4g} mm); strands {shown}. Check the units, up_axis and transform "
                             "of the groom and the mesh, or raise max_distance.")
        fv = faces[fid]
        corners = torch.as_tensor(verts[fv])  # (S, 3, 3)
        stats = dict(median_distance=float(np.median(dist)) if len(dist) else 0.0,
                     max_distance=float(dist.max()) if len(dist) else 0.0,
                     mean_distance=float(dist.mean()) if len(dist) else 0.0,
                     max_allowed=max_distance, mesh=name, snapped=bool(snap))
        log.info("bound %d roots to %s: root-surface distance median %.3g mm, max %.3g mm%s", len(roots), name,
                 stats["median_distance"] * 1e3, stats["max_distance"] * 1e3, " (snapped)" if snap else "")
        meta = dict(self.metadata)
        meta["binding"] = stats
        rest, strands = self.rest_positions, self.strands
        if snap:
            shift = surface - roots  # (S, 3)
            if rest is not None:
                rest = (rest.double() + torch.as_tensor(shift)[:, None, :]).float()
            if strands is not None:
                strands = [np.asarray(p, np.float64) + d for p, d in zip(strands, shift)]
        return Groom(rest, torch.as_tensor(fid), torch.as_tensor(bary, dtype=torch.float32), torch.as_tensor(fv),
                     triangle_frames(corners).float(), strands, meta, self.width)

    # -- misc --------------------------------------------------------------------------------
    def to(self, device) -> "Groom":
        """A copy with the tensors on ``device`` (``strands`` stay numpy arrays)."""
        def mv(t):
            return None if t is None else t.to(device)
        return Groom(mv(self.rest_positions), mv(self.root_triangles), mv(self.root_barycentrics),
                     mv(self.root_face_vertices), mv(self.root_rest_frames), self.strands, dict(self.metadata),
                     self.width)

    def __repr__(self) -> str:
        shape = (f"{self.num_strands}x{self.num_particles}" if self.rest_positions is not None
                 else f"{self.num_strands} ragged strands")
        name = self.metadata.get("preset") or self.metadata.get("source") or ""
        extra = f", {name}" if name else ""
        return f"Groom({shape}, binding={'yes' if self.has_binding else 'no'}{extra})"


def fps_order(roots: torch.Tensor, count: int, start: int | None = None) -> torch.Tensor:
    """Greedy farthest-point order on root positions.

    roots: (S, 3) metres. Returns (count,) long indices; the first k entries are the FPS choice
    of k guides for every k ≤ count. Starts at ``start`` or, by default, the root nearest the
    centroid (deterministic; ties broken by the lowest index).
    """
    roots = torch.as_tensor(roots).detach().to(torch.float64)
    s = roots.shape[0]
    if not 1 <= count <= s:
        raise ValueError(f"guide count {count} must be in [1, {s}] (the number of strands)")
    if start is None:
        start = int((roots - roots.mean(0)).norm(dim=-1).argmin())
    idx = torch.empty(count, dtype=torch.long)
    idx[0] = start
    dist = (roots - roots[start]).square().sum(-1)
    for k in range(1, count):
        nxt = int(dist.argmax())
        idx[k] = nxt
        dist = torch.minimum(dist, (roots - roots[nxt]).square().sum(-1))
    return idx
