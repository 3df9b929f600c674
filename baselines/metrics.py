"""Fidelity metrics of interpolated hair against the dense simulation (SPEC §11).

All positions are metres, shaped (F, S, N, 3) (a sequence) or (S, N, 3) (one frame); reported
lengths are millimetres. Functions return Python floats.
"""
from __future__ import annotations

import time
from typing import Callable, Dict, Optional, Sequence

import torch

from ams_torch.stages.collide import collider_distances
from ams_torch.geometry.pose import Pose

__all__ = ["vertex_errors", "tip_error", "curvature", "curvature_error", "segment_length_error",
           "strand_length_error", "penetration", "temporal_jitter", "stack_poses", "summary",
           "ms_per_frame"]

MM = 1000.0


def _check(pred: torch.Tensor, ref: torch.Tensor):
    if pred.shape != ref.shape or pred.shape[-1] != 3:
        raise ValueError(f"pred and ref must have the same (..., S, N, 3) shape, got "
                         f"{tuple(pred.shape)} and {tuple(ref.shape)}")


def _quantile(x: torch.Tensor, q: float) -> float:
    x = x.reshape(-1).double()
    k = max(1, min(x.numel(), int(round(q * (x.numel() - 1))) + 1))
    return float(x.kthvalue(k).values)


def vertex_errors(pred: torch.Tensor, ref: torch.Tensor, pinned: int = 0) -> Dict[str, float]:
    """Per-vertex distance |pred − ref| over all frames/strands/vertices from index ``pinned``
    on. Returns {"mean_mm", "p95_mm", "max_mm"}."""
    _check(pred, ref)
    d = (pred - ref)[..., pinned:, :].norm(dim=-1) * MM
    return {"mean_mm": float(d.mean()), "p95_mm": _quantile(d, 0.95), "max_mm": float(d.max())}


def tip_error(pred: torch.Tensor, ref: torch.Tensor) -> float:
    """Mean distance (mm) between the last vertices (tips) of pred and ref."""
    _check(pred, ref)
    return float((pred[..., -1, :] - ref[..., -1, :]).norm(dim=-1).mean() * MM)


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


def stack_poses(poses: Sequence[Pose]) -> Pose:
    """Per-frame poses → one Pose with a leading frame dim (F, 3, 3) (velocities dropped)."""
    return Pose(torch.stack([p.rotation for p in poses]), torch.stack([p.translation for p in poses]))


def penetration(x: torch.Tensor, colliders: Sequence, world_poses: Sequence[Optional[Pose]],
                pinned: int = 0, tolerance: float = 1e-5) -> Dict[str, float]:
    """Vertices inside colliders.

    x: (F, S, N, 3) or (S, N, 3) world positions, metres; colliders: ams_torch colliders;
    world_poses: one world Pose per collider, batched (F, 3, 3) per frame for sequences
    (see :func:`stack_poses`) or unbatched. Vertices before index ``pinned`` are skipped. A vertex
    counts as inside when σ < −``tolerance`` (metres; default 0.01 mm, so particles the contact
    response left exactly on the surface, up to rounding, do not count).
    Returns {"inside_share" (0…1), "mean_depth_mm" (over penetrating vertices, 0 if none),
    "max_depth_mm"}; the depth of a vertex is −min over colliders of σ when negative.
    """
    if len(colliders) == 0:
        return {"inside_share": 0.0, "mean_depth_mm": 0.0, "max_depth_mm": 0.0}
    sd = collider_distances(x, colliders, world_poses).min(0).values[..., pinned:]
    depth = (-sd).clamp_min(0) * MM
    inside = sd < -tolerance
    n = int(inside.sum())
    return {"inside_share": float(inside.double().mean()),
            "mean_depth_mm": float(depth[inside].mean()) if n else 0.0,
            "max_depth_mm": float(depth[inside].max()) if n else 0.0}


def temporal_jitter(x: torch.Tensor) -> float:
    """Mean second time difference |x_{t+1} − 2x_t + x_{t−1}| (mm) of a sequence (F, S, N, 3)."""
    if x.dim() < 4 or x.shape[0] < 3:
        raise ValueError("temporal_jitter needs a sequence (F ≥ 3, S, N, 3)")
    return float((x[2:] - 2 * x[1:-1] + x[:-2]).norm(dim=-1).mean() * MM)


def summary(pred: torch.Tensor, ref: torch.Tensor, colliders: Sequence = (),
            world_poses: Sequence[Optional[Pose]] = (), pinned: int = 0) -> Dict[str, float]:
    """All metrics of pred against ref in one dict (penetration of pred only; jitter of both)."""
    out = vertex_errors(pred, ref, pinned)
    out.update(tip_mm=tip_error(pred, ref), curvature_err=curvature_error(pred, ref),
               segment_length_err=segment_length_error(pred, ref),
               strand_length_mm=strand_length_error(pred, ref))
    out.update({f"pen_{k}": v for k, v in penetration(pred, colliders, world_poses, pinned).items()})
    if pred.dim() >= 4 and pred.shape[0] >= 3:
        out.update(jitter_mm=temporal_jitter(pred), ref_jitter_mm=temporal_jitter(ref))
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
