"""The default head mesh (procedural) and a simple hanging groom on it.

The default head is built procedurally from an analytic implicit field (ellipsoids for the
cranium, face, jaw, chin, nose and ears, a capsule for the neck, joined by smooth unions).
A subdivided icosphere is projected radially onto the field's outermost zero crossing from a
centre inside the head, then relaxed tangentially and re-projected onto the surface. The
icosphere's connectivity is kept throughout, so the result is a closed, manifold, consistently
oriented surface (watertight by construction).

Head frame (metres): +y up, +z toward the face, +x toward the head's left ear; the origin sits
roughly at the centre of the skull at ear level. Crown to chin is about 0.22 m; the neck reaches
down to y ≈ −0.22.
"""
from __future__ import annotations

import functools
import logging
from typing import Dict

import numpy as np
import torch
import trimesh

__all__ = ["default_head", "head_implicit", "hanging_groom"]

log = logging.getLogger(__name__)

# Ellipsoids: centre (m), radii (m). Capsule: end points (m), radius (m).
_CRANIUM = ((0.0, 0.025, -0.012), (0.074, 0.098, 0.094))
_FACE = ((0.0, -0.025, 0.028), (0.062, 0.080, 0.068))
_JAW = ((0.0, -0.072, 0.030), (0.050, 0.040, 0.052))
_CHIN = ((0.0, -0.098, 0.062), (0.021, 0.015, 0.016))
_NOSE = ((0.0, -0.012, 0.094), (0.011, 0.026, 0.016))
_NOSE_TIP = ((0.0, -0.030, 0.104), (0.012, 0.010, 0.010))
_BROW = ((0.0, 0.035, 0.070), (0.055, 0.018, 0.020))
_EAR = ((0.072, -0.005, -0.008), (0.014, 0.031, 0.020))
_NECK = ((0.0, -0.175, -0.022), (0.0, -0.060, -0.012), 0.052)
_CENTRE = np.array([0.0, -0.03, -0.005])  # projection centre (inside every part but the ears)


def _ellipsoid(p: np.ndarray, centre, radii) -> np.ndarray:
    """Approximate signed distance to an axis-aligned ellipsoid (exact on the surface)."""
    r = np.asarray(radii)
    q = (p - np.asarray(centre)) / r
    k0 = np.sqrt(np.einsum("...i,...i->...", q, q))
    q = q / r
    k1 = np.sqrt(np.einsum("...i,...i->...", q, q))
    return k0 * (k0 - 1.0) / np.maximum(k1, 1e-12)


def _capsule(p: np.ndarray, a, b, r) -> np.ndarray:
    a, b = np.asarray(a), np.asarray(b)
    ab = b - a
    h = np.clip(((p - a) @ ab) / (ab @ ab), 0.0, 1.0)
    return np.linalg.norm(p - a - h[..., None] * ab, axis=-1) - r


