"""Fidelity metrics of interpolated hair against the dense simulation (SPEC §11).

Positions are metres, shaped (T, S, N, 3) (a sequence) or (S, N, 3) (one frame); reported
lengths are millimetres, velocities mm/s, accelerations mm/s². Every function returns Python
floats (or a dict of them). ``pinned`` skips the first particles of every strand (they follow the
head in every method and in the reference, so they would only dilute the errors); give a
per-strand count (S,) or one number.

Per sequence, :func:`sequence_metrics` computes all of them; :func:`aggregate` combines
sequences (frame-weighted means, the worst sequence, the maximum of maxima).
"""
from __future__ import annotations

import math
import time
from typing import Callable, Dict, Iterable, List, Optional, Sequence, Union

import torch

from ams_torch.geometry.pose import Pose
from ams_torch.stages.collide import collider_distances

__all__ = ["vertex_errors", "tip_error", "chamfer", "curvature", "curvature_error", "segment_length_error",
           "strand_length_error", "velocity_error", "acceleration_error", "penetration", "stack_poses",
           "free_mask", "sequence_metrics", "aggregate", "ms_per_frame", "MM"]

MM = 1000.0
Pinned = Union[int, torch.Tensor]


def _check(pred: torch.Tensor, ref: torch.Tensor):
    if pred.shape != ref.shape or pred.shape[-1] != 3 or pred.dim() < 3:
        raise ValueError(f"pred and ref must have the same (..., S, N, 3) shape, got "
                         f"{tuple(pred.shape)} and {tuple(ref.shape)}")


def _quantile(x: torch.Tensor, q: float) -> float:
    x = x.reshape(-1).double()
    if x.numel() == 0:
        return 0.0
    k = max(1, min(x.numel(), int(round(q * (x.numel() - 1))) + 1))
    return float(x.kthvalue(k).values)


def free_mask(pinned: Pinned, s: int, n: int, device=None) -> torch.Tensor:
    """(S, N) bool: particles at or past each strand's pinned prefix (``pinned``: int or (S,))."""
    counts = torch.as_tensor(pinned, device=device).reshape(-1)
    counts = counts.expand(s) if counts.numel() == 1 else counts
    if counts.shape != (s,):
        raise ValueError(f"pinned must be one count or one per strand ({s}); got shape {tuple(counts.shape)}")
    return torch.arange(n, device=device)[None, :] >= counts.to(device)[:, None]


def _free_values(d: torch.Tensor, pinned: Pinned) -> torch.Tensor:
    """The entries of d (..., S, N) at free particles, flattened."""
    mask = free_mask(pinned, d.shape[-2], d.shape[-1], d.device)
    return d[..., mask]


def vertex_errors(pred: torch.Tensor, ref: torch.Tensor, pinned: Pinned = 0) -> Dict[str, float]:
    """Per-vertex distance |pred − ref| over all frames, strands and free vertices.
    Returns {"mean_mm", "p95_mm", "max_mm"}."""
    _check(pred, ref)
    d = _free_values((pred - ref).norm(dim=-1), pinned) * MM
    return {"mean_mm": float(d.mean()), "p95_mm": _quantile(d, 0.95), "max_mm": float(d.max())}


def tip_error(pred: torch.Tensor, ref: torch.Tensor) -> float:
    """Mean distance (mm) between the last vertices (tips) of pred and ref."""
    _check(pred, ref)
    return float((pred[..., -1, :] - ref[..., -1, :]).norm(dim=-1).mean() * MM)


def chamfer(pred: torch.Tensor, ref: torch.Tensor, pinned: Pinned = 0, max_points: int = 1024,
            max_frames: int = 8, seed: int = 0) -> float:
    """Symmetric Chamfer distance (mm) between the vertex clouds of pred and ref, per frame, averaged
    over frames: ½ (mean over p of min over r |p − r| + mean over r of min over p |r − p|).

    It scores the hair volume regardless of which strand is where (two methods that swap strands
    score alike). To keep it O(max_points²) per sequence: frames with more than ``max_points`` free
    vertices use the same random subset (``seed``) of vertices in both clouds, and sequences of more
    than ``max_frames`` frames are scored on ``max_frames`` evenly spaced frames (first and last
    included). Identical clouds score 0 whatever the subset.
    """
    _check(pred, ref)
    frames_p = pred.reshape((-1,) + pred.shape[-3:])
    frames_r = ref.reshape((-1,) + ref.shape[-3:])
    T = frames_p.shape[0]
    if T > max_frames:
        pick = torch.linspace(0, T - 1, max_frames).round().long().unique()
        frames_p, frames_r = frames_p[pick.to(pred.device)], frames_r[pick.to(ref.device)]
    mask = free_mask(pinned, pred.shape[-3], pred.shape[-2], pred.device)
    idx = torch.nonzero(mask.reshape(-1), as_tuple=False)[:, 0]
    if idx.numel() > max_points:
        g = torch.Generator().manual_seed(seed)
        idx = idx[torch.randperm(idx.numel(), generator=g)[:max_points].to(idx.device)]
    total = 0.0
    for p, r in zip(frames_p, frames_r):
        a, b = p.reshape(-1, 3)[idx].double(), r.reshape(-1, 3)[idx].double()
        d = torch.cdist(a, b, compute_mode="donot_use_mm_for_euclid_dist")
        total += 0.5 * float(d.amin(1).mean() + d.amin(0).mean())  # amin: min(0) is strided and slow
    return total / frames_p.shape[0] * MM


