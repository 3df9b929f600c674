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


def hemisphere(r, rings=16, segments=48):
    """An open cup: the upper half (y ≥ 0) of a sphere of radius r, outward faces, rim at y = 0."""
    theta = np.linspace(0.0, np.pi / 2, rings + 1)[1:]
    phi = 2 * np.pi * np.arange(segments) / segments
    ring = np.stack([np.sin(theta)[:, None] * np.cos(phi), np.cos(theta)[:, None] + 0 * phi,
                     np.sin(theta)[:, None] * np.sin(phi)], -1).reshape(-1, 3)
    verts = np.concatenate([[[0.0, 1.0, 0.0]], ring]) * r
    k, k1 = np.arange(segments), (np.arange(segments) + 1) % segments
    faces = [np.stack([np.zeros(segments, int), 1 + k1, 1 + k], 1)]
    for j in range(rings - 1):
        a, b = 1 + j * segments, 1 + (j + 1) * segments
        faces += [np.stack([a + k, a + k1, b + k1], 1), np.stack([a + k, b + k1, b + k], 1)]
    mesh = trimesh.Trimesh(verts, np.concatenate(faces), process=False)
    assert (mesh.face_normals * mesh.triangles_center).sum(1).min() > 0  # outward
    return mesh


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


def test_load_mesh_roundtrip_open_meshes_and_repair(tmp_path, caplog):
    box = trimesh.creation.box((0.1, 0.2, 0.3))
    good = tmp_path / "box.ply"
    box.export(good)
    loaded = load_mesh(good)
    assert loaded.is_watertight and math.isclose(loaded.volume, 0.006, rel_tol=1e-6)
    assert loaded.metadata["source"] == str(good)

    # open meshes load as they are (real heads are open at the neck) ...
    holed = trimesh.Trimesh(box.vertices, box.faces[1:], process=False)
    bad = tmp_path / "holed_box.obj"
    holed.export(bad)
    opened = load_mesh(bad)
    assert not opened.is_watertight and len(opened.faces) == 11
    # ... and repair=True is an optional clean-up: it closes what it can ...
    with caplog.at_level("INFO"):
        fixed = load_mesh(bad, repair=True)
    assert fixed.is_watertight and fixed.volume > 0
    assert any("repaired" in r.message for r in caplog.records)
    # ... and no longer fails when a hole stays open
    cup = tmp_path / "cup.ply"
    hemisphere(0.1).export(cup)
    caplog.clear()
    with caplog.at_level("WARNING"):
        still_open = load_mesh(cup, repair=True)
    assert not still_open.is_watertight
    assert any("stay open" in r.message for r in caplog.records)


