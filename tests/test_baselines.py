"""Guide-strand baselines: guide selection, skinning, metrics, upsampler training and DDP."""
import pytest
import torch

import ams_torch as at
from ams_torch.geometry.pose import axis_angle_to_matrix
from ams_torch.testing import sphere_groom
from baselines import LinearHairSkinning, metrics, select_guides


@pytest.fixture(scope="module")
def groom():
    return sphere_groom(strands=300, particles=12, dtype=torch.float64)


def _rigid(x, rot, trans):
    return x @ rot.T + trans


# -- guide selection ----------------------------------------------------------------------
def test_fps_spread_and_deterministic(groom):
    roots = groom[:, 0]
    a = select_guides(roots, 32)
    assert torch.equal(a, select_guides(roots, 32))
    assert a.unique().numel() == 32
    # FPS covers the scalp: every root is closer to a guide than for a random pick on average
    cover_fps = torch.cdist(roots, roots[a]).min(1).values.max()
    g = torch.Generator().manual_seed(0)
    rnd = torch.randperm(roots.shape[0], generator=g)[:32]
    cover_rnd = torch.cdist(roots, roots[rnd]).min(1).values.max()
    assert cover_fps < cover_rnd
    # chosen guides are well separated: min pairwise distance ≥ half the covering radius
    d = torch.cdist(roots[a], roots[a]) + torch.eye(32, dtype=roots.dtype)
    assert d.min() >= 0.5 * cover_fps
    # prefix property: the first 16 of 32 are the 16-guide choice
    assert torch.equal(select_guides(roots, 16), a[:16])


def test_kmeans_guides(groom):
    roots = groom[:, 0]
    k = select_guides(roots, 40, method="kmeans", seed=3)
    assert torch.equal(k, select_guides(roots, 40, method="kmeans", seed=3))
    assert k.unique().numel() == 40 and int(k.max()) < roots.shape[0]
    assert select_guides(roots, roots.shape[0]).unique().numel() == roots.shape[0]
    with pytest.raises(ValueError):
        select_guides(roots, roots.shape[0] + 1)


# -- skinning -----------------------------------------------------------------------------
def test_skinning_exact_when_every_strand_is_a_guide(groom):
    skin = LinearHairSkinning(groom, groom, k=4)
    g = torch.Generator().manual_seed(1)
    moved = groom + 0.01 * torch.randn(groom.shape, generator=g, dtype=groom.dtype)
    assert torch.allclose(skin(moved), moved, atol=1e-12)
    # also with a batch of frames and a head rotation
    rot = axis_angle_to_matrix(torch.tensor([0.2, 0.5, -0.1], dtype=groom.dtype))
    out = skin(torch.stack((moved, groom)), root_rotation=torch.stack((rot, torch.eye(3, dtype=groom.dtype))))
    assert torch.allclose(out[0], moved, atol=1e-12) and torch.allclose(out[1], groom, atol=1e-12)


def test_skinning_reproduces_rigid_motion(groom):
    idx = select_guides(groom[:, 0], 24)
    skin = LinearHairSkinning(groom, groom[idx], k=4)
    assert torch.allclose(skin(groom[idx]), groom, atol=1e-12)
    rot = axis_angle_to_matrix(torch.tensor([0.4, -1.3, 0.8], dtype=groom.dtype))
    trans = torch.tensor([0.05, -0.2, 0.3], dtype=groom.dtype)
    out = skin(_rigid(groom[idx], rot, trans), root_rotation=rot)
    assert (out - _rigid(groom, rot, trans)).abs().max() < 1e-12
    # without the head rotation the twist about the root segment is unknown: not exact
    out_nr = skin(_rigid(groom[idx], rot, trans))
    assert (out_nr - _rigid(groom, rot, trans)).abs().max() > 1e-4
    # a pure translation needs no rotation
    assert torch.allclose(skin(groom[idx] + trans), groom + trans, atol=1e-12)


def test_skinning_rotates_offsets_not_only_translates():
    # one guide bending 90° at its root: the dense strand's offset must rotate with the guide frame
    n = 5
    s = torch.arange(n, dtype=torch.float64)
    guide = torch.stack((torch.zeros(n), -0.01 * s, torch.zeros(n)), -1)[None]
    dense = guide + torch.tensor([0.001, 0.0, 0.0], dtype=torch.float64)
    skin = LinearHairSkinning(dense, guide, k=1)
    bent = torch.stack((0.01 * s, torch.zeros(n), torch.zeros(n)), -1)[None]  # now along +x
    out = skin(bent)
    # rest offset +x ⟂ tangent −y; after a rotation taking −y to +x (about z) it points to +y
    assert torch.allclose(out[0, 1:] - bent[0, 1:], torch.tensor([0.0, 0.001, 0.0], dtype=torch.float64), atol=1e-12)