def curvature(x: torch.Tensor) -> torch.Tensor:
    """Discrete curvature (1/m) at interior vertices: (..., N, 3) → (..., N−2).

    κ_i = 2 tan(φ_i / 2) / ((|e_{i−1}| + |e_i|) / 2) with φ_i the turning angle between segments.
    """
    e = x[..., 1:, :] - x[..., :-1, :]
    a, b = e[..., :-1, :], e[..., 1:, :]
    la, lb = a.norm(dim=-1), b.norm(dim=-1)
    kb = 2 * torch.linalg.cross(a, b, dim=-1).norm(dim=-1) / (la * lb + (a * b).sum(-1)).clamp_min(1e-30)
    return kb / (0.5 * (la + lb)).clamp_min(1e-30)


def curvature_error(pred: torch.Tensor, ref: torch.Tensor) -> float:
    """Mean |κ_pred − κ_ref| (1/m) over interior vertices."""
    _check(pred, ref)
    return float((curvature(pred) - curvature(ref)).abs().mean())


def segment_length_error(pred: torch.Tensor, ref: torch.Tensor) -> float:
    """Mean relative segment-length error | |e_pred| / |e_ref| − 1 | (dimensionless)."""
    _check(pred, ref)
    lp = (pred[..., 1:, :] - pred[..., :-1, :]).norm(dim=-1)
    lr = (ref[..., 1:, :] - ref[..., :-1, :]).norm(dim=-1)
    return float((lp / lr.clamp_min(1e-30) - 1).abs().mean())


def strand_length_error(pred: torch.Tensor, ref: torch.Tensor) -> float:
    """Mean absolute difference of strand (polyline) lengths, mm."""
    _check(pred, ref)
    lp = (pred[..., 1:, :] - pred[..., :-1, :]).norm(dim=-1).sum(-1)
    lr = (ref[..., 1:, :] - ref[..., :-1, :]).norm(dim=-1).sum(-1)
    return float((lp - lr).abs().mean() * MM)


def _difference_error(pred: torch.Tensor, ref: torch.Tensor, order: int, dt: float, pinned: Pinned) -> float:
    if pred.dim() != 4 or pred.shape[0] < order + 1:
        raise ValueError(f"a sequence (T ≥ {order + 1}, S, N, 3) is needed; got {tuple(pred.shape)}")
    if not dt > 0:
        raise ValueError(f"dt must be > 0 seconds; got {dt}")
    d = pred - ref
    for _ in range(order):
        d = d[1:] - d[:-1]
    return float(_free_values(d.norm(dim=-1), pinned).mean() / dt ** order * MM)


def velocity_error(pred: torch.Tensor, ref: torch.Tensor, dt: float, pinned: Pinned = 0) -> float:
    """Mean |v_pred − v_ref| (mm/s) of the finite-difference velocities (x_{t+1} − x_t)/dt of a
    sequence (T ≥ 2, S, N, 3): a constant offset scores 0, flicker scores high."""
    _check(pred, ref)
    return _difference_error(pred, ref, 1, dt, pinned)


def acceleration_error(pred: torch.Tensor, ref: torch.Tensor, dt: float, pinned: Pinned = 0) -> float:
    """Mean |a_pred − a_ref| (mm/s²) of (x_{t+1} − 2x_t + x_{t−1})/dt² of a sequence (T ≥ 3, S, N, 3)."""
    _check(pred, ref)
    return _difference_error(pred, ref, 2, dt, pinned)


def stack_poses(poses: Sequence[Pose]) -> Pose:
    """Per-frame poses → one Pose with a leading frame dim (T, 3, 3) (velocities dropped)."""
    return Pose(torch.stack([p.rotation for p in poses]), torch.stack([p.translation for p in poses]))


def penetration(x: torch.Tensor, colliders: Sequence, world_poses: Sequence[Optional[Pose]],
                pinned: Pinned = 0, tolerance: float = 1e-4) -> Dict[str, float]:
    """Vertices inside colliders.

    x: (T, S, N, 3) or (S, N, 3) world positions, metres; colliders: ams_torch colliders;
    world_poses: one world Pose per collider, batched (T, 3, 3) per frame for sequences
    (see :func:`stack_poses`) or unbatched. Pinned vertices are skipped. A vertex counts as inside
    when σ < −``tolerance`` (metres; default 0.1 mm, so particles that the contact response left
    on the surface, up to rounding and the SDF grid's interpolation, do not count).
    Returns {"inside_share" (0…1), "mean_depth_mm" (over penetrating vertices, 0 if none),
    "max_depth_mm"}; the depth of a vertex is −min over colliders of σ when negative.
    """
    if len(colliders) == 0:
        return {"inside_share": 0.0, "mean_depth_mm": 0.0, "max_depth_mm": 0.0}
    sd = _free_values(collider_distances(x, colliders, world_poses).min(0).values, pinned)
    depth = (-sd).clamp_min(0) * MM
    inside = sd < -tolerance
    n = int(inside.sum())
    return {"inside_share": float(inside.double().mean()),
            "mean_depth_mm": float(depth[inside].mean()) if n else 0.0,
            "max_depth_mm": float(depth[inside].max()) if n else 0.0}