def test_load_mesh_rejects_broken_meshes_naming_the_file_and_problem(tmp_path):
    cases = {
        "points.obj": ("v 0 0 0\nv 1 0 0\nv 0 1 0\n", "no triangle faces found"),
        "nan.obj": ("v 0 0 nan\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "1 of 3 vertices have NaN/Inf coordinates"),
        "index.obj": ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n", "face index is out of range"),
        "index.ply": (("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                       "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
                       "0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n"), r"face 0 refers to vertex 7, outside \[0, 3\)"),
    }
    for name, (text, problem) in cases.items():
        path = tmp_path / name
        path.write_text(text)
        with pytest.raises(ValueError, match=problem) as err:
            load_mesh(path)
        assert str(err.value).startswith(str(path)), str(err.value)
    with pytest.raises(FileNotFoundError, match="no such mesh file"):
        load_mesh(tmp_path / "missing.obj")


def test_load_mesh_units_axes_transform_and_size_warning(tmp_path):
    from ams_torch.geometry.units import ImplausibleSizeWarning

    box = trimesh.creation.box((10.0, 20.0, 30.0))  # centimetres
    box.apply_translation((1.0, 2.0, 3.0))
    path = tmp_path / "cm.obj"
    box.export(path)
    with pytest.warns(ImplausibleSizeWarning, match=r"mesh width .* is 30 m, more than 1 m"):
        load_mesh(path)
    m = load_mesh(path, units="cm", up_axis="z", transform=(np.eye(3), (0.0, 0.5, 0.0)))
    np.testing.assert_allclose(m.extents, [0.1, 0.3, 0.2], rtol=1e-12)  # z-up: the 30 cm side is now y
    np.testing.assert_allclose(m.bounds.mean(0), [0.01, 0.03 + 0.5, -0.02], atol=1e-12)
    assert m.is_watertight and m.volume > 0  # a proper rotation keeps the outward orientation


def _tfxmesh_text(vertices, faces, bones=("root_JNT", "head_JNT")):
    lines = ["# TressFX collision mesh (test)", f"numOfBones {len(bones)}", "# bone index, bone name"]
    lines += [f"{i} {b}" for i, b in enumerate(bones)]
    lines += [f"numOfVertices {len(vertices)}", "# vertex index, x y z, normal, joints, weights"]
    for i, v in enumerate(vertices):
        n = v / np.linalg.norm(v)
        lines.append(f"{i} {v[0]:.9g} {v[1]:.9g} {v[2]:.9g} {n[0]:.6g} {n[1]:.6g} {n[2]:.6g} 1 0 0 0 0.75 0.25 0 0")
    lines += [f"numOfTriangles {len(faces)}", "# triangle index, vertex index 0, 1, 2"]
    lines += [f"{i} {a} {b} {c}" for i, (a, b, c) in enumerate(faces)]
    return "\n".join(lines) + "\n"


def test_tfxmesh_reading_and_broken_files(tmp_path):
    ico = trimesh.creation.icosphere(subdivisions=1, radius=0.1)
    v, f = np.asarray(ico.vertices), np.asarray(ico.faces)
    text = _tfxmesh_text(v, f)
    path = tmp_path / "body.tfxmesh"
    path.write_text(text)
    m = load_mesh(path)
    np.testing.assert_allclose(m.vertices, v, atol=1e-9)  # vertex order kept (process=False)
    np.testing.assert_array_equal(m.faces, f)
    assert m.metadata["tfx_bones"] == ["root_JNT", "head_JNT"] and m.is_watertight
    assert m.metadata["tfx_bone_indices"].shape == (len(v), 4) and np.all(m.metadata["tfx_bone_indices"][:, 0] == 1)
    np.testing.assert_allclose(m.metadata["tfx_bone_weights"][0], [0.75, 0.25, 0, 0])
    z = load_mesh(path, up_axis="z")  # normals turn with the mesh
    n0 = m.metadata["tfx_normals"][0]
    np.testing.assert_allclose(z.metadata["tfx_normals"][0], [n0[0], n0[2], -n0[1]], atol=1e-6)

    lines = text.splitlines(keepends=True)
    cut = "".join(lines[: len(lines) // 2])
    broken = {
        "cut.tfxmesh": (cut.encode(), r"truncated or corrupt \.tfxmesh file: numOfTriangles 80 \(line 50\) but only 14"),
        "count.tfxmesh": (text.replace("numOfTriangles 80", "numOfTriangles 81").encode(), "numOfTriangles 81"),
        "flip.tfxmesh": (text.encode()[:200] + b"\xff\xfe" + text.encode()[202:], "byte 200 .* is not UTF-8"),
        "word.tfxmesh": (text.replace("0.75", "heavy", 1).encode(), r"non-numeric value on line \d+"),
        "range.tfxmesh": (text.replace(f"79 {f[79][0]} ", "79 420 ").encode(), r"refers to vertex 420, outside \[0, 42\)"),
        "nothing.tfxmesh": (b"# empty\n", "no numOfVertices section"),
    }
    for name, (data, problem) in broken.items():
        p = tmp_path / name
        p.write_bytes(data)
        with pytest.raises(ValueError, match=problem) as err:
            load_mesh(p)
        assert str(err.value).startswith(str(p)), str(err.value)


# ---------------------------------------------------------------------------------------
# SDF grid
# ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_sdf_accuracy_near_the_head(head, head_sdf, dtype):
    pts = near_surface_points(head, 1000, -0.01, 0.02, seed=1)
    exact = exact_signed_distance(head, pts)
    grid = head_sdf.to(dtype=dtype)
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


def test_sdf_sign_matches_containment(head, head_sdf):
    rng = np.random.default_rng(7)
    lo, hi = head.bounds
    pts = rng.uniform(lo - 0.03, hi + 0.03, size=(4000, 3))
    inside = ray_parity_inside(head, pts)
    sigma = head_sdf.distance(torch.as_tensor(pts, dtype=torch.float32)).numpy()
    band = np.abs(sigma) > head_sdf.voxel_size
    assert inside[band].sum() > 500 and (~inside[band]).sum() > 500  # both signs well covered
    np.testing.assert_array_equal(sigma[band] < 0, inside[band])


def test_sdf_outside_the_box_and_gradients(head, head_sdf):
    far = torch.tensor([[1.0, 0.0, 0.0], [0.0, -2.0, 0.0], [0.3, 0.4, -0.5]], dtype=torch.float64)
    sigma, n = head_sdf.to(dtype=torch.float64).distance_and_normal(far)
    exact = exact_signed_distance(head, far.numpy())
    # clamp-to-box plus distance to the box: positive, and an upper bound within a few per cent
    assert (sigma > 0).all()
    h = head_sdf.voxel_size
    assert (sigma.numpy() >= exact - h).all() and (sigma.numpy() <= 1.03 * exact + h).all()
    # the normal far away points roughly away from the head
    assert ((n * far).sum(-1) / far.norm(dim=-1) > 0.7).all()
    # differentiable w.r.t. points; the gradient of σ is close to the normal
    p = torch.tensor([[0.0, 0.15, 0.0], [0.12, 0.0, 0.0]], dtype=torch.float64, requires_grad=True)
    grid = head_sdf.to(dtype=torch.float64)
    grid.distance(p).sum().backward()
    _, n_p = grid.distance_and_normal(p.detach())
    cos = torch.nn.functional.cosine_similarity(p.grad, n_p, dim=-1)
    assert (cos > 0.95).all(), cos


def test_sdf_samples_are_the_trilinear_interpolant(head_sdf):
    """distance_and_normal samples the volume through a mosaic of its z-slices (two bilinear
    samples and a step in z, sdf._trilinear): the values and the derivative are grid_sample's 3-D
    trilinear ones (float64 to rounding), at slice and box boundaries too, in both layouts."""
    import torch.nn.functional as F

    grid = SDFGrid(head_sdf.values.double(), head_sdf.origin.double(), head_sdf.spacing)
    gen = torch.Generator().manual_seed(3)
    lo, hi = grid.origin, grid.upper
    p = lo + (hi - lo) * (torch.rand(3000, 3, generator=gen, dtype=torch.float64) * 1.2 - 0.1)
    nodes = torch.randint(0, 8, (200, 3), generator=gen).double()  # exact grid nodes (slice edges)
    p = torch.cat((p, lo + nodes * grid.spacing, lo[None], hi[None]))
    sigma, normal = grid.distance_and_normal(p)
    scale = 2.0 / (hi - lo)
    raw = (p - lo) * scale - 1.0
    coords = raw.clamp(-1.0, 1.0)
    ref = F.grid_sample(grid._volume, coords.reshape(1, 1, 1, -1, 3), mode="bilinear", padding_mode="border",
                        align_corners=True).reshape(4, -1).t()
    outside = (raw - coords) / scale
    d_out = outside.norm(dim=-1)
    assert torch.allclose(sigma, ref[:, 0] + d_out, atol=1e-12, rtol=0)
    away = torch.where(d_out[:, None] > 0, outside / d_out.clamp_min(1e-300)[:, None], torch.zeros_like(outside))
    torch.testing.assert_close(normal, torch.nn.functional.normalize(ref[:, 1:] + away, dim=-1), atol=1e-10, rtol=0)
    s_rows, n_rows = grid.distance_and_normal_rows(p.t().contiguous())
    assert torch.equal(s_rows, sigma) and torch.equal(n_rows.t(), normal)
    # the derivative of σ inside the box is the trilinear interpolant's (off the cell faces)
    q = p[:3000][(coords[:3000].abs() < 0.999).all(-1)].clone().requires_grad_(True)
    grid.distance_and_normal(q)[0].sum().backward()
    c = ((q.detach() - lo) * scale - 1.0).requires_grad_(True)
    F.grid_sample(grid._volume[:, :1], c.reshape(1, 1, 1, -1, 3), mode="bilinear", padding_mode="border",
                  align_corners=True).sum().backward()
    torch.testing.assert_close(q.grad, c.grad * scale, atol=1e-9, rtol=1e-9)
    # float32: the same surface to a fraction of a micrometre
    s32, _ = head_sdf.to(dtype=torch.float32).distance_and_normal(p.float())
    assert (s32.double() - sigma).abs().max() < 1e-6


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


# ---------------------------------------------------------------------------------------
# open meshes, several parts, flipped triangles (SPEC §14)
# ---------------------------------------------------------------------------------------
def test_sdf_of_an_open_hemisphere_cup(tmp_path):
    """For an open part, "inside" is what the surface and the cap spanning its hole enclose:
    for this cup, the upper half ball. Queries stay away from the cap (y = 0), where the
    winding number is 1/2 and the sign is ambiguous."""
    r = 0.1
    cup = hemisphere(r)
    grid = SDFGrid.from_mesh(cup, resolution=48, cache=False)
    rng = np.random.default_rng(0)
    p = rng.uniform(-1.3 * r, 1.3 * r, (8000, 3))
    dist = np.linalg.norm(p, axis=1)
    inside = (dist < 0.85 * r) & (p[:, 1] > 0.25 * r)
    outside = (dist > 1.15 * r) | (p[:, 1] < -0.25 * r)
    sigma = grid.distance(torch.as_tensor(p, dtype=torch.float32)).numpy()
    assert inside.sum() > 250 and outside.sum() > 4000
    assert np.all(sigma[inside] < 0) and np.all(sigma[outside] > 0)
    # distances to the cup where the closest point is on it (y > 0): | |p| − r |, up to faceting
    upper = (p[:, 1] > 0.25 * r) & (np.abs(dist - r) < 0.3 * r)
    exact = np.abs(dist - r)
    facet = r * (1 - np.cos(np.pi / 48))
    assert np.abs(np.abs(sigma[upper]) - exact[upper]).max() < 0.5 * grid.voxel_size + facet


def test_sdf_of_a_cube_with_a_missing_and_a_flipped_face():
    h = 0.05
    box = trimesh.creation.box((2 * h, 2 * h, 2 * h))
    faces = np.asarray(box.faces)
    normals = box.face_normals
    top = normals[:, 1] > 0.9  # +y face: removed
    side = normals[:, 0] > 0.9  # +x face: flipped
    faces = np.concatenate([faces[~top & ~side], faces[side][:, ::-1]])
    mesh = trimesh.Trimesh(box.vertices, faces, process=False)
    assert not mesh.is_watertight and not mesh.is_winding_consistent
    grid = SDFGrid.from_mesh(mesh, resolution=48, cache=False)
    rng = np.random.default_rng(1)
    # inside, away from the missing top: exact distance to the five remaining faces
    q_in = rng.uniform([-0.045, -0.045, -0.045], [0.045, 0.0, 0.045], (2000, 3))
    d_in = np.minimum.reduce([h - np.abs(q_in[:, 0]), h - np.abs(q_in[:, 2]), q_in[:, 1] + h])
    # outside: beside the flipped +x face and below the bottom face
    q_x = rng.uniform([0.055, -0.04, -0.04], [0.08, 0.04, 0.04], (500, 3))
    q_y = rng.uniform([-0.04, -0.08, -0.04], [0.04, -0.055, 0.04], (500, 3))
    q = np.concatenate([q_in, q_x, q_y])
    exact = np.concatenate([-d_in, q_x[:, 0] - h, -h - q_y[:, 1]])
    sigma = grid.to(dtype=torch.float64).distance(torch.as_tensor(q)).numpy()
    np.testing.assert_array_equal(sigma < 0, exact < 0)
    err = np.abs(sigma - exact)
    assert err.max() < 0.5 * grid.voxel_size and np.median(err) < 1e-6, (err.max(), np.median(err))


def test_sdf_of_two_disjoint_spheres_and_random_flips():
    r = 0.05
    a = trimesh.creation.icosphere(subdivisions=3, radius=r)
    b = a.copy()
    a.apply_translation((-0.1, 0, 0))
    b.apply_translation((0.1, 0.02, 0))
    faces = np.concatenate([a.faces, b.faces + len(a.vertices)])
    rng = np.random.default_rng(2)
    flip = rng.random(len(faces)) < 0.3  # 30 % of the triangles flipped, and all of sphere b inverted
    flip[len(a.faces):] = ~flip[len(a.faces):]
    faces[flip] = faces[flip][:, ::-1]
    mesh = trimesh.Trimesh(np.concatenate([a.vertices, b.vertices]), faces, process=False)
    grid = SDFGrid.from_mesh(mesh, resolution=48, cache=False)
    q = rng.uniform([-0.17, -0.07, -0.07], [0.17, 0.09, 0.07], (5000, 3))
    ca, cb = np.array([-0.1, 0, 0]), np.array([0.1, 0.02, 0])
    exact = np.minimum(np.linalg.norm(q - ca, axis=1), np.linalg.norm(q - cb, axis=1)) - r
    sigma = grid.to(dtype=torch.float64).distance(torch.as_tensor(q)).numpy()
    facet = 1.5e-4  # icosphere(3) lies within this of the true sphere at r = 5 cm
    band = np.abs(exact) > grid.voxel_size
    assert (exact[band] < 0).sum() > 200
    np.testing.assert_array_equal(sigma[band] < 0, exact[band] < 0)
    assert np.abs(sigma - exact)[np.abs(exact) < 0.02].max() < 0.5 * grid.voxel_size + facet


def test_orient_faces_and_resolution_bound():
    from ams_torch.geometry.sdf import MAX_RESOLUTION, orient_faces

    ico = trimesh.creation.icosphere(subdivisions=2)
    faces = np.asarray(ico.faces).copy()
    flip = np.random.default_rng(4).random(len(faces)) < 0.5
    faces[flip] = faces[flip][:, ::-1]
    np.testing.assert_array_equal(orient_faces(ico.vertices, faces), ico.faces)
    # a seam of duplicated vertices does not cut the part: split every vertex per face
    soup_v = np.asarray(ico.vertices)[faces].reshape(-1, 3)
    soup_f = np.arange(len(soup_v)).reshape(-1, 3)
    np.testing.assert_array_equal(orient_faces(soup_v, soup_f), np.where(flip[:, None], soup_f[:, ::-1], soup_f))
    with pytest.raises(ValueError, match=rf"resolution must be in \[4, {MAX_RESOLUTION}\]; got 600"):
        SDFGrid.from_mesh(ico, resolution=600, cache=False)
    with pytest.raises(ValueError, match=r"face indices must lie in \[0, 162\); got \[0, 999\]"):
        SDFGrid.from_mesh(trimesh.Trimesh(ico.vertices, np.array([[0, 1, 999]]), process=False), cache=False)


# ---------------------------------------------------------------------------------------
# binding imported roots to a mesh (SPEC §14)
# ---------------------------------------------------------------------------------------
def test_bind_to_reports_distances_and_names_far_strands(caplog):
    from ams_torch.grooms.groom import Groom

    r = 0.1
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=r)
    rng = np.random.default_rng(6)
    dirs = rng.normal(size=(40, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    gap = np.full(40, 2e-4)
    gap[[5, 17, 33]] = [0.02, 0.03, 0.025]  # three roots far off the surface
    roots = dirs * (r + gap[:, None])
    strands = [roots[i] + dirs[i] * np.linspace(0, 0.05, 3 + i % 4)[:, None] for i in range(40)]  # ragged
    groom = Groom(strands=strands)
    with pytest.raises(ValueError, match=r"bind_to: 3 of 40 roots are farther than max_distance = 5 mm .*"
                                         r"\(farthest: strand 17 at 30\.\d+ mm\); strands 5, 17, 33\."):
        groom.bind_to(sphere)
    with caplog.at_level("INFO"):
        bound = groom.bind_to(sphere, max_distance=0.05)
    stats = bound.metadata["binding"]
    facet = r * (1 - np.cos(np.deg2rad(3.0)))  # icosphere(4) sits inside the sphere by less than this
    assert stats["median_distance"] == pytest.approx(2e-4, abs=facet)
    assert stats["max_distance"] == pytest.approx(0.03, abs=facet)
    assert any("root-surface distance median" in rec.message for rec in caplog.records)
    on = bound.root_positions(sphere.vertices).numpy()
    assert np.abs(np.linalg.norm(on, axis=1) - r).max() < facet  # on the mesh
    np.testing.assert_array_equal(bound.root_face_vertices.numpy(), np.asarray(sphere.faces)[bound.root_triangles])
    np.testing.assert_allclose(bound.root_barycentrics.sum(1).numpy(), 1, atol=1e-6)
    snapped = groom.bind_to(sphere, max_distance=0.05, snap=True)
    np.testing.assert_allclose(np.stack([s[0] for s in snapped.strands]), on, atol=1e-7)
    np.testing.assert_allclose(snapped.lengths(), groom.lengths(), rtol=1e-6)  # moved rigidly
    with pytest.raises(ValueError, match="max_distance must be a non-negative number"):
        groom.bind_to(sphere, max_distance=-1)
