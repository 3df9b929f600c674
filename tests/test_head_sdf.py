"""The default head mesh, mesh loading and the signed distance grid (SPEC §8)."""
import math
import os

import numpy as np
import pytest
import torch
import trimesh

from ams_torch.geometry.mesh import load_mesh
from ams_torch.grooms.head import default_head
from ams_torch.geometry.sdf import SDFGrid, sdf_cache_dir

pcu = pytest.importorskip("point_cloud_utils")


@pytest.fixture(scope="session")
def head():
    return default_head()


@pytest.fixture(scope="session")
def head_sdf64(head, tmp_path_factory):
    return SDFGrid.from_mesh(head, resolution=64, cache_dir=tmp_path_factory.mktemp("sdf"))


def exact_signed_distance(mesh, points):
    """Reference σ (float64): exact closest-point distance, sign by ray parity (independent of
    the winding number the grid uses)."""
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    d, _, _ = pcu.closest_points_on_mesh(points, v, f)
    return np.where(ray_parity_inside(mesh, points), -d, d)


def ray_parity_inside(mesh, points):
    """Containment oracle: crossings of rays in three generic directions, majority vote."""
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    votes = np.zeros(len(points), dtype=np.int64)
    for d in ([1.0, 0.01234, 0.00789], [-0.0123, 1.0, 0.0231], [0.0311, -0.0177, -1.0]):
        d = np.asarray(d) / np.linalg.norm(d)
        origin = np.array(points, dtype=np.float64)
        crossings = np.zeros(len(origin), dtype=np.int64)
        active = np.arange(len(origin))
        for _ in range(64):
            fid, _, t = pcu.ray_mesh_intersection(v, f, origin[active], np.tile(d, (len(active), 1)))
            fid, t = np.atleast_1d(fid), np.atleast_1d(t)  # pcu squeezes the answer for one ray
            hit = fid >= 0
            if not hit.any():
                break
            active = active[hit]
            crossings[active] += 1
            origin[active] = origin[active] + (t[hit, None] + 1e-5) * d  # step past the hit (float32 BVH)
        votes += crossings % 2
    return votes >= 2


def near_surface_points(mesh, count, lo, hi, seed):
    rng = np.random.default_rng(seed)
    pts, fid = trimesh.sample.sample_surface(mesh, count, seed=seed)
    return pts + mesh.face_normals[fid] * rng.uniform(lo, hi, (count, 1))


# ---------------------------------------------------------------------------------------
# head
# ---------------------------------------------------------------------------------------
def test_default_head_is_closed_deterministic_and_head_sized(head):
    assert head.is_watertight and head.is_winding_consistent and head.volume > 0
    again = default_head()
    np.testing.assert_array_equal(np.asarray(again.vertices), np.asarray(head.vertices))
    np.testing.assert_array_equal(np.asarray(again.faces), np.asarray(head.faces))
    lo, hi = head.bounds
    width, height, depth = hi - lo
    assert 0.13 < width < 0.20 and 0.18 < depth < 0.26  # ear to ear, nose to back of skull
    assert 0.25 < height < 0.40  # crown to the bottom of the neck
    assert 0.08 < hi[1] < 0.16  # crown above the origin, head centred near it
    assert hi[2] > -lo[2]  # the face (nose) looks toward +z
    volume_litres = head.volume * 1e3
    assert 3.0 < volume_litres < 7.0


def test_default_head_regions(head):
    regions = head.metadata["regions"]
    nf = len(head.faces)
    for name in ("scalp", "beard"):
        assert regions[name].size > 500, name
        assert regions[name].min() >= 0 and regions[name].max() < nf
    # the named regions partition the faces
    allf = np.concatenate(list(regions.values()))
    assert len(allf) == nf and len(np.unique(allf)) == nf
    c = head.triangles_center
    scalp, beard = c[regions["scalp"]], c[regions["beard"]]
    assert scalp[:, 1].mean() > 0.03 and beard[:, 1].mean() < -0.05  # scalp on top, beard low
    assert beard[:, 2].min() > -0.01  # beard on the front half
    assert head.area_faces[regions["scalp"]].sum() > 0.03  # m²: a real scalp, not a patch
    # returned meshes are copies: editing one does not change the next
    mine = default_head()
    mine.vertices[:] = 0
    mine.metadata["regions"]["scalp"][:] = 0
    fresh = default_head()
    assert np.abs(np.asarray(fresh.vertices)).max() > 0.05
    np.testing.assert_array_equal(fresh.metadata["regions"]["scalp"], regions["scalp"])


