"""Headless pictures of a groom with matplotlib (Agg): no display, no system libraries."""
from __future__ import annotations

from typing import Optional

import numpy as np

from ams_torch.apps.video import check_picture_path, write_png, write_video

__all__ = ["render_groom", "SequenceRenderer", "render_sequence", "render_strip", "write_video", "collider_shapes"]


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
    import io

    from ams_torch.apps.atomic import write_bytes

    buf = io.BytesIO()
    fig.savefig(buf, dpi=110, format="png")
    plt.close(fig)
    write_bytes(path, buf.getvalue())
    return path


#: largest picture side, pixels (a [render] size of 81.92 inches at 100 dpi)
MAX_PIXELS = 8192
_AXES = {"front": (0, 1, 2, 1.0), "side": (2, 1, 0, -1.0), "back": (0, 1, 2, -1.0)}  # (h, v, depth, sign)


def _as_np(a) -> np.ndarray:
    return np.asarray(a.detach().cpu() if hasattr(a, "detach") else a, dtype=np.float64)


class SequenceRenderer:
    """Draws frames of a simulation into RGB arrays with one reused matplotlib (Agg) figure.

    Args:
        head_vertices, head_faces: (V, 3) m and (F, 3) int, the head mesh in the head frame
            (moved by each frame's pose), or None.
        head_radius: draw a sphere of this radius (m) when there is no mesh.
        view: "front" (look along −z), "side" (along +x) or "back" (along +z, mirrored).
        extent: ((xmin, xmax), (ymin, ymax)) metres of the picture; default from the first frame.
        size: inches (square); dpi: pixels per inch (size·dpi pixels, rounded to even).
        max_strands: draw at most this many strands (evenly picked).
    """

    def __init__(self, head_vertices=None, head_faces=None, head_radius: Optional[float] = None,
                 view: str = "front", extent=None, size: float = 4.0, dpi: int = 100, max_strands: int = 4000,
                 title: str = ""):
        import matplotlib

        matplotlib.use("Agg")
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        if view not in _AXES:
            raise ValueError(f"view must be one of {sorted(_AXES)}; got {view!r}")
        self.view, self.extent, self.max_strands, self.title = view, extent, max_strands, title
        self.head_vertices = None if head_vertices is None else _as_np(head_vertices)
        self.head_faces = None if head_faces is None else np.asarray(head_faces, dtype=np.int64)
        self.head_radius = head_radius
        if not (isinstance(size, (int, float)) and np.isfinite(size) and size > 0 and 16 <= size * dpi <= MAX_PIXELS):
            raise ValueError(f"the picture size must be {16 / dpi:g} to {MAX_PIXELS / dpi:g} inches at {dpi} dpi "
                             f"(16 to {MAX_PIXELS} pixels a side); got size = {size!r}")
        px = int(round(size * dpi / 2)) * 2  # even: H.264 needs even sizes
        self.fig = Figure(figsize=(px / dpi, px / dpi), dpi=dpi)
        self.canvas = FigureCanvasAgg(self.fig)
        self.ax = self.fig.add_axes((0.0, 0.0, 1.0, 1.0))
        self.pick = None

    def draw(self, x, rotation=None, translation=None, label: str = "", shapes=()) -> np.ndarray:
        """One frame: strands x (S, N, 3) m (world), head pose (3, 3)/(3,) (default identity).
        ``shapes``: colliders to outline, dicts ``{"type": "sphere"|"hollow_sphere"|"capsule",
        "center"/"a"/"b": world points (3,) m, "radius": m, "thickness": m}``.
        Returns (H, W, 3) uint8. Strands and head faces are drawn back to front."""
        from matplotlib.collections import LineCollection, PolyCollection

        x = _as_np(x)
        if x.ndim != 3 or x.shape[-1] != 3:
            raise ValueError(f"positions must be (S, N, 3); got {x.shape}")
        if self.pick is None:
            self.pick = np.linspace(0, x.shape[0] - 1, min(x.shape[0], self.max_strands)).astype(int)
            roots = x[self.pick, 0]
            span = np.ptp(roots, axis=0) + 1e-9
            self.colour = 0.25 + 0.6 * np.clip((roots - roots.min(0)) / span, 0, 1)
            self.colour = np.c_[self.colour * np.array([0.9, 0.7, 0.45]), np.full(len(self.pick), 0.85)]
            if self.extent is None:
                lo, hi = x.reshape(-1, 3).min(0), x.reshape(-1, 3).max(0)
                for sh in shapes:  # keep the drawn colliders in view
                    if "center" in sh:
                        reach = sh.get("radius", 0.0) + 0.5 * sh.get("thickness", 0.0)
                        lo = np.minimum(lo, np.asarray(sh["center"]) - reach)
                        hi = np.maximum(hi, np.asarray(sh["center"]) + reach)
                a, b = _AXES[self.view][:2]
                c = 0.5 * (lo + hi)
                half = 0.55 * max(hi[a] - lo[a], hi[b] - lo[b], 0.3)
                self.extent = ((c[a] - half, c[a] + half), (c[b] - half, c[b] + half))
        x = x[self.pick]
        a, b, c, sign = _AXES[self.view]
        ax = self.ax
        ax.cla()
        ax.set_axis_off()
        ax.set_facecolor((1, 1, 1))
        rot = np.eye(3) if rotation is None else _as_np(rotation)
        trans = np.zeros(3) if translation is None else _as_np(translation)
        if self.head_vertices is not None and self.head_faces is not None:
            v = self.head_vertices @ rot.T + trans
            tri = v[self.head_faces]
            n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            n /= np.linalg.norm(n, axis=1, keepdims=True) + 1e-12
            facing = sign * n[:, c] > 0
            order = np.argsort(sign * tri[:, :, c].mean(1))
            order = order[facing[order]]
            light = np.clip(0.3 + 0.7 * (sign * n[order, c] * 0.8 + n[order, 1] * 0.2), 0, 1)
            ax.add_collection(PolyCollection(tri[order][:, :, [a, b]], facecolors=np.c_[light, light * 0.88, light * 0.8],
                                             edgecolors="none", zorder=1))
        elif self.head_radius:
            import matplotlib.patches as mpatches

            ax.add_patch(mpatches.Circle((trans[a], trans[b]), self.head_radius, color=(0.85, 0.75, 0.7), zorder=1))
        # hair behind the head centre first, then the head, then hair in front
        depth = sign * (x[:, :, c].mean(1) - trans[c])
        order = np.argsort(depth)
        behind = order[depth[order] < 0]
        front = order[depth[order] >= 0]
        for idx, z in ((behind, 0), (front, 2)):
            if len(idx):
                ax.add_collection(LineCollection(x[idx][:, :, [a, b]], colors=self.colour[idx], linewidths=0.6, zorder=z))
        lo_h, hi_h = self.extent[0]
        ax.set_xlim(*((hi_h, lo_h) if self.view == "back" else (lo_h, hi_h)))  # from behind: +x to the left
        ax.set_ylim(*self.extent[1])
        ax.set_aspect("equal")
        self._draw_shapes(shapes, a, b)
        text = " ".join(t for t in (self.title, label) if t)
        if text:
            ax.text(0.02, 0.97, text, transform=ax.transAxes, va="top", fontsize=8)
        self.canvas.draw()
        return np.asarray(self.canvas.buffer_rgba())[..., :3].copy()

    def _draw_shapes(self, shapes, a: int, b: int) -> None:
        import matplotlib.patches as mpatches

        style = dict(fill=False, edgecolor=(0.2, 0.35, 0.8), linewidth=1.2, zorder=3)
        for sh in shapes:
            kind = sh["type"]
            if kind == "sphere":
                c = np.asarray(sh["center"], dtype=np.float64)
                self.ax.add_patch(mpatches.Circle((c[a], c[b]), sh["radius"], **style))
            elif kind == "hollow_sphere":
                self._draw_shell(sh, a, b, style)
            elif kind == "capsule":
                p, q = np.asarray(sh["a"], dtype=np.float64)[[a, b]], np.asarray(sh["b"], dtype=np.float64)[[a, b]]
                d = q - p
                n = np.array([-d[1], d[0]]) / (np.linalg.norm(d) + 1e-12) * sh["radius"]
                self.ax.add_patch(mpatches.Polygon([p + n, q + n, q - n, p - n], closed=True, **style))
                for e in (p, q):
                    self.ax.add_patch(mpatches.Circle(tuple(e), sh["radius"], **style))


    def _draw_shell(self, sh: dict, a: int, b: int, style: dict) -> None:
        """A hollow sphere's wall (radius ± thickness/2) as two arcs that leave its opening (the cap
        beyond ``cut_height`` along ``axis``) open where the opening faces the view sideways."""
        import matplotlib.patches as mpatches

        c = np.asarray(sh["center"], dtype=np.float64)
        radius, half = sh["radius"], 0.5 * sh["thickness"]
        axis, cut = sh.get("axis"), sh.get("cut_height")
        start, end = 0.0, 360.0
        if axis is not None and cut is not None:
            ax2 = np.asarray(axis, dtype=np.float64)[[a, b]]
            if np.linalg.norm(ax2) > 0.3:  # the opening is seen from the side: leave it open
                facing = np.degrees(np.arctan2(ax2[1], ax2[0]))
                opening = np.degrees(np.arccos(np.clip(cut / radius, -1.0, 1.0)))
                start, end = facing + opening, facing - opening + 360.0
        for r in (radius - half, radius + half):
            self.ax.add_patch(mpatches.Arc((c[a], c[b]), 2 * r, 2 * r, theta1=start, theta2=end,
                                           **{k: v for k, v in style.items() if k != "fill"}))