def sequence_metrics(pred: torch.Tensor, ref: torch.Tensor, sample: dict) -> Dict[str, float]:
    """Every metric of one sequence: pred, ref (T, S, N, 3) m world; ``sample`` the protocol sample
    (``num_pinned``, ``dt``, ``colliders``, ``collider_poses``, ``head_collider``).

    Keys: mean/p95/max_mm, tip_mm, chamfer_mm, curvature_err (1/m), segment_length_err (relative),
    strand_length_mm, velocity_mm_s, acceleration_mm_s2 (when T allows), head_inside_share,
    head_depth_mean_mm, head_depth_max_mm, colliders_inside_share, colliders_depth_mean_mm,
    colliders_depth_max_mm, frames.
    """
    _check(pred, ref)
    pinned = sample["num_pinned"]
    out = vertex_errors(pred, ref, pinned)
    out.update(tip_mm=tip_error(pred, ref), chamfer_mm=chamfer(pred, ref, pinned),
               curvature_err=curvature_error(pred, ref), segment_length_err=segment_length_error(pred, ref),
               strand_length_mm=strand_length_error(pred, ref), frames=int(pred.shape[0]))
    dt = float(sample["dt"])
    out["velocity_mm_s"] = velocity_error(pred, ref, dt, pinned) if pred.shape[0] >= 2 else math.nan
    out["acceleration_mm_s2"] = acceleration_error(pred, ref, dt, pinned) if pred.shape[0] >= 3 else math.nan
    cols, poses, head = sample["colliders"], sample["collider_poses"], sample.get("head_collider", -1)
    parts = {"head": [i for i in range(len(cols)) if i == head], "colliders": [i for i in range(len(cols)) if i != head]}
    for label, idx in parts.items():
        p = penetration(pred, [cols[i] for i in idx], [poses[i] for i in idx], pinned)
        out.update({f"{label}_inside_share": p["inside_share"], f"{label}_depth_mean_mm": p["mean_depth_mm"],
                    f"{label}_depth_max_mm": p["max_depth_mm"]})
    return out


#: how :func:`aggregate` combines a metric over sequences: "max" for maxima, else a frame-weighted mean
_MAXED = ("max_mm", "head_depth_max_mm", "colliders_depth_max_mm")


def aggregate(rows: Iterable[Dict[str, float]]) -> Dict[str, float]:
    """Combine per-sequence metrics: frame-weighted means (maxima: the maximum), plus
    ``worst_mean_mm`` / ``worst_p95_mm`` (the worst sequence's), ``sequences`` and ``frames``.
    Penetration depth means are weighted by frames too (an approximation: per-vertex counts are not
    kept). NaN entries (velocity of a 1-frame sequence) are skipped."""
    rows: List[Dict[str, float]] = list(rows)
    if not rows:
        return {}
    keys = [k for k in rows[0] if k != "frames" and isinstance(rows[0][k], (int, float))]
    out: Dict[str, float] = {}
    for k in keys:
        vals = [(r[k], r.get("frames", 1)) for r in rows if k in r and not math.isnan(r[k])]
        if not vals:
            out[k] = math.nan
        elif k in _MAXED:
            out[k] = max(v for v, _ in vals)
        else:
            out[k] = sum(v * w for v, w in vals) / sum(w for _, w in vals)
    out["worst_mean_mm"] = max(r["mean_mm"] for r in rows)
    out["worst_p95_mm"] = max(r["p95_mm"] for r in rows)
    out["sequences"] = len(rows)
    out["frames"] = sum(int(r.get("frames", 1)) for r in rows)
    return out


def ms_per_frame(fn: Callable[[int], object], frames: int, warmup: int = 1, device=None) -> float:
    """Wall time per call of ``fn(frame_index)`` in ms, after ``warmup`` untimed calls.

    Synchronises CUDA (when ``device`` is a CUDA device) before reading the clock.
    """
    cuda = device is not None and torch.device(device).type == "cuda"
    for i in range(warmup):
        fn(i)
    if cuda:
        torch.cuda.synchronize(device)
    t0 = time.perf_counter()
    for i in range(frames):
        fn(i)
    if cuda:
        torch.cuda.synchronize(device)
    return (time.perf_counter() - t0) * 1000.0 / max(frames, 1)
