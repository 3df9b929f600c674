"""Known-answer tests of the interpolation benchmark's metrics (baselines.metrics)."""
import math

import pytest
import torch

from ams_torch.geometry.pose import Pose
from ams_torch.stages.collide import SphereCollider
from baselines import metrics as M

D = torch.float64


def _strands(s=6, n=8, t=5, seed=0):
    g = torch.Generator().manual_seed(seed)
    base = torch.zeros(s, n, 3, dtype=D)
    base[..., 1] = -torch.arange(n, dtype=D) * 0.01  # vertical strands, 1 cm segments
    base[..., 0] = torch.arange(s, dtype=D)[:, None] * 0.05  # 5 cm apart
    wobble = 0.002 * torch.randn(t, s, n, 3, generator=g, dtype=D)
    return base + wobble


def test_vertex_tip_errors_of_a_constant_offset():
    ref = _strands()
    d = torch.tensor([0.0012, -0.0016, 0.0], dtype=D)  # |d| = 2 mm
    pred = ref + d
    e = M.vertex_errors(pred, ref)
    assert e["mean_mm"] == pytest.approx(2.0) and e["p95_mm"] == pytest.approx(2.0) and e["max_mm"] == pytest.approx(2.0)
    assert M.tip_error(pred, ref) == pytest.approx(2.0)
    # pinned vertices are skipped: a huge error at the first two particles is not counted
    pred2 = ref.clone()
    pred2[..., :2, :] += 1.0
    assert M.vertex_errors(pred2, ref, pinned=2)["max_mm"] == 0.0
    per_strand = torch.tensor([2, 2, 2, 2, 2, 1])  # strand 5 pins only its root: its particle 1 counts
    assert M.vertex_errors(pred2, ref, pinned=per_strand)["max_mm"] == pytest.approx(math.sqrt(3) * 1000)
    with pytest.raises(ValueError, match="same"):
        M.vertex_errors(pred[:, :3], ref)


def test_chamfer_known_answers():
    ref = _strands()
    # the same cloud with strands swapped: 0 (the volume is the same)
    assert M.chamfer(ref[:, [1, 0, 3, 2, 5, 4]], ref) == pytest.approx(0.0, abs=1e-12)
    # a shift far smaller than the spacing (1 cm): every nearest neighbour is the shifted twin
    d = torch.tensor([0.0, 0.0, 1e-4], dtype=D)
    assert M.chamfer(ref + d, ref) == pytest.approx(0.1, rel=1e-9)
    # subsampling keeps the same answer on this cloud
    assert M.chamfer(ref + d, ref, max_points=17) == pytest.approx(0.1, rel=1e-9)
    # frame subsampling: shifts of 0.01 mm t on frames t = 0..6; 3 evenly spaced frames are 0, 3, 6
    seq = ref[:1].repeat(7, 1, 1, 1)
    shift = torch.arange(7, dtype=D).view(7, 1, 1, 1) * 1e-5 * torch.tensor([0.0, 0.0, 1.0], dtype=D)
    assert M.chamfer(seq + shift, seq) == pytest.approx(0.03, rel=1e-9)  # all 7 frames: mean of 0.01 t
    assert M.chamfer(seq + shift, seq, max_frames=3) == pytest.approx(0.03, rel=1e-9)  # (0 + .03 + .06) / 3
    assert M.chamfer(seq[:5] + shift[:5], seq[:5], max_frames=2) == pytest.approx(0.02, rel=1e-9)  # frames 0, 4


def test_curvature_of_a_circle_and_length_errors():
    r, k = 0.05, 40
    phi = 2 * math.pi / k
    a = torch.arange(k + 1, dtype=D) * phi
    circle = torch.stack((r * torch.cos(a), r * torch.sin(a), torch.zeros_like(a)), -1)[None]
    # regular polygon inscribed in a circle of radius r: 2 tan(φ/2) / (2 r sin(φ/2)) = 1 / (r cos(φ/2))
    assert torch.allclose(M.curvature(circle), torch.full((1, k - 1), 1 / (r * math.cos(phi / 2)), dtype=D))
    assert M.curvature_error(circle, circle) == 0.0
    ref = _strands()
    scaled = ref[..., :1, :] + 1.1 * (ref - ref[..., :1, :])  # every strand 10 % longer
    lengths = (ref[..., 1:, :] - ref[..., :-1, :]).norm(dim=-1).sum(-1)
    assert M.strand_length_error(scaled, ref) == pytest.approx(float(0.1 * lengths.mean() * 1000), rel=1e-9)
    assert M.segment_length_error(scaled, ref) == pytest.approx(0.1, rel=1e-9)