def collider_shapes(specs, rotations, translations) -> list:
    """World outlines for :meth:`SequenceRenderer.draw` from scene collider specs (dicts with
    ``type`` and local ``center``/``a``/``b``/``radius``/``thickness``) and their world poses
    rotations (C, 3, 3), translations (C, 3) m. Planes are not drawn."""
    out = []
    for spec, r, t in zip(specs, rotations, translations):
        r, t = np.asarray(r, dtype=np.float64), np.asarray(t, dtype=np.float64)
        kind = spec["type"]
        if kind in ("sphere", "hollow_sphere"):
            c = r @ np.asarray(spec.get("center", (0.0, 0.0, 0.0)), dtype=np.float64) + t
            shape = {"type": kind, "center": c, "radius": float(spec.get("radius", 0.1 if kind == "sphere" else 0.2)),
                     "thickness": float(spec.get("thickness", 0.02))}
            if kind == "hollow_sphere":
                axis = np.asarray(spec.get("axis", (0.0, 1.0, 0.0)), dtype=np.float64)
                shape["axis"] = r @ (axis / np.linalg.norm(axis))
                shape["cut_height"] = spec.get("cut_height", 0.1)
            out.append(shape)
        elif kind == "capsule":
            out.append({"type": "capsule", "a": r @ np.asarray(spec.get("a", (0.0, 0.0, 0.0))) + t,
                        "b": r @ np.asarray(spec.get("b", (0.0, 0.1, 0.0))) + t, "radius": float(spec.get("radius", 0.05))})
    return out


