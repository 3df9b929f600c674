"""Procedural growth (SPEC §9), presets, the Groom's root binding and strand resampling."""
import math

import numpy as np
import pytest
import torch
import trimesh

import ams_torch.grooms.presets as presets
from ams_torch.grooms.groom import Groom, resample_strands, strand_lengths
from ams_torch.grooms.clumps import clump_labels, neighbour_distance, strand_draws
from ams_torch.grooms.growth import GrowthParams, grow, grow_from_roots
from ams_torch.grooms.presets import preset


# ------------------------------------------------------------------------------------------
# fixtures
# ------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def sphere():
    """A 0.1 m icosphere with a 'top' region (faces whose centre has y > 0.05)."""
    m = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    m.metadata["regions"] = {"top": np.flatnonzero(m.triangles_center[:, 1] > 0.05)}
    return m


def exact_signed_distance(mesh, points):
    """Exact σ (m, negative inside) from closest points and the winding number (pcu)."""
    pcu = pytest.importorskip("point_cloud_utils")
    v = np.ascontiguousarray(mesh.vertices, dtype=np.float64)
    f = np.ascontiguousarray(mesh.faces, dtype=np.int64)
    p = np.ascontiguousarray(points, dtype=np.float64)
    d, _, _ = pcu.closest_points_on_mesh(p, v, f)
    w = pcu.triangle_soup_fast_winding_number(v, f, p)
    return np.where(np.abs(w) > 0.5, -d, d)


def mean_curvature(x):
    """Mean discrete curvature (turning angle per unit length, 1/m) of strands (S, N, 3)."""
    e = np.diff(np.asarray(x, dtype=np.float64), axis=1)
    el = np.linalg.norm(e, axis=-1)
    t = e / el[..., None]
    cos = np.clip((t[:, 1:] * t[:, :-1]).sum(-1), -1, 1)
    return float((np.arccos(cos) / (0.5 * (el[:, 1:] + el[:, :-1]))).mean())


# ------------------------------------------------------------------------------------------
# the recurrence itself
# ------------------------------------------------------------------------------------------
def literal_strand(root, d0, steps, tau, p_gamma, p_h, p_freq=1.0, p_omega=0.017, p_Gamma=0.2, phase=0.0):
    """SPEC §9 written out with Python floats, one strand, no collisions."""
    x = [list(root)]
    d = list(d0)
    for i in range(1, steps + 1):
        g = [0.0, -(i - 1) * p_gamma, 0.0]
        f = max(p_Gamma, 1.0 - abs(d[1]))
        dp = [d[k] + g[k] * f for k in range(3)]
        h = [p_h * math.cos(i * p_freq + phase), 1.0, p_h * math.sin(i * p_freq + phase)]
        d = [dp[k] + p_omega * (dp[k] - h[k]) for k in range(3)]
        n = math.sqrt(sum(c * c for c in d))
        x.append([x[-1][k] + tau * d[k] / n for k in range(3)])
    return np.array(x)


def test_recurrence_matches_spec_literally():
    rng = np.random.default_rng(3)
    roots = rng.normal(size=(5, 3)) * 0.05
    dirs = rng.normal(size=(5, 3))
    phase = rng.uniform(-1, 1, 5)
    params = GrowthParams(step=0.004, droop=0.03, helix_radius=40.0, helix_freq=0.7, collide=False)
    got = grow_from_roots(roots, dirs, 30, params, phase=phase)
    for s in range(5):
        want = literal_strand(roots[s], dirs[s], 30, 0.004, 0.03, 40.0, p_freq=0.7, phase=phase[s])
        np.testing.assert_allclose(got[s], want, rtol=0, atol=1e-12)


def test_paper_defaults_and_aliases():
    p = GrowthParams()
    assert (p.gravity_floor, p.helix_freq, p.spiral) == (0.2, 1.0, 0.017)
    q = GrowthParams.make(p_tau=0.003, p_gamma=0.1, p_h=7.0, p_Omega=0.02, p_Gamma=0.3, p_freq=0.5)
    assert (q.step, q.droop, q.helix_radius, q.spiral, q.gravity_floor, q.helix_freq) == (0.003, 0.1, 7.0, 0.02, 0.3, 0.5)
    with pytest.raises(TypeError, match="unknown growth parameter"):
        GrowthParams.make(p_tua=0.1)
    with pytest.raises(TypeError, match="twice"):
        GrowthParams.make(step=0.1, p_tau=0.2)
    with pytest.raises(ValueError, match="positive"):
        GrowthParams(step=0.0)


