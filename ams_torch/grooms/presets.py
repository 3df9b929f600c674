"""Named presets of procedural growth (SPEC §9) on the default head: straight, wavy, curly, bob,
ponytail, fur, beard (:func:`preset`)."""
from __future__ import annotations

import math
from typing import Any, Dict, Optional

import numpy as np
import torch

from ams_torch.grooms.groom import Groom, resample_strands, triangle_frames
from ams_torch.grooms.growth import (ALIASES, _Collider, _mesh_arrays,
                                     _sdf_for, grow, sample_roots)

__all__ = ["preset", "PRESETS"]


def _smoothstep(t: np.ndarray) -> np.ndarray:
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _parted_comb(strength: float, part_x: float = 0.0, back: float = 2.0):
    """Comb for long hair: away from a parting at x = part_x, and backward at the front.

    Returns ``f(roots (S, 3), normals (S, 3)) → (S, 3)`` (added to p_dir⁰): strength × (side, 0,
    −back·front) where side = ±1 on either side of the parting (smoothed over 1 cm) and front
    rises from 0 at z = −0.03 to 1 at z = 0.05 (the forehead).
    """
    def comb(roots, normals):
        side = np.tanh((roots[:, 0] - part_x) / 0.01)
        front = _smoothstep((roots[:, 2] + 0.03) / 0.08)
        return strength * np.stack([side, np.zeros_like(side), -back * front], 1)
    return comb


def _bob_length(short: float, long: float, width: float = 0.03):
    """Asymmetric bob: strands on the −x side (the face's right) ``short``, on +x ``long`` (m)."""
    def length(roots, normals):
        w = 0.5 * (1.0 + np.tanh(roots[:, 0] / width))
        # the fringe over the forehead is cut shorter than the sides
        front = _smoothstep((roots[:, 2] - 0.02) / 0.06)
        return (short + (long - short) * w) * (1.0 - 0.45 * front)
    return length


#: The clumps of the wavy and curly presets (see :mod:`ams_torch.grooms.growth`): clumps of roots
#: within 15 mm share phase and shape (5 % per-strand jitter), the clumps' phases vary over ~4 cm.
#: Strands whose roots are 8 mm apart stay ~27 mm apart along their length instead of ~105 mm
#: (``scripts/clump_study.py``); override with ``clump_radius=0`` for independent strands.
_CLUMPS = dict(clump_radius=0.015, clump_jitter=0.05, phase_length=0.04)

_PRESET_PARAMS: Dict[str, Dict[str, Any]] = {
    "straight": dict(region="scalp", particles=32, params=dict(
        step=0.005, droop=0.3, noise=0.15, length=0.36, length_jitter=0.12, comb=_parted_comb(1.2, back=2.0))),
    "wavy": dict(region="scalp", particles=48, params=dict(
        step=0.005, droop=2.0, helix_radius=3000.0, helix_freq=0.5, noise=0.15, phase_jitter=math.pi,
        helix_radius_jitter=0.2, length=0.32, length_jitter=0.12, comb=_parted_comb(1.2, back=2.0), **_CLUMPS)),
    "curly": dict(region="scalp", particles=64, params=dict(
        step=0.006, droop=0.2, helix_radius=600.0, helix_freq=0.6, noise=0.2, phase_jitter=math.pi,
        helix_radius_jitter=0.2, length=0.26, length_jitter=0.15, **_CLUMPS)),
    "bob": dict(region="scalp", particles=32, params=dict(
        step=0.004, droop=0.3, noise=0.15, length=_bob_length(0.09, 0.21), length_jitter=0.05,
        comb=_parted_comb(1.2, part_x=0.025, back=2.0))),
    "fur": dict(region=None, particles=8, params=dict(
        step=0.0015, droop=0.05, noise=0.5, length=0.015, length_jitter=0.3, root_min_cos=0.5, margin=0.001)),
    "beard": dict(region="beard", particles=12, params=dict(
        step=0.003, droop=0.08, helix_radius=60.0, helix_freq=0.8, noise=0.4, phase_jitter=math.pi,
        length=0.04, length_jitter=0.3, root_min_cos=0.4, margin=0.001)),
}

#: Names accepted by :func:`preset`.
PRESETS = tuple(sorted(list(_PRESET_PARAMS) + ["ponytail"]))


