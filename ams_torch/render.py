"""Headless pictures of a groom with matplotlib (Agg): no display, no system libraries."""
from __future__ import annotations

from typing import Optional

import numpy as np

__all__ = ["render_groom"]


def render_groom(x, path: str, head_vertices: Optional[np.ndarray] = None, head_faces: Optional[np.ndarray] = None,
                 head_radius: Optional[float] = None, title: str = "", views=("front", "side"),
                 size: float = 5.0, max_strands: int = 20000) -> str:
    """Draw strands (S, N, 3) metres as depth-sorted polylines, coloured by root position.

    One panel per view: "front" looks along −z (x right, y up), "side" along +x (z right).
    The head is drawn as a shaded mesh (vertices (V, 3), faces (F, 3)) or a disc of
    ``head_radius``. Writes a PNG to ``path`` and returns the path.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection, PolyCollection

    x = np.asarray(x.detach().cpu() if hasattr(x, "detach") else x, dtype=np.float64)
    if x.ndim != 3 or x.shape[-1] != 3:
        raise ValueError(f"render_groom: positions must be (S, N, 3); got {x.shape}")
    if x.shape[0] > max_strands:
        x = x[np.linspace(0, x.shape[0] - 1, max_strands).astype(int)]
    roots = x[:, 0]
    span = np.ptp(roots, axis=0) + 1e-9
    colour = np.clip((roots - roots.min(0)) / span, 0, 1)
    colour = 0.25 + 0.6 * colour[:, [0, 1, 2]]
    axes_of = {"front": (0, 1, 2), "side": (2, 1, 0)}  # (horizontal, vertical, depth toward viewer)
    fig, axes = plt.subplots(1, len(views), figsize=(size * len(views), size), squeeze=False)
    lo, hi = x.reshape(-1, 3).min(0), x.reshape(-1, 3).max(0)
    for ax, view in zip(axes[0], views):
        a, b, c = axes_of[view]
        sign = 1.0 if view == "front" else -1.0
        if head_vertices is not None and head_faces is not None:
            tri = head_vertices[head_faces]
            n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            n /= np.linalg.norm(n, axis=1, keepdims=True) + 1e-12
            facing = sign * n[:, c] > 0
            depth = sign * tri[:, :, c].mean(1)
            order = np.argsort(depth)
            order = order[facing[order]]
            light = np.clip(0.3 + 0.7 * (sign * n[order, c] * 0.8 + n[order, 1] * 0.2), 0, 1)
            ax.add_collection(PolyCollection(tri[order][:, :, [a, b]], facecolors=np.c_[light, light * 0.9, light * 0.85],
                                             edgecolors="none", zorder=1))
        elif head_radius:
            ax.add_patch(plt.Circle((0, 0), head_radius, color=(0.85, 0.75, 0.7), zorder=1))
        segs = x[:, :, [a, b]]
        depth = sign * x[:, :, c].mean(1)
        order = np.argsort(depth)
        ax.add_collection(LineCollection(segs[order], colors=colour[order], linewidths=0.5, alpha=0.8, zorder=2))
        pad = 0.05 * max(hi[a] - lo[a], hi[b] - lo[b])
        ax.set_xlim(min(lo[a], -0.12) - pad, max(hi[a], 0.12) + pad)
        ax.set_ylim(min(lo[b], -0.12) - pad, max(hi[b], 0.12) + pad)
        ax.set_aspect("equal")
        ax.set_title(f"{title} ({view})" if title else view)
        ax.set_xlabel("xyz"[a] + " (m)")
        ax.set_ylabel("y (m)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