def test_skinning_interpolates_and_runs_in_float32(groom):
    idx = select_guides(groom[:, 0], 32)
    skin = LinearHairSkinning(groom.float(), groom[idx].float(), k=4)
    assert torch.allclose(skin.weights.sum(1), torch.ones(groom.shape[0]))
    out = skin(groom[idx].float())
    assert out.dtype == torch.float32 and out.shape == groom.shape
    assert (out - groom.float()).abs().max() < 1e-5


# -- metrics ------------------------------------------------------------------------------
def test_metrics_known_values(groom):
    ref = groom.clone()
    pred = ref.clone()
    pred[0] += torch.tensor([0.001, 0.0, 0.0], dtype=ref.dtype)  # strand 0 shifted by 1 mm
    e = metrics.vertex_errors(pred[:1], ref[:1])
    assert e["mean_mm"] == pytest.approx(1.0) and e["max_mm"] == pytest.approx(1.0)
    assert e["p95_mm"] == pytest.approx(1.0)
    assert metrics.tip_error(pred[:1], ref[:1]) == pytest.approx(1.0)
    s = ref.shape[0]
    assert metrics.vertex_errors(pred, ref)["mean_mm"] == pytest.approx(1.0 / s)
    assert metrics.curvature_error(pred, ref) == pytest.approx(0.0, abs=1e-9)
    assert metrics.segment_length_error(pred, ref) == pytest.approx(0.0, abs=1e-12)
    # stretching a straight strand by 10 %: segment error 0.1, strand length error = 10 % of length
    line = torch.stack((torch.zeros(6), -0.01 * torch.arange(6.0), torch.zeros(6)), -1)[None].double()
    assert metrics.segment_length_error(line * 1.1, line) == pytest.approx(0.1)
    assert metrics.strand_length_error(line * 1.1, line) == pytest.approx(5.0)
    # a circle of radius r has curvature 1/r
    t = torch.linspace(0, 1.0, 20, dtype=torch.float64)
    circ = 0.05 * torch.stack((torch.cos(t), torch.sin(t), torch.zeros_like(t)), -1)[None]
    assert metrics.curvature(circ)[0].mean().item() == pytest.approx(20.0, rel=1e-3)


def test_penetration_with_per_frame_poses():
    sphere = at.stages.SphereCollider(center=(0.0, 0.0, 0.0), radius=0.1)
    x = torch.tensor([[[0.098, 0.0, 0.0], [0.2, 0.0, 0.0], [0.0, 0.3, 0.0], [0.0, 0.0, 0.5]]],
                     dtype=torch.float64)  # one vertex 2 mm inside
    p = metrics.penetration(x, [sphere], [None])
    assert p["inside_share"] == pytest.approx(0.25)
    assert p["mean_depth_mm"] == pytest.approx(2.0) and p["max_depth_mm"] == pytest.approx(2.0)
    # the collider moved by a per-frame pose: frame 1 puts it 0.2 m away, nothing inside
    seq = torch.stack((x, x))
    poses = metrics.stack_poses([at.Pose.identity(dtype=torch.float64),
                                 at.Pose.from_rotvec((0, 0, 0), (0.0, -0.2, 0.0), dtype=torch.float64)])
    p2 = metrics.penetration(seq, [sphere], [poses])
    assert p2["inside_share"] == pytest.approx(0.125)
    assert metrics.ms_per_frame(lambda i: None, 3) >= 0.0


# -- the upsampler's network (its training: tests/test_learned.py) -------------------------------
from baselines.upsampler import GuideUpsampler  # noqa: E402


def test_upsampler_is_small_and_starts_at_skinning(groom):
    rest = groom.float()
    g = select_guides(rest[:, 0], 8)
    gen = torch.Generator().manual_seed(0)
    rot = torch.stack([axis_angle_to_matrix(0.3 * torch.randn(3, generator=gen)) for _ in range(4)])
    trans = 0.02 * torch.randn(4, 3, generator=gen)
    x = torch.einsum("tij,snj->tsni", rot, rest) + trans[:, None, None] + 0.003 * torch.randn((4,) + rest.shape, generator=gen)
    up = GuideUpsampler(rest, rest[g], k=4)
    assert sum(p.numel() for p in up.parameters()) < 300_000
    out = up(x[:, g], rot, trans)
    assert out.shape == (4, rest.shape[0], rest.shape[1], 3)
    assert torch.equal(out, up.skin(x[:, g], rot))
    # per-strand pinned counts: no residual on each strand's own pinned prefix
    pinned = torch.randint(1, 4, (rest.shape[0],), generator=gen)
    up = GuideUpsampler(rest, rest[g], k=4, pinned=pinned)
    torch.nn.init.normal_(up.mlp[-1].weight)
    moved = up(x[:2, g], rot[:2], trans[:2]) - up.skin(x[:2, g], rot[:2])
    still = torch.arange(rest.shape[1])[None, :] < pinned[:, None]
    assert moved.norm(dim=-1)[:, still].max() == 0 and moved.norm(dim=-1)[:, ~still].min() > 0
    with pytest.raises(ValueError, match=r"one count or \(S,\)"):
        GuideUpsampler(rest, rest[g], pinned=torch.ones(3, dtype=torch.long))