# ------------------------------------------------------------------------------------------
# roots
# ------------------------------------------------------------------------------------------
def test_every_root_lies_on_its_triangle(sphere):
    g = grow(sphere, region="top", strands=500, particles=8, seed=2, collide=False)
    b = g.root_barycentrics.double()
    assert torch.all(b >= 0) and torch.allclose(b.sum(1), torch.ones(500, dtype=torch.float64), atol=1e-6)
    faces = torch.as_tensor(sphere.faces)
    assert torch.equal(g.root_face_vertices, faces[g.root_triangles])
    assert set(g.root_triangles.tolist()) <= set(sphere.metadata["regions"]["top"].tolist())
    corners = torch.as_tensor(sphere.vertices)[g.root_face_vertices]  # (S, 3, 3)
    on_tri = (b[..., None] * corners).sum(1)
    root = g.rest_positions[:, 0].double()
    assert torch.allclose(root, on_tri, atol=1e-7)
    # and in the triangle's plane, within float32 rounding
    nrm = torch.linalg.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    nrm = nrm / nrm.norm(dim=1, keepdim=True)
    assert ((root - corners[:, 0]) * nrm).sum(1).abs().max() < 1e-7
    assert torch.allclose(g.root_positions(sphere.vertices), root, atol=1e-7)


def test_per_triangle_mode_places_p_n_roots_on_every_triangle(sphere):
    faces = sphere.metadata["regions"]["top"]
    g = grow(sphere, region="top", per_triangle=3, particles=4, seed=0, collide=False)
    assert g.num_strands == 3 * len(faces)
    counts = np.bincount(g.root_triangles.numpy(), minlength=len(sphere.faces))
    assert np.all(counts[faces] == 3) and counts.sum() == 3 * len(faces)


def test_strands_mode_samples_triangles_by_area():
    # two triangles, areas 1 : 3
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 0, -1], [2, 0, 0], [3, 0, 0], [2, 0, -3.0]]) * 0.01
    f = np.array([[0, 1, 2], [3, 4, 5]])
    g = grow((v, f), region=None, strands=20000, particles=2, seed=5, collide=False)  # (vertices, faces) works too
    frac = float((g.root_triangles == 1).double().mean())
    assert abs(frac - 0.75) < 0.015


def test_bad_region_is_a_clear_error(sphere):
    with pytest.raises(ValueError, match="no region 'scalp'"):
        grow(sphere, region="scalp", strands=10)
    with pytest.raises(ValueError, match="exactly one"):
        grow(sphere, region="top", strands=10, per_triangle=2, collide=False)