def render_sequence(positions, path: str, rotations=None, translations=None, fps: float = 30.0,
                    every: int = 1, progress: bool = False, colliders=(), collider_rotations=None,
                    collider_translations=None, **renderer_args) -> str:
    """Render a sequence to MP4 (or to a PNG of the last frame if ``path`` ends in .png).

    positions: (F, S, N, 3) m world; rotations (F, 3, 3), translations (F, 3) m the head poses
    (default identity); ``every``: draw every k-th frame; ``colliders``: scene collider specs
    outlined with their world poses ``collider_rotations`` (F, C, 3, 3) and
    ``collider_translations`` (F, C, 3) m; ``renderer_args`` go to :class:`SequenceRenderer`
    (head mesh, view, size...). Returns the path.
    """
    check_picture_path(path, "render path")
    if isinstance(every, bool) or not isinstance(every, (int, np.integer)) or every < 1:
        raise ValueError(f"every must be an integer >= 1 (draw every k-th frame); got {every!r}")
    if not isinstance(positions, np.ndarray) and not hasattr(positions, "shape"):
        positions = _as_np(positions)  # a list: an array; an array or an h5py dataset is read frame by frame
    if len(positions.shape) != 4 or positions.shape[-1] != 3 or positions.shape[0] < 1:
        raise ValueError(f"positions must be (F, S, N, 3) with F >= 1; got {tuple(positions.shape)}")
    frames = range(0, positions.shape[0], int(every))
    r = SequenceRenderer(**renderer_args)
    if renderer_args.get("extent") is None:  # frame the whole sequence
        a, b = _AXES[r.view][:2]
        lo, hi = _bounds(positions)
        c = 0.5 * (lo + hi)
        half = 0.55 * max(hi[a] - lo[a], hi[b] - lo[b], 0.3)
        r.extent = ((c[a] - half, c[a] + half), (c[b] - half, c[b] + half))
    pose = lambda k: (None if rotations is None else rotations[k],  # noqa: E731
                      None if translations is None else translations[k])
    shapes = lambda k: collider_shapes(colliders, collider_rotations[k], collider_translations[k]) \
        if len(colliders) and collider_rotations is not None else ()  # noqa: E731
    if str(path).lower().endswith(".png"):
        last = positions.shape[0] - 1
        return write_png(path, r.draw(positions[-1], *pose(last), shapes=shapes(last)))
    it = frames
    if progress:
        from tqdm.auto import tqdm

        it = tqdm(frames, desc="rendering", unit="frame")
    return write_video((r.draw(positions[k], *pose(k), label=f"frame {k + 1}", shapes=shapes(k)) for k in it), path,
                       fps=fps / int(every))