def test_load_mesh_roundtrip_and_non_watertight(tmp_path, caplog):
    box = trimesh.creation.box((0.1, 0.2, 0.3))
    good = tmp_path / "box.ply"
    box.export(good)
    loaded = load_mesh(good)
    assert loaded.is_watertight and math.isclose(loaded.volume, 0.006, rel_tol=1e-6)

    holed = trimesh.Trimesh(box.vertices, box.faces[1:], process=False)
    bad = tmp_path / "holed_box.obj"
    holed.export(bad)
    with pytest.raises(ValueError, match="holed_box.obj.*not watertight"):
        load_mesh(bad)
    with caplog.at_level("WARNING"):
        fixed = load_mesh(bad, repair=True)
    assert fixed.is_watertight and fixed.volume > 0
    assert any("repairing" in r.message for r in caplog.records)

    from ams_torch.stages.collide import MeshCollider

    with pytest.raises(ValueError, match="not watertight"):
        MeshCollider(holed)


# ---------------------------------------------------------------------------------------
# SDF grid
# ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_sdf_accuracy_near_the_head(head, head_sdf64, dtype):
    pts = near_surface_points(head, 1000, -0.01, 0.02, seed=1)
    exact = exact_signed_distance(head, pts)
    grid = head_sdf64.to(dtype=dtype)
    sigma = grid.distance(torch.as_tensor(pts, dtype=dtype))
    assert sigma.dtype == dtype and sigma.shape == (1000,)
    err = np.abs(sigma.double().numpy() - exact)
    h = grid.voxel_size
    assert err.max() <= 0.5 * h, f"max error {err.max() / h:.3f} voxel"
    assert err.mean() <= 0.05 * h
    # distance_and_normal agrees with distance; normals are unit and point outward
    s2, n = grid.distance_and_normal(torch.as_tensor(pts, dtype=dtype))
    torch.testing.assert_close(s2, sigma)
    torch.testing.assert_close(n.norm(dim=-1), torch.ones(1000, dtype=dtype))
    pts_s, fid = trimesh.sample.sample_surface(head, 500, seed=3)
    _, n_s = grid.distance_and_normal(torch.as_tensor(pts_s, dtype=dtype))
    cos = (n_s.double().numpy() * head.face_normals[fid]).sum(1)
    assert np.median(cos) > 0.97 and (cos > 0.5).mean() > 0.97


def test_sdf_sign_matches_containment(head, head_sdf64):
    rng = np.random.default_rng(7)
    lo, hi = head.bounds
    pts = rng.uniform(lo - 0.03, hi + 0.03, size=(4000, 3))
    inside = ray_parity_inside(head, pts)
    sigma = head_sdf64.distance(torch.as_tensor(pts, dtype=torch.float32)).numpy()
    band = np.abs(sigma) > head_sdf64.voxel_size
    assert inside[band].sum() > 500 and (~inside[band]).sum() > 500  # both signs well covered
    np.testing.assert_array_equal(sigma[band] < 0, inside[band])