# ------------------------------------------------------------------------------------------
# determinism and trends
# ------------------------------------------------------------------------------------------
def test_same_seed_same_groom_bit_for_bit(head, head_sdf):
    kw = dict(region="scalp", strands=300, particles=24, droop=0.3, helix_radius=300.0, phase_jitter=1.0,
              noise=0.5, length=0.12, length_jitter=0.3, sdf=head_sdf)
    a = grow(head, seed=11, **kw)
    b = grow(head, seed=11, **kw)
    c = grow(head, seed=12, **kw)
    for name in ("rest_positions", "root_triangles", "root_barycentrics", "root_rest_frames"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name
    assert not torch.equal(a.rest_positions, c.rest_positions)


def test_same_seed_same_clumped_groom_and_unclumped_draws_unchanged(head, head_sdf):
    """Clumps are a deterministic function of the roots and their draws come after the strands':
    the same seed gives the same clumped groom bit for bit, and clump_jitter = 1 (every strand
    keeps its own draws) gives exactly the groom without clumps."""
    kw = dict(region="scalp", strands=300, particles=24, droop=0.3, helix_radius=300.0, phase_jitter=math.pi,
              helix_radius_jitter=0.2, noise=0.5, length=0.12, length_jitter=0.3, sdf=head_sdf)
    a = grow(head, seed=11, clump_radius=0.015, phase_length=0.04, **kw)
    b = grow(head, seed=11, clump_radius=0.015, phase_length=0.04, **kw)
    assert torch.equal(a.rest_positions, b.rest_positions) and a.metadata["clumps"] == b.metadata["clumps"] > 1
    alone = grow(head, seed=11, **kw)
    assert alone.metadata["clumps"] == 0 and not torch.equal(a.rest_positions, alone.rest_positions)
    own = grow(head, seed=11, clump_radius=0.015, phase_length=0.04, clump_jitter=1.0, **kw)
    assert torch.equal(own.rest_positions, alone.rest_positions)
    with pytest.raises(ValueError, match="clump_jitter must be in"):
        GrowthParams(clump_jitter=1.5)
    with pytest.raises(ValueError, match="clump_radius must be"):
        GrowthParams(clump_radius=-0.01)


def test_clumps_cover_the_roots_and_members_share_their_draws():
    rng = np.random.default_rng(0)
    roots = rng.uniform(-0.05, 0.05, (400, 3)) * [1, 0.2, 1]
    labels, centres = clump_labels(roots, 0.012)
    assert len(centres) > 5 and np.array_equal(labels[centres], np.arange(len(centres)))
    dist = np.linalg.norm(roots[:, None] - roots[centres][None], axis=-1)  # (S, C)
    assert np.array_equal(labels, dist.argmin(1))  # each root joins its nearest centre ...
    assert dist.min(1).max() <= 0.012  # ... and every root is within the radius of one
    params = GrowthParams(clump_radius=0.012, clump_jitter=0.05, phase_jitter=math.pi, noise=0.4)
    draws, lab = strand_draws(np.random.default_rng(1), roots, params)
    assert np.array_equal(lab, labels)
    for c in range(len(centres)):
        m = labels == c
        if m.sum() > 1:  # members differ by at most w × (the full range of a strand's own draw)
            assert np.ptp(draws["phase"][m]) <= 2 * 0.05 * math.pi + 1e-12
            assert np.ptp(draws["noise"][m], axis=0).max() <= 2 * 0.05 * 0.4 + 1e-12
            assert np.ptp(draws["length_u"][m]) <= 0.05 + 1e-12
    clump_phase = np.array([draws["phase"][labels == c].mean() for c in range(len(centres))])
    assert np.ptp(clump_phase) > math.pi  # ... while the clumps' phases span the range


def test_clumped_wavy_and_curly_keep_neighbours_together(head, head_sdf):
    """Strands whose roots are 8 mm apart: with independent phases (the paper's jitter) they are a
    wave amplitude apart along their length; in the presets' clumps they run together."""
    for name in ("wavy", "curly"):
        clumped = preset(name, strands=800, seed=2, mesh=head, sdf=head_sdf)
        apart = preset(name, strands=800, seed=2, mesh=head, sdf=head_sdf, clump_radius=0.0)
        (near, pairs), (far, _) = neighbour_distance(clumped.rest_positions), neighbour_distance(apart.rest_positions)
        assert pairs > 100
        assert near < 0.04 and far > 0.08 and far > 2.5 * near, (name, near, far)
    straight = preset("straight", strands=800, seed=2, mesh=head, sdf=head_sdf)
    assert neighbour_distance(straight.rest_positions)[0] < 0.025


def test_curliness_rises_with_helix_radius(sphere):
    curv = []
    for p_h in (0.0, 20.0, 60.0, 150.0, 400.0):
        g = grow(sphere, region="top", strands=200, particles=48, seed=0, p_h=p_h, p_tau=0.004, p_gamma=0.0,
                 noise=0.2, collide=False)
        curv.append(mean_curvature(g.rest_positions))
    assert all(b > a for a, b in zip(curv, curv[1:])), curv
    assert curv[-1] > 5 * curv[0]


def test_length_rises_with_step(sphere):
    lengths = []
    for tau in (0.001, 0.002, 0.004, 0.008):
        g = grow(sphere, region="top", strands=100, particles=20, seed=0, p_tau=tau, p_gamma=0.02, p_h=30.0,
                 collide=False)
        lengths.append(g.lengths())
        np.testing.assert_allclose(g.lengths(), 19 * tau, rtol=1e-6)  # K = N − 1 steps of p_τ
    means = [float(np.mean(x)) for x in lengths]
    assert all(b > a for a, b in zip(means, means[1:]))


def test_droop_rises_with_gravity_parameter(sphere):
    drop = []
    for p_gamma in (0.0, 0.002, 0.01, 0.05, 0.3):
        g = grow(sphere, region="top", strands=200, particles=32, seed=0, p_gamma=p_gamma, p_tau=0.005, noise=0.3,
                 collide=False)
        x = g.rest_positions.double()
        drop.append(float((x[:, 0, 1] - x[:, -1, 1]).mean()))  # how far the tips fall below the roots
    assert all(b > a for a, b in zip(drop, drop[1:])), drop


def test_length_parameter_cuts_and_resamples(sphere):
    lengths = np.linspace(0.02, 0.1, 64)
    g = grow(sphere, region="top", strands=64, particles=16, seed=1, p_tau=0.004, p_h=50.0, length=lengths,
             collide=False)
    assert g.rest_positions.shape == (64, 16, 3)
    np.testing.assert_allclose(g.lengths(), lengths, rtol=2e-6)


# ------------------------------------------------------------------------------------------
# collisions and presets on the default head
# ------------------------------------------------------------------------------------------
def test_collision_aware_growth_keeps_strands_out_of_the_head(head, head_sdf):
    kw = dict(region="scalp", strands=300, particles=40, seed=3, droop=0.3, noise=0.2, p_tau=0.006)
    free = grow(head, collide=False, **kw)
    sig_free = exact_signed_distance(head, free.rest_positions[:, 1:].reshape(-1, 3).numpy())
    assert (sig_free < 0).mean() > 0.05  # without collisions, drooping hair goes through the head
    g = grow(head, sdf=head_sdf, **kw)
    sig = exact_signed_distance(head, g.rest_positions[:, 1:].reshape(-1, 3).numpy())
    assert sig.min() > 0
    seg = np.linalg.norm(np.diff(g.rest_positions.double().numpy(), axis=1), axis=-1)
    assert np.median(seg) == pytest.approx(0.006, rel=1e-6)


@pytest.mark.parametrize("name", presets.PRESETS)
def test_presets_start_outside_the_head(name, head, head_sdf):
    g = preset(name, strands=300, seed=0, mesh=head, sdf=head_sdf)
    assert g.metadata["preset"] == name
    x = g.rest_positions
    assert x.dtype == torch.float32 and x.shape[0] == 300 and torch.isfinite(x).all()
    sig = exact_signed_distance(head, x[:, 1:].reshape(-1, 3).numpy())
    assert sig.min() >= 0.0, f"{name}: a particle is {-sig.min() * 1e3:.3f} mm inside the head"
    assert np.abs(exact_signed_distance(head, x[:, 0].numpy())).max() < 1e-6  # roots on the surface
    seg = torch.diff(x.double(), dim=1).norm(dim=-1)
    assert seg.min() > 1e-4  # no degenerate segments
    region = {"beard": "beard", "fur": None}.get(name, "scalp")
    if region is not None:
        assert set(g.root_triangles.tolist()) <= set(head.metadata["regions"][region].tolist())


def test_preset_strand_count_scales_from_100_to_100000(head, head_sdf):
    small = preset("fur", strands=100, mesh=head, sdf=head_sdf)
    big = preset("fur", strands=100_000, particles=4, mesh=head, sdf=head_sdf)
    assert small.rest_positions.shape == (100, 8, 3)
    assert big.rest_positions.shape == (100_000, 4, 3)
    assert 0.008 < float(np.mean(big.lengths())) < 0.016


def test_bob_is_asymmetric(head, head_sdf):
    g = preset("bob", strands=2000, mesh=head, sdf=head_sdf)
    root_x = g.rest_positions[:, 0, 0].numpy()
    length = g.lengths()
    assert length[root_x > 0.03].mean() > 1.6 * length[root_x < -0.03].mean()


def test_ponytail_strands_are_gathered_at_the_tie(head, head_sdf):
    g = preset("ponytail", strands=500, mesh=head, sdf=head_sdf)
    tie = np.asarray(g.metadata["tie"])
    x = g.rest_positions.double().numpy()
    near = np.linalg.norm(x - tie, axis=-1).min(1)
    assert near.max() < 0.015  # every strand passes through the tie
    tips = x[:, -1]
    assert tips[:, 1].max() < tie[1] - 0.1  # and hangs down along the guide


def test_unknown_preset_names_the_choices():
    with pytest.raises(ValueError, match="straight"):
        preset("mohawk", strands=10)


# ------------------------------------------------------------------------------------------
# re-attaching to a moved or deformed mesh
# ------------------------------------------------------------------------------------------
def test_reattach_follows_rigid_motion_and_deformation(sphere):
    g = grow(sphere, region="top", strands=50, particles=10, seed=4, p_h=20.0, collide=False)
    v = torch.as_tensor(sphere.vertices)
    rot = torch.as_tensor(trimesh.transformations.rotation_matrix(0.7, [1, 2, 3])[:3, :3])
    shift = torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64)
    moved = v @ rot.T + shift
    expect = g.rest_positions.double() @ rot.T + shift
    assert torch.allclose(g.root_positions(moved), expect[:, 0], atol=1e-6)
    assert torch.allclose(g.reattach(moved), expect, atol=1e-6)
    # batched vertices (2, V, 3) → (2, S, N, 3)
    both = g.reattach(torch.stack([v, moved]))
    assert both.shape == (2, 50, 10, 3) and torch.allclose(both[0], g.rest_positions.double(), atol=1e-6)
    # deformation: inflate the mesh; roots stay on their (moved) triangles, strands keep their shape
    big = v * 1.2
    assert torch.allclose(g.root_positions(big), 1.2 * g.rest_positions[:, 0].double(), atol=1e-6)
    re = g.reattach(big)
    np.testing.assert_allclose(strand_lengths(re), g.lengths(), rtol=1e-5)
    with pytest.raises(ValueError, match="vertices"):
        g.root_positions(v[:10])