def _ponytail(mesh, strands: int, particles: int, seed: int, sdf=None, *, tail_length: float = 0.24,
              tie_radius: float = 0.008, spread: float = 0.035, margin: float = 0.002,
              region="scalp") -> Groom:
    """Ponytail: every strand runs over the scalp to a tie at the back of the head, then
    follows a guide curve (the tail) with a per-strand offset that fans out toward the tip.

    Scalp part: the path from the root to the tie is interpolated on great circles about the
    cranium's centre and shrink-wrapped onto the head (SDF push-out to ``margin``). Tail: a
    quadratic Bézier guide from the tie, backward then down, ``tail_length`` metres; strand
    offsets in the plane normal to the guide grow from ``tie_radius`` to ``spread``.
    The polyline of each strand is resampled to ``particles`` keeping its length.
    """
    mesh, verts, faces = _mesh_arrays(mesh)
    rng = np.random.default_rng(seed)
    root = sample_roots(mesh, region, strands=strands, rng=rng)
    s = root["positions"].shape[0]
    col = _Collider(sdf if sdf is not None else _sdf_for(mesh, 128))
    centre = np.array([0.0, 0.025, -0.012])
    # tie: the head's surface point furthest along (0, 0.45, −1) from the centre, plus its thickness
    vn = np.asarray(mesh.vertex_normals)
    aim = np.array([0.0, 0.45, -1.0]) / np.linalg.norm([0.0, 0.45, -1.0])
    vi = int(np.argmax((verts - centre) @ aim))
    tie = verts[vi] + vn[vi] * (tie_radius + margin)
    # scalp part: great-circle interpolation about the centre, then shrink-wrap
    m = 28
    t = np.linspace(0.0, 1.0, m)
    a = root["positions"] - centre
    b = tie - centre
    ra, rb = np.linalg.norm(a, axis=1), np.linalg.norm(b)
    ua, ub = a / ra[:, None], b / rb
    cos = np.clip(ua @ ub, -1.0, 1.0)
    ang = np.arccos(cos)
    sin = np.maximum(np.sin(ang), 1e-9)
    wa = np.sin((1 - t)[None] * ang[:, None]) / sin[:, None]
    wb = np.sin(t[None] * ang[:, None]) / sin[:, None]
    small = ang < 1e-6
    wa[small], wb[small] = (1 - t)[None], t[None]
    u = wa[..., None] * ua[:, None] + wb[..., None] * ub[None, None]
    u /= np.linalg.norm(u, axis=-1, keepdims=True)
    r = ra[:, None] * (1 - t)[None] + rb * t[None]
    # lift off the scalp along the way (hair volume), zero at the root
    r = r + 0.006 * np.sin(0.5 * np.pi * t)[None]
    scalp = centre + r[..., None] * u
    body = scalp[:, 1:].reshape(-1, 3)
    for _ in range(3):
        body, _ = col.push_out(body, margin)
    scalp[:, 1:] = body.reshape(s, m - 1, 3)
    # tail: guide curve and per-strand offsets
    k = 40
    v = np.linspace(0.0, 1.0, k)
    p0, p1, p2 = tie, tie + np.array([0.0, 0.02, -0.08]), tie + np.array([0.0, -tail_length * 0.85, -0.12])
    guide = ((1 - v) ** 2)[:, None] * p0 + (2 * (1 - v) * v)[:, None] * p1 + (v ** 2)[:, None] * p2
    glen = np.linalg.norm(np.diff(guide, axis=0), axis=1).sum()
    guide = p0 + (guide - p0) * (tail_length / glen)  # scale to the tail length
    tang = np.gradient(guide, axis=0)
    tang /= np.linalg.norm(tang, axis=1, keepdims=True)
    e1 = np.cross(tang, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(tang, e1)
    theta = rng.uniform(0.0, 2 * np.pi, s)
    rad = np.sqrt(rng.random(s))
    wave_phase = rng.uniform(0.0, 2 * np.pi, s)
    rho = (tie_radius + (spread - tie_radius) * v[None] ** 0.8) * rad[:, None]  # (S, k)
    ct, st = np.cos(theta)[:, None, None], np.sin(theta)[:, None, None]
    off = rho[..., None] * (ct * e1[None] + st * e2[None])
    wave = 0.004 * v[None] * np.sin(2 * np.pi * 3 * v[None] + wave_phase[:, None])
    tail = guide[None] + off + wave[..., None] * e1[None]
    poly = np.concatenate([scalp, tail], axis=1)
    pts = resample_strands(poly, particles, keep_length=True)
    body, _ = col.push_out(pts[:, 1:].reshape(-1, 3), 0.5 * margin)
    pts[:, 1:] = body.reshape(s, particles - 1, 3)
    corners = torch.as_tensor(verts[root["face_vertices"]])
    meta = dict(generator="ams_torch.preset", preset="ponytail", seed=int(seed), region=region, strands=int(s),
                particles=int(particles), guide=guide.tolist(), tie=tie.tolist(), tail_length=tail_length,
                tie_radius=tie_radius, spread=spread, margin=margin,
                mesh=str(getattr(mesh, "metadata", {}).get("name", "")))
    return Groom(torch.as_tensor(pts, dtype=torch.float32), torch.as_tensor(root["triangles"]),
                 torch.as_tensor(root["barycentrics"], dtype=torch.float32), torch.as_tensor(root["face_vertices"]),
                 triangle_frames(corners).float(), None, meta)


def preset(name: str, strands: int = 5000, particles: Optional[int] = None, seed: int = 0, *, mesh=None,
           sdf=None, **overrides) -> Groom:
    """A named groom on the default head (or on ``mesh``, which must carry the same regions).

    Names (see ``PRESETS``):

    * ``straight``: long (0.36 m) straight hair parted in the middle, hanging to the shoulders.
    * ``wavy``: long (0.32 m) wavy hair (p_h = 3000, p_freq = 0.5, p_γ = 2), in clumps (below).
    * ``curly``: 0.26 m curls (p_h = 600, p_freq = 0.6), voluminous, in clumps.
    * ``bob``: asymmetric bob, 0.21 m on the +x side, 0.09 m on the −x side, shorter fringe.
    * ``ponytail``: strands pulled over the scalp to a tie at the back and gathered along a
      guide curve (a 0.24 m tail that fans out).
    * ``fur``: short (1.5 cm) fur over the whole head.
    * ``beard``: 4 cm slightly curly beard on the ``beard`` region.

    Args:
        strands: S (100 … 100,000 are all fine; area-weighted roots).
        particles: N per strand; default per preset (straight/bob 32, wavy 48, curly 64,
            ponytail 48, fur 8, beard 12). Curls need ≳ 6 particles per turn.
        seed: random seed (same seed → same groom, bit for bit).
        mesh: head mesh in metres (+y up, face toward +z) with ``metadata["regions"]``;
            default ``ams_torch.grooms.head.default_head()``.
        sdf: collision ``SDFGrid`` of ``mesh`` to reuse.
        **overrides: growth parameters replacing the preset's (not for ``ponytail``, which
            takes ``tail_length``, ``tie_radius``, ``spread``, ``margin``).

    Clumps: ``wavy`` and ``curly`` grow in clumps (``clump_radius`` 15 mm, ``clump_jitter`` 0.05,
    ``phase_length`` 4 cm): strands of a clump share wave phase and shape, so neighbours run
    together as in real hair. Pass ``clump_radius=0`` for the paper's independent strands.

    Returns:
        :class:`Groom` with ``rest_positions`` (S, N, 3) float32 metres in the head frame;
        ``metadata["preset"]`` is the name.
    """
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}")
    if mesh is None:
        from ams_torch.grooms.head import default_head
        mesh = default_head()
    if name == "ponytail":
        n = 48 if particles is None else int(particles)
        return _ponytail(mesh, int(strands), n, seed, sdf=sdf, **overrides)
    spec = _PRESET_PARAMS[name]
    params = dict(spec["params"])
    region = overrides.pop("region", spec["region"])
    for key, value in overrides.items():
        params[ALIASES.get(key, key)] = value
    n = spec["particles"] if particles is None else int(particles)
    groom = grow(mesh, region=region, strands=int(strands), particles=n, seed=seed, sdf=sdf, **params)
    groom.metadata["generator"] = "ams_torch.preset"
    groom.metadata["preset"] = name
    return groom
