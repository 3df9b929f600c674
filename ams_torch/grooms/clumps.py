"""Clumps of a grown groom (SPEC §9 extended): strands grouped by root proximity share their random
draws (wave phase, helix radius, root-direction noise, length), so neighbouring strands of wavy
and curly hair stay together, and a measure of how far neighbours drift apart along their length.

- :func:`clump_labels`: clumps of roots (farthest-point centres within a radius).
- :func:`strand_draws`: the per-strand random draws of :func:`~ams_torch.grooms.growth.grow`,
  shared within clumps (``GrowthParams.clump_radius``, ``clump_jitter``, ``phase_length``).
- :func:`neighbour_distance`: mean distance along the length of strands whose roots are close.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["clump_labels", "strand_draws", "neighbour_distance"]


def clump_labels(roots, radius: float):
    """Clumps of roots by proximity.

    Clump centres are roots taken in farthest-point order (starting at the root nearest the
    centroid; ties to the lowest index) until every root lies within ``radius`` of a centre;
    each root joins its nearest centre (ties to the earlier centre). Deterministic.

    Args:
        roots: (S, 3) metres.
        radius: r > 0, metres: the largest root–centre distance of a clump.
    Returns:
        ``(labels (S,) int64 in [0, C), centres (C,) int64 root indices)``; ``labels[centres[c]] == c``.
    """
    r = np.asarray(roots, dtype=np.float64).reshape(-1, 3)
    if not radius > 0:
        raise ValueError(f"clump radius must be positive (m), got {radius!r}")
    if len(r) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    centres = [int(np.argmin(((r - r.mean(0)) ** 2).sum(1)))]
    dist = ((r - r[centres[0]]) ** 2).sum(1)
    labels = np.zeros(len(r), np.int64)
    r2 = float(radius) ** 2
    while True:
        far = int(np.argmax(dist))
        if dist[far] <= r2:
            break
        d = ((r - r[far]) ** 2).sum(1)
        closer = d < dist
        labels[closer] = len(centres)
        dist = np.where(closer, d, dist)
        centres.append(far)
    return labels, np.asarray(centres, np.int64)


def neighbour_distance(positions, root_distance: float = 0.008, tolerance: float = 0.001) -> tuple:
    """How far apart strands whose roots are close stay along their length.

    positions: (S, N, 3) metres (particle 0 the root). For every pair of strands whose roots are
    ``root_distance`` ± ``tolerance`` metres apart, the distance between their particles of the
    same index, averaged over the N particles; returns ``(mean over the pairs (m), pair count)``
    (``(nan, 0)`` when no pair qualifies). Straight combed hair keeps neighbours close (≈ the
    root distance plus the spread of root directions and lengths); strands whose waves are out
    of phase are a wave amplitude apart.
    """
    x = np.asarray(positions.detach().cpu() if hasattr(positions, "detach") else positions, dtype=np.float64)
    roots = x[:, 0]
    total, count = 0.0, 0
    for i in range(len(x) - 1):  # row by row: O(S) memory for any S
        d = np.linalg.norm(roots[i + 1:] - roots[i], axis=1)
        j = i + 1 + np.flatnonzero(np.abs(d - root_distance) <= tolerance)
        if j.size:
            total += float(np.linalg.norm(x[j] - x[i], axis=-1).mean(1).sum())
            count += int(j.size)
    return (total / count if count else float("nan")), count


def _smooth_phase(theta: np.ndarray, centres: np.ndarray, length: float) -> np.ndarray:
    """arg Σ_d exp(−|c − c_d|²/(2 length²)) e^{iθ_d} at every centre c: (C,) angles in (−π, π]."""
    z = np.exp(1j * theta)
    out = np.empty(len(theta))
    for a in range(0, len(theta), 1024):  # rows in blocks: O(1024 C) memory
        d2 = ((centres[a:a + 1024, None] - centres[None]) ** 2).sum(-1)
        out[a:a + 1024] = np.angle(np.exp(-d2 / (2.0 * length * length)) @ z)
    return out


def strand_draws(rng: np.random.Generator, roots: np.ndarray, params) -> tuple:
    """The per-strand random draws of :func:`~ams_torch.grooms.growth.grow` (``params``: its
    :class:`~ams_torch.grooms.growth.GrowthParams`), in their fixed order: ``noise`` (S, 3) (scaled
    by ``params.noise``), ``phase`` (S,) radians, ``radius_u`` (S,) in [−1, 1], ``length_u`` (S,)
    in [0, 1). With ``clump_radius`` > 0 the clumps' draws follow (same kinds, (C, ...)) and each
    strand's draw becomes (1 − w) × its clump's + w × its own (w = ``clump_jitter``).
    Returns ``(draws, clumps)`` with ``clumps`` the (S,) clump labels, or None."""
    s = len(roots)
    draws = {"noise": rng.uniform(-1.0, 1.0, (s, 3)) * params.noise,
             "phase": rng.uniform(-1.0, 1.0, s) * params.phase_jitter,
             "radius_u": rng.uniform(-1.0, 1.0, s), "length_u": rng.random(s)}
    if not params.clump_radius > 0:
        return draws, None
    labels, centres = clump_labels(roots, params.clump_radius)
    c = len(centres)
    shared = {"noise": rng.uniform(-1.0, 1.0, (c, 3)) * params.noise,
              "phase": rng.uniform(-1.0, 1.0, c) * params.phase_jitter,
              "radius_u": rng.uniform(-1.0, 1.0, c), "length_u": rng.random(c)}
    if params.phase_length > 0 and params.phase_jitter > 0:
        shared["phase"] = _smooth_phase(shared["phase"] * (math.pi / params.phase_jitter), roots[centres],
                                        params.phase_length) * (params.phase_jitter / math.pi)
    w = float(params.clump_jitter)
    return {k: (1.0 - w) * shared[k][labels] + w * v for k, v in draws.items()}, labels