def test_groom_without_binding_refuses_root_positions():
    g = Groom(rest_positions=torch.zeros(2, 4, 3))
    with pytest.raises(ValueError, match="binding"):
        g.root_positions(np.zeros((3, 3)))


# ------------------------------------------------------------------------------------------
# resampling
# ------------------------------------------------------------------------------------------
def _helix(n, turns=3.0, radius=0.01, pitch=0.02):
    t = np.linspace(0, 2 * np.pi * turns, n)
    return np.stack([radius * np.cos(t), -pitch * t / (2 * np.pi), radius * np.sin(t)], 1)


def test_resampling_keeps_lengths_and_is_arc_length_uniform():
    rng = np.random.default_rng(0)
    strands = [_helix(n, turns=rng.uniform(1, 4)) for n in (200, 57, 311, 1000)]
    strands.append(np.cumsum(rng.normal(size=(40, 3)) * 0.003, 0))  # a random walk
    lengths = strand_lengths(strands)
    out = resample_strands(strands, 64)
    assert out.shape == (5, 64, 3)
    np.testing.assert_allclose(strand_lengths(out), lengths, rtol=1e-9)
    for s, src in zip(out, strands):
        np.testing.assert_allclose(s[0], src[0], atol=1e-15)
    seg = np.linalg.norm(np.diff(out[:4], axis=1), axis=-1)  # smooth helices: nearly equal segments
    assert (seg.max(1) / seg.min(1)).max() < 1.02
    # without the length correction the points lie on the polyline at s = L k / (n − 1)
    on = resample_strands([strands[0]], 33, keep_length=False)[0]
    t = np.linspace(0, 2 * np.pi * 1, 10_000)  # dense straight polyline check
    line = np.stack([t, 2 * t, 0 * t], 1)
    on_line = resample_strands([line], 11, keep_length=False)[0]
    np.testing.assert_allclose(on_line, np.linspace(line[0], line[-1], 11), atol=1e-12)
    cum = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(strands[0], axis=0), axis=1))])
    # the arc length of each resampled point, found by locating it on the source polyline
    idx = np.clip(np.searchsorted(cum, np.linspace(0, cum[-1], 33)), 1, len(cum) - 1)
    a, b = strands[0][idx - 1], strands[0][idx]
    frac = np.einsum("ij,ij->i", on - a, b - a) / np.einsum("ij,ij->i", b - a, b - a)
    s_found = cum[idx - 1] + frac * (cum[idx] - cum[idx - 1])
    np.testing.assert_allclose(s_found, np.linspace(0, cum[-1], 33), atol=1e-12)


def test_resampling_tensor_in_tensor_out_and_groom_resampled():
    x = torch.as_tensor(_helix(100), dtype=torch.float64)[None].repeat(3, 1, 1)
    y = resample_strands(x, 20)
    assert isinstance(y, torch.Tensor) and y.dtype == torch.float64 and y.shape == (3, 20, 3)
    g = Groom(strands=[_helix(50), _helix(80)])
    assert g.rest_positions is None and g.num_particles is None
    r = g.resampled(16)
    assert r.rest_positions.shape == (2, 16, 3) and r.strands is None
    np.testing.assert_allclose(r.lengths(), g.lengths(), rtol=1e-6)
    with pytest.raises(ValueError, match="at least 2"):
        resample_strands(x, 1)