def _bounds(positions) -> tuple:
    """(lo, hi) (3,) of every point of positions (F, S, N, 3), read one frame at a time when it is
    not in memory (an h5py dataset), so a long sequence is never loaded whole."""
    if isinstance(positions, np.ndarray):
        flat = positions.reshape(-1, 3)
        return flat.min(0).astype(np.float64), flat.max(0).astype(np.float64)
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for k in range(positions.shape[0]):
        x = _as_np(positions[k]).reshape(-1, 3)
        lo, hi = np.minimum(lo, x.min(0)), np.maximum(hi, x.max(0))
    return lo, hi


def render_strip(positions, path: str, picks, rotations=None, translations=None, labels=None, colliders=(),
                 collider_rotations=None, collider_translations=None, **renderer_args) -> str:
    """A PNG strip: the frames ``picks`` (indices into positions (F, S, N, 3)) side by side
    (arguments as :func:`render_sequence`)."""
    positions = _as_np(positions)
    r = SequenceRenderer(**renderer_args)
    a, b = _AXES[r.view][:2]
    sel = positions[list(picks)]
    lo, hi = sel.reshape(-1, 3).min(0), sel.reshape(-1, 3).max(0)
    shapes = {k: collider_shapes(colliders, collider_rotations[k], collider_translations[k])
              if len(colliders) and collider_rotations is not None else () for k in picks}
    for sh in (s for k in picks for s in shapes[k] if "center" in s):  # keep the colliders in view
        reach = sh.get("radius", 0.0) + 0.5 * sh.get("thickness", 0.0)
        lo, hi = np.minimum(lo, sh["center"] - reach), np.maximum(hi, sh["center"] + reach)
    c = 0.5 * (lo + hi)
    half = 0.55 * max(hi[a] - lo[a], hi[b] - lo[b], 0.3)
    r.extent = ((c[a] - half, c[a] + half), (c[b] - half, c[b] + half))
    imgs = []
    for j, k in enumerate(picks):
        rot = None if rotations is None else rotations[k]
        tr = None if translations is None else translations[k]
        imgs.append(r.draw(positions[k], rot, tr, label=labels[j] if labels else f"frame {k + 1}", shapes=shapes[k]))
    return write_png(path, np.concatenate(imgs, axis=1))