def test_velocity_and_acceleration_errors():
    ref = _strands(t=7)
    dt = 1 / 60
    t = torch.arange(7, dtype=D)[:, None, None, None] * dt
    assert M.velocity_error(ref + 0.01, ref, dt) == pytest.approx(0.0, abs=1e-9)  # a constant offset: no error
    v = torch.tensor([0.3, 0.0, 0.4], dtype=D)  # 0.5 m/s drift
    assert M.velocity_error(ref + t * v, ref, dt) == pytest.approx(500.0, rel=1e-9)
    assert M.acceleration_error(ref + t * v, ref, dt) == pytest.approx(0.0, abs=1e-6)
    b = torch.tensor([0.0, 2.0, 0.0], dtype=D)  # 2 m/s² extra acceleration
    assert M.acceleration_error(ref + 0.5 * t ** 2 * b, ref, dt) == pytest.approx(2000.0, rel=1e-9)
    with pytest.raises(ValueError, match="T ≥ 3"):
        M.acceleration_error(ref[:2], ref[:2], dt)


def test_penetration_depths():
    x = torch.zeros(2, 1, 4, 3, dtype=D)
    x[..., 0] = torch.tensor([0.2, 0.09, 0.095, 0.2], dtype=D)  # two vertices 10 and 5 mm inside
    col = SphereCollider(radius=0.1).to(dtype=D)
    pose = Pose(torch.eye(3, dtype=D).expand(2, 3, 3), torch.zeros(2, 3, dtype=D), check=False)
    p = M.penetration(x, [col], [pose])
    assert p["inside_share"] == pytest.approx(0.5)
    assert p["max_depth_mm"] == pytest.approx(10.0) and p["mean_depth_mm"] == pytest.approx(7.5)
    assert M.penetration(x, [col], [pose], pinned=3)["inside_share"] == 0.0  # only the last vertex is free
    # the collider moved away: nothing inside
    away = Pose(torch.eye(3, dtype=D).expand(2, 3, 3), torch.tensor([[0, 5.0, 0]] * 2, dtype=D), check=False)
    assert M.penetration(x, [col], [away])["inside_share"] == 0.0


def test_sequence_metrics_and_aggregate():
    ref = _strands(t=4)
    col = SphereCollider(radius=0.001, center=(10.0, 0, 0)).to(dtype=D)  # far away: nothing inside
    eye = Pose(torch.eye(3, dtype=D).expand(4, 3, 3), torch.zeros(4, 3, dtype=D), check=False)
    sample = {"num_pinned": torch.full((6,), 2), "dt": 1 / 60, "colliders": [col], "collider_poses": [eye],
              "head_collider": 0}
    row = M.sequence_metrics(ref + torch.tensor([0.001, 0, 0], dtype=D), ref, sample)
    assert row["mean_mm"] == pytest.approx(1.0) and row["velocity_mm_s"] == pytest.approx(0.0, abs=1e-9)
    assert row["frames"] == 4 and row["head_inside_share"] == 0.0 and row["colliders_inside_share"] == 0.0
    rows = [dict(row, mean_mm=1.0, frames=10, max_mm=3.0), dict(row, mean_mm=4.0, frames=30, max_mm=2.0)]
    agg = M.aggregate(rows)
    assert agg["mean_mm"] == pytest.approx((10 * 1.0 + 30 * 4.0) / 40)  # frame-weighted
    assert agg["max_mm"] == 3.0 and agg["worst_mean_mm"] == 4.0 and agg["sequences"] == 2 and agg["frames"] == 40
