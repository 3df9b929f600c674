"""Render the procedural-growth gallery into docs/gallery/.

* ``growth_sweeps.png``: the parameter sweeps of the supplement's Figures 3–4 on one contact
  sheet — helix radius p_h × step p_τ (curliness and length) and droop p_γ × step p_τ (deviation
  in y) — each cell a tuft of strands grown from a small patch of the default head's crown.
* ``preset_<name>.png``: every named preset of :func:`ams_torch.preset` on the default head,
  seen from the front and from the side.

Rendering is plain matplotlib (Agg): an orthographic projection, head triangles and hair
segments depth-sorted together (painter's algorithm) in one collection.

    .venv/bin/python scripts/grow_gallery.py [--out docs/gallery] [--strands 3000]
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.collections import PolyCollection  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import ams_torch.grooms.growth as growth  # noqa: E402
import ams_torch.grooms.presets as presets  # noqa: E402
from ams_torch.grooms.head import default_head  # noqa: E402
from ams_torch.geometry.sdf import SDFGrid  # noqa: E402

VIEWS = {
    # name: (right, up, toward viewer) axes of the head frame (+y up, face toward +z)
    "front": (np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), np.array([0, 0, 1.0])),
    "side": (np.array([0, 0, -1.0]), np.array([0, 1.0, 0]), np.array([1.0, 0, 0])),
    "back": (np.array([-1.0, 0, 0]), np.array([0, 1.0, 0]), np.array([0, 0, -1.0])),
}
LIGHT = np.array([0.4, 0.7, 0.6]) / np.linalg.norm([0.4, 0.7, 0.6])


def occluded(points, sdf, toward, reach=0.35, step=0.003):
    """Whether each point (M, 3) is hidden by the head: the ray toward the viewer enters the SDF."""
    pts = torch.as_tensor(points, dtype=torch.float32)
    hidden = torch.zeros(len(pts), dtype=torch.bool)
    d = torch.as_tensor(toward, dtype=torch.float32)
    for t in np.arange(step, reach, step):
        hidden |= sdf.distance(pts + float(t) * d) < 0
    return hidden.numpy()


def draw(ax, strands=None, mesh=None, view="front", hair_color=(0.35, 0.22, 0.12), linewidth=0.35,
         mesh_faces=None, sdf=None):
    """Draw strands (S, N, 3) and an optional mesh on ``ax``, orthographic ``view``, metres.

    With ``sdf`` (the mesh's SDFGrid), hair segments hidden behind the head are left out
    (painter's sorting alone lets them show through the seams between triangles).
    """
    right, up, toward = VIEWS[view]
    polys, depth, face, edge, lw = [], [], [], [], []
    if mesh is not None:
        f = np.asarray(mesh.faces if mesh_faces is None else mesh.faces[mesh_faces])
        tri = np.asarray(mesh.vertices)[f]
        nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-30)
        keep = nrm @ toward > 0  # back-face culling
        tri, nrm = tri[keep], nrm[keep]
        shade = 0.35 + 0.6 * np.clip(nrm @ LIGHT, 0, 1)
        col = np.stack([0.93 * shade, 0.80 * shade, 0.70 * shade, np.ones_like(shade)], 1)
        polys += list(np.stack([tri @ right, tri @ up], -1))
        depth += list(tri.mean(1) @ toward)
        face += list(col)
        edge += list(col)
        lw += [0.2] * len(tri)
    if strands is not None:
        x = np.asarray(strands, dtype=np.float64)
        seg = np.stack([x[:, :-1], x[:, 1:]], 2).reshape(-1, 2, 3)
        if sdf is not None:
            seg = seg[~occluded(seg.mean(1), sdf, toward)]
        t = (seg[:, 1] - seg[:, 0])
        t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-30)
        # Kajiya-style tangent shading: brighter where the strand is across the light
        shade = 0.55 + 0.45 * np.sqrt(np.clip(1 - (t @ LIGHT) ** 2, 0, 1))
        hc = np.asarray(hair_color)
        col = np.concatenate([np.clip(hc[None] * shade[:, None] * 1.6, 0, 1), np.ones((len(seg), 1))], 1)
        polys += list(np.stack([seg @ right, seg @ up], -1))
        depth += list(seg.mean(1) @ toward)
        face += [(0, 0, 0, 0)] * len(seg)
        edge += list(col)
        lw += [linewidth] * len(seg)
    order = np.argsort(np.asarray(depth), kind="stable")
    pc = PolyCollection([polys[i] for i in order], facecolors=[face[i] for i in order],
                        edgecolors=[edge[i] for i in order], linewidths=[lw[i] for i in order],
                        closed=False)
    ax.add_collection(pc)
    ax.set_aspect("equal")
    ax.autoscale_view()
    ax.set_xticks([])
    ax.set_yticks([])
    for s in ax.spines.values():
        s.set_visible(False)


def crown_patch(mesh, radius=0.02):
    """Faces of the default head's crown within ``radius`` metres of its top, for the sweeps."""
    c = mesh.triangles_center
    top = c[np.argmax(c[:, 1])]
    return np.flatnonzero(np.linalg.norm(c - top, axis=1) < radius)


def sweep_sheet(mesh, out: Path, strands: int = 60, particles: int = 48):
    """Figures 3–4 of the supplement: p_h × p_τ and p_γ × p_τ, as one PNG."""
    patch = crown_patch(mesh)
    radii = [0.0, 300.0, 1000.0, 3000.0]
    droops = [0.0, 0.003, 0.03, 0.3]
    steps = [0.002, 0.004, 0.006]
    fig, axes = plt.subplots(len(steps), len(radii) + len(droops), figsize=(16, 6.4))
    for r, tau in enumerate(steps):
        for c, ph in enumerate(radii):
            g = growth.grow(mesh, region=patch, strands=strands, particles=particles, seed=1, p_tau=tau, p_h=ph,
                            p_gamma=0.3, noise=0.2, phase_jitter=np.pi, collide=False)
            ax = axes[r, c]
            draw(ax, g.rest_positions.numpy(), view="front", linewidth=0.5)
            ax.set_title(f"p_h={ph:g}, p_τ={tau * 1e3:g} mm", fontsize=8)
        for c, pg in enumerate(droops):
            g = growth.grow(mesh, region=patch, strands=strands, particles=particles, seed=1, p_tau=tau, p_h=0.0,
                            p_gamma=pg, noise=0.6, collide=False)
            ax = axes[r, len(radii) + c]
            draw(ax, g.rest_positions.numpy(), view="side", linewidth=0.5, hair_color=(0.15, 0.15, 0.3))
            ax.set_title(f"p_γ={pg:g}, p_τ={tau * 1e3:g} mm", fontsize=8)
    # same scale everywhere within each figure half
    for half in (axes[:, : len(radii)], axes[:, len(radii):]):
        xl = [min(a.get_xlim()[0] for a in half.flat), max(a.get_xlim()[1] for a in half.flat)]
        yl = [min(a.get_ylim()[0] for a in half.flat), max(a.get_ylim()[1] for a in half.flat)]
        for a in half.flat:
            a.set_xlim(xl)
            a.set_ylim(yl)
    fig.suptitle("Procedural growth sweeps (supplement Figs. 3–4): left, helix radius p_h × step p_τ (front view); "
                 "right, droop p_γ × step p_τ (side view).\np_Γ=0.2, p_freq=1, p_Ω=0.017, N=%d; left p_γ=0.3, "
                 "right p_h=0; roots on a 2 cm crown patch, no collisions" % particles,
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(out, dpi=80)
    plt.close(fig)


def preset_sheet(mesh, name: str, out: Path, strands: int, particles=None, sdf=None):
    t0 = time.perf_counter()
    g = presets.preset(name, strands=strands, particles=particles, seed=0, mesh=mesh, sdf=sdf)
    t1 = time.perf_counter()
    fig, axes = plt.subplots(1, 3, figsize=(10.5, 4.2))
    for ax, view in zip(axes, ("front", "side", "back")):
        draw(ax, g.rest_positions.numpy(), mesh, view=view, linewidth=0.3, sdf=sdf)
    fig.suptitle(f"preset '{name}': {g.num_strands} strands × {g.num_particles} particles "
                 f"(grown in {t1 - t0:.1f} s)", fontsize=10)
    fig.tight_layout()
    fig.savefig(out, dpi=72)
    plt.close(fig)
    return g


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="docs/gallery")
    ap.add_argument("--strands", type=int, default=3000, help="strands per preset picture")
    ap.add_argument("--only", nargs="*", help="presets to render (default: all) ")
    ap.add_argument("--no-sweeps", action="store_true")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    mesh = default_head()
    sdf = SDFGrid.from_mesh(mesh, resolution=128)
    if not args.no_sweeps:
        sweep_sheet(mesh, out / "growth_sweeps.png")
        print("wrote", out / "growth_sweeps.png", os.path.getsize(out / "growth_sweeps.png") // 1024, "KB")
    for name in args.only or sorted(presets.PRESETS):
        path = out / f"preset_{name}.png"
        preset_sheet(mesh, name, path, args.strands, sdf=sdf)
        print("wrote", path, os.path.getsize(path) // 1024, "KB")


if __name__ == "__main__":
    main()