def _smin(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth minimum (smooth union of two implicit solids), blend width k (m)."""
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b * (1 - h) + a * h - k * h * (1 - h)


def head_implicit(p: np.ndarray) -> np.ndarray:
    """Implicit field of the default head, negative inside. p: (..., 3) metres → (...) metres.

    Close to a signed distance near the surface, but not exact (smooth unions, ellipsoid
    approximation); use :class:`ams_torch.SDFGrid` on the mesh for true distances.
    """
    p = np.asarray(p, dtype=np.float64)
    f = _smin(_ellipsoid(p, *_CRANIUM), _ellipsoid(p, *_FACE), 0.03)
    f = _smin(f, _ellipsoid(p, *_JAW), 0.02)
    f = _smin(f, _ellipsoid(p, *_CHIN), 0.012)
    f = _smin(f, _ellipsoid(p, *_BROW), 0.012)
    f = _smin(f, _ellipsoid(p, *_NOSE), 0.010)
    f = _smin(f, _ellipsoid(p, *_NOSE_TIP), 0.008)
    ear_c, ear_r = _EAR
    mirrored = (-ear_c[0],) + tuple(ear_c[1:])
    f = _smin(f, _ellipsoid(p, ear_c, ear_r), 0.010)
    f = _smin(f, _ellipsoid(p, mirrored, ear_r), 0.010)
    f = _smin(f, _capsule(p, *_NECK), 0.03)
    return f


def _implicit_grad(p: np.ndarray, h: float = 1e-5) -> np.ndarray:
    e = np.eye(3) * h
    return np.stack([(head_implicit(p + e[i]) - head_implicit(p - e[i])) / (2 * h) for i in range(3)], -1)


def _outermost_root(dirs: np.ndarray, r_max: float = 0.26, step: float = 2e-3) -> np.ndarray:
    """Distance along each unit ray from _CENTRE to the outermost zero of the field."""
    ts = np.arange(r_max, 0.0, -step)
    hi = np.full(len(dirs), r_max)  # outside
    lo = np.zeros(len(dirs))
    found = np.zeros(len(dirs), bool)
    for t in ts:  # march inward (rays not yet inside only) until the first inside sample
        todo = np.flatnonzero(~found)
        if len(todo) == 0:
            break
        new = todo[head_implicit(_CENTRE + t * dirs[todo]) < 0]
        lo[new] = t
        hi[new] = min(t + step, r_max)
        found[new] = True
    if not found.all():
        raise RuntimeError("default head: a ray from the centre never entered the head")
    for _ in range(40):  # bisection: f(lo) < 0 <= f(hi)
        mid = 0.5 * (lo + hi)
        inside = head_implicit(_CENTRE + mid[:, None] * dirs) < 0
        lo = np.where(inside, mid, lo)
        hi = np.where(inside, hi, mid)
    return 0.5 * (lo + hi)


def _project(v: np.ndarray, iters: int = 3) -> np.ndarray:
    """Newton steps onto the zero set along the field gradient."""
    for _ in range(iters):
        g = _implicit_grad(v)
        v = v - (head_implicit(v) / np.maximum((g * g).sum(-1), 1e-12))[:, None] * g
    return v


def _regions(mesh: trimesh.Trimesh) -> Dict[str, np.ndarray]:
    c = mesh.triangles_center
    n = mesh.face_normals
    x, y, z = c[:, 0], c[:, 1], c[:, 2]
    ear_c = np.asarray(_EAR[0])
    near_ear = np.minimum(
        np.linalg.norm((c - ear_c) / (0.028, 0.045, 0.034), axis=1),
        np.linalg.norm((c - ear_c * (-1, 1, 1)) / (0.028, 0.045, 0.034), axis=1),
    ) < 1.0
    # Hairline: low at the nape (y ≈ −0.05), rising over the temples to the forehead (y ≈ 0.07).
    s = np.clip((z + 0.01) / 0.07, 0.0, 1.0)
    hairline = -0.05 + (0.07 + 0.05) * (s * s * (3 - 2 * s))
    scalp = (y > hairline) & ~near_ear & (n[:, 1] > -0.75)
    # Beard: cheeks below the cheekbones, jaw line, chin and upper lip, front half only.
    beard = (
        (y < -0.035) & (y > -0.125) & (z > 0.0) & ~near_ear & (np.abs(x) < 0.07)
        & ~((np.abs(x) < 0.016) & (y > -0.05) & (z > 0.09))  # nose tip stays bare
    )
    # Neck: below the jaw, and the bare skin of the nape behind the ears.
    neck = ((y < -0.125) | (z < -0.01)) & ~beard & ~scalp & ~near_ear
    ears = near_ear
    face = ~(scalp | beard | neck | ears)
    return {name: np.flatnonzero(m) for name, m in
            dict(scalp=scalp, beard=beard, face=face, ears=ears, neck=neck).items()}


@functools.lru_cache(maxsize=4)
def _build_head(subdivisions: int) -> trimesh.Trimesh:
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    dirs = np.asarray(sphere.vertices, dtype=np.float64)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    faces = np.asarray(sphere.faces, dtype=np.int64)
    v = _CENTRE + _outermost_root(dirs)[:, None] * dirs
    # Tangential relaxation (umbrella operator, tangential part only), then re-projection:
    # evens out the triangles that the radial map stretched (neck, ears) without moving the
    # surface. Small steps keep every triangle's orientation.
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    nbr_sum_count = np.bincount(edges[:, 0], minlength=len(v)).astype(np.float64)
    for _ in range(6):
        nbr_sum = np.zeros_like(v)
        np.add.at(nbr_sum, edges[:, 0], v[edges[:, 1]])
        lap = nbr_sum / nbr_sum_count[:, None] - v
        g = _implicit_grad(v)
        g /= np.linalg.norm(g, axis=1, keepdims=True)
        lap -= (lap * g).sum(1, keepdims=True) * g
        v = _project(v + 0.5 * lap)
    mesh = trimesh.Trimesh(v, faces, process=False)
    if not (mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0):
        raise RuntimeError("default head: construction did not give a closed, outward-oriented surface")
    mesh.metadata["regions"] = _regions(mesh)
    mesh.metadata["name"] = "ams_torch default head"
    return mesh


def default_head(subdivisions: int = 5) -> trimesh.Trimesh:
    """The default head: a deterministic watertight triangle mesh in metres, head frame.

    Cranium, face with brow, nose and chin, jaw, ears and a neck; +y up, face toward +z,
    about 0.15 m wide, 0.22 m crown to chin (0.35 m including the neck), origin near the
    middle of the skull. ``subdivisions`` is the icosphere level (5: 10,242 vertices,
    20,480 faces; each level ×4).

    ``mesh.metadata["regions"]`` maps region names to int64 arrays of face indices:
    ``scalp`` (hair-bearing top, back and sides), ``beard`` (cheeks, jaw, chin, upper lip),
    ``face``, ``ears``, ``neck``; together they partition the faces.

    The mesh is built once per process (cached) and a fresh copy is returned on each call.
    """
    mesh = _build_head(int(subdivisions))
    out = mesh.copy()
    out.metadata["regions"] = {k: v.copy() for k, v in mesh.metadata["regions"].items()}
    return out


def hanging_groom(mesh: trimesh.Trimesh, strands: int = 1000, particles: int = 32, length: float = 0.2,
                  region: str = "scalp", sdf=None, clearance: float = 0.003, seed: int = 0,
                  dtype=torch.float32) -> torch.Tensor:
    """A simple deterministic groom hanging from a region of a head mesh (tests, benchmarks, demos).

    Not the procedural grower of SPEC §9: roots are area-uniform samples of the region's
    triangles, each strand leaves along the face normal and turns smoothly outward-and-down
    over its first third; with ``sdf`` (an :class:`~ams_torch.geometry.sdf.SDFGrid` of ``mesh``) every
    particle after the root is kept at least ``clearance`` metres outside the head.

    Args:
        mesh: head mesh in metres with ``metadata["regions"]`` (e.g. :func:`default_head`).
        strands, particles: S and N. length: strand length, metres (±10 % per strand).
        region: name of the root region. seed: sampling seed.
    Returns: rest positions (S, N, 3), metres, head frame.
    """
    faces = np.asarray(mesh.metadata["regions"][region])
    sub = mesh.submesh([faces], append=True)
    roots, fid = trimesh.sample.sample_surface(sub, strands, seed=seed)
    rng = np.random.default_rng(seed)
    n = sub.face_normals[fid]
    horiz = n * np.array([1.0, 0.0, 1.0])
    hn = np.linalg.norm(horiz, axis=1, keepdims=True)
    horiz = np.where(hn > 1e-3, horiz / np.maximum(hn, 1e-9), np.array([0.0, 0.0, -1.0]))
    down = np.array([0.0, -1.0, 0.0])
    step = length * (1 + 0.1 * rng.uniform(-1, 1, size=(strands, 1))) / (particles - 1)
    x = np.zeros((strands, particles, 3))
    x[:, 0] = roots
    grid = None if sdf is None else sdf.to(dtype=torch.float64)
    for i in range(1, particles):
        s = (i - 1) / max(1, particles - 2)
        w = min(1.0, 3.0 * s)
        w = w * w * (3 - 2 * w)
        d = (1 - w) * n + w * (0.35 * horiz + down)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        xi = x[:, i - 1] + step * d
        if grid is not None:
            for _ in range(3):
                sig, nrm = grid.distance_and_normal(torch.from_numpy(xi))
                push = (clearance - sig).clamp_min(0).numpy()
                xi = xi + push[:, None] * nrm.numpy()
            # keep the segment length after the push
            seg = xi - x[:, i - 1]
            xi = x[:, i - 1] + seg / np.linalg.norm(seg, axis=1, keepdims=True) * step
        x[:, i] = xi
    return torch.as_tensor(x, dtype=dtype)
