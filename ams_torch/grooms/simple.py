"""Simple deterministic grooms without a head mesh: strands on a sphere, a curly strand, a wisp.

Metres, head frame with +y up. Used by scene files (``[groom] kind = ...``), tests and benchmarks.
"""
from __future__ import annotations

import math

import numpy as np
import torch

__all__ = ["sphere_groom", "curly_strand", "wisp"]


def _fibonacci_upper_hemisphere(count: int, min_height: float) -> np.ndarray:
    """Quasi-uniform unit vectors with y ≥ min_height. Returns (count, 3)."""
    pts = []
    golden = math.pi * (3 - math.sqrt(5))
    total = int(count / (1 - min_height) * 2) + 8
    for i in range(total):
        y = 1 - (i + 0.5) / total * 2
        if y < min_height:
            break
        r = math.sqrt(max(0.0, 1 - y * y))
        t = golden * i
        pts.append((r * math.cos(t), y, r * math.sin(t)))
    pts = np.asarray(pts)
    idx = np.linspace(0, len(pts) - 1, count).round().astype(int)
    return pts[idx]


def sphere_groom(strands: int = 1000, particles: int = 32, radius: float = 0.1, length: float = 0.25,
                 seed: int = 0, dtype=torch.float32) -> torch.Tensor:
    """Strands rooted on the upper half of a sphere of ``radius`` m centred at the origin.

    Each strand leaves the scalp along the normal and bends smoothly downward, staying
    outside the sphere, over ``length`` m. Deterministic for a seed.
    Returns rest positions (strands, particles, 3) metres.
    """
    rng = np.random.default_rng(seed)
    n = _fibonacci_upper_hemisphere(strands, 0.05)
    n = n + rng.normal(scale=0.01, size=n.shape)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    horiz = n * np.array([1.0, 0.0, 1.0])
    hn = np.linalg.norm(horiz, axis=1, keepdims=True)
    horiz = np.where(hn > 1e-3, horiz / np.maximum(hn, 1e-9), np.array([0.0, 0.0, -1.0]))
    down = np.array([0.0, -1.0, 0.0])
    step = length / (particles - 1)
    x = np.zeros((strands, particles, 3))
    x[:, 0] = radius * n
    lengths = length * (1 + 0.1 * rng.uniform(-1, 1, size=(strands, 1)))
    step = lengths / (particles - 1)
    for i in range(1, particles):
        s = (i - 1) / (particles - 2)
        w = min(1.0, s * 3.0)
        w = w * w * (3 - 2 * w)  # smoothstep: normal → outward-and-down
        d = (1 - w) * n + w * (0.35 * horiz + down)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        x[:, i] = x[:, i - 1] + step * d
        # keep a small clearance from the sphere
        r = np.linalg.norm(x[:, i], axis=1, keepdims=True)
        x[:, i] = np.where(r < radius * 1.02, x[:, i] / r * radius * 1.02, x[:, i])
    return torch.as_tensor(x, dtype=dtype)


def curly_strand(particles: int = 30, radius: float = 0.02, pitch: float = 0.02, turns: float = 4.0,
                 dtype=torch.float64) -> torch.Tensor:
    """One helical strand hanging down from the origin along −y. Returns (1, particles, 3) m.

    ``radius`` and ``pitch`` (rise per turn) in metres, ``turns`` full turns.
    """
    t = torch.linspace(0, 2 * math.pi * turns, particles, dtype=torch.float64)
    x = radius * (torch.cos(t) - 1)
    z = radius * torch.sin(t)
    y = -pitch * t / (2 * math.pi)
    return torch.stack((x, y, z), -1)[None].to(dtype)


def wisp(strands: int = 16, particles: int = 30, length: float = 0.3, spread: float = 0.01,
         seed: int = 0, dtype=torch.float64) -> torch.Tensor:
    """A wisp: parallel strands leaving a small patch horizontally along +x, then curving down.

    Returns (strands, particles, 3) metres.
    """
    g = torch.Generator().manual_seed(seed)
    roots = torch.zeros(strands, 3, dtype=torch.float64)
    roots[:, 1:] = (torch.rand(strands, 2, generator=g, dtype=torch.float64) - 0.5) * 2 * spread
    s = torch.linspace(0, 1, particles, dtype=torch.float64)
    angle = 0.5 * math.pi * s ** 2  # tangent turns from +x to −y along the strand
    ds = length / (particles - 1)
    tang = torch.stack((torch.cos(angle), -torch.sin(angle), torch.zeros_like(angle)), -1)
    path = torch.cumsum(torch.cat((torch.zeros(1, 3, dtype=torch.float64), tang[:-1] * ds)), 0)
    return (roots[:, None, :] + path[None]).to(dtype)