def test_sdf_outside_the_box_and_gradients(head, head_sdf64):
    far = torch.tensor([[1.0, 0.0, 0.0], [0.0, -2.0, 0.0], [0.3, 0.4, -0.5]], dtype=torch.float64)
    sigma, n = head_sdf64.to(dtype=torch.float64).distance_and_normal(far)
    exact = exact_signed_distance(head, far.numpy())
    # clamp-to-box plus distance to the box: positive, and an upper bound within a few per cent
    assert (sigma > 0).all()
    h = head_sdf64.voxel_size
    assert (sigma.numpy() >= exact - h).all() and (sigma.numpy() <= 1.03 * exact + h).all()
    # the normal far away points roughly away from the head
    assert ((n * far).sum(-1) / far.norm(dim=-1) > 0.7).all()
    # differentiable w.r.t. points; the gradient of σ is close to the normal
    p = torch.tensor([[0.0, 0.15, 0.0], [0.12, 0.0, 0.0]], dtype=torch.float64, requires_grad=True)
    grid = head_sdf64.to(dtype=torch.float64)
    grid.distance(p).sum().backward()
    _, n_p = grid.distance_and_normal(p.detach())
    cos = torch.nn.functional.cosine_similarity(p.grad, n_p, dim=-1)
    assert (cos > 0.95).all(), cos


def test_sdf_from_function_sphere(device):
    r = 0.1

    def sphere(p):
        return p.norm(dim=-1) - r

    grid = SDFGrid.from_function(sphere, (-0.15, -0.15, -0.15), (0.15, 0.15, 0.15), resolution=48,
                                 dtype=torch.float64).to(device)
    gen = torch.Generator().manual_seed(0)
    p = (torch.rand(2000, 3, generator=gen, dtype=torch.float64) * 0.4 - 0.2).to(device)
    sigma, n = grid.distance_and_normal(p)
    h = grid.voxel_size
    in_box = (p.abs() <= 0.15).all(-1)
    # smooth field inside the box, away from the kink at the centre: trilinear error O(h²/r)
    smooth = in_box & (p.norm(dim=-1) > 0.03)
    assert (sigma - sphere(p))[smooth].abs().max() < 0.1 * h
    # outside the box: positive and never below the true distance (clamp + distance to box)
    assert (sigma[~in_box] >= sphere(p)[~in_box] - 1e-9).all() and (~in_box).sum() > 500
    cos = (n * p / p.norm(dim=-1, keepdim=True)).sum(-1)
    assert cos[smooth].min() > 0.995
    assert cos[~in_box].min() > 0.7  # outside the box: still pointing away
    assert grid.device.type == device.type and sigma.device.type == device.type
    # float32 points on the float64 grid are converted on the fly
    s32 = grid.distance(p.float())
    assert s32.dtype == torch.float32
    torch.testing.assert_close(s32.double(), sigma, atol=1e-6, rtol=0)


def test_sdf_disk_cache(head, tmp_path, monkeypatch):
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=0.05)
    monkeypatch.setenv("AMS_TORCH_CACHE", str(tmp_path / "env_cache"))
    assert sdf_cache_dir() == tmp_path / "env_cache" / "sdf"
    a = SDFGrid.from_mesh(mesh, resolution=16)
    files = sorted(os.listdir(sdf_cache_dir()))
    assert len(files) == 1 and files[0].endswith("_16.npz")  # no temporary files left behind
    b = SDFGrid.from_mesh(mesh, resolution=16)
    torch.testing.assert_close(a.values, b.values)
    # a cache hit must not recompute: corrupt the stored values and see them come back
    path = sdf_cache_dir() / files[0]
    with np.load(path) as data:
        stored = dict(data)
    stored["values"] = stored["values"] + 1.0
    np.savez(path, **stored)
    c = SDFGrid.from_mesh(mesh, resolution=16)
    torch.testing.assert_close(c.values, a.values + 1.0)
    # another resolution or another mesh is another key
    SDFGrid.from_mesh(mesh, resolution=20)
    moved = mesh.copy()
    moved.apply_translation((0.001, 0, 0))
    SDFGrid.from_mesh(moved, resolution=16)
    assert len(os.listdir(sdf_cache_dir())) == 3
    # an unreadable cache file is rebuilt, not trusted
    path.write_bytes(b"not an npz")
    d = SDFGrid.from_mesh(mesh, resolution=16)
    torch.testing.assert_close(d.values, a.values)
