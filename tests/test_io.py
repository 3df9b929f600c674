"""Groom file formats: round trips, ragged strands, import units/axes, USD curve types, TressFX
writing, and clear errors on broken files."""
import struct
import tracemalloc
import warnings

import numpy as np
import pytest
import torch

from ams_torch.geometry.units import ImplausibleSizeWarning
from ams_torch.grooms.groom import Groom, strand_lengths
from ams_torch.grooms.io import FORMATS, GroomFileError, read_groom, write_groom

WRITABLE = [".data", ".hair", ".bin", ".ply", ".npz", ".usda", ".usdc"]


def needs(ext):
    if ext.startswith(".usd"):
        pytest.importorskip("pxr")


def uniform_groom(s=40, n=12, seed=0, bound=True):
    rng = np.random.default_rng(seed)
    x = np.cumsum(rng.normal(size=(s, n, 3)) * 0.004, axis=1) + rng.normal(size=(s, 1, 3)) * 0.05
    kw = {}
    if bound:
        kw = dict(root_triangles=rng.integers(0, 500, s), root_barycentrics=rng.dirichlet([1, 1, 1], s),
                  root_face_vertices=rng.integers(0, 300, (s, 3)),
                  root_rest_frames=np.linalg.qr(rng.normal(size=(s, 3, 3)))[0])
    return Groom(rest_positions=torch.as_tensor(x, dtype=torch.float32), metadata={"note": "test"}, **kw)


def ragged_groom(seed=1):
    rng = np.random.default_rng(seed)
    strands = [np.cumsum(rng.normal(size=(n, 3)) * 0.003, 0) for n in (2, 7, 30, 5, 64, 3)]
    return Groom(strands=strands)


def positions(g):
    return np.concatenate([np.asarray(s, np.float32) for s in g.polylines()])


# ------------------------------------------------------------------------------------------
# round trips
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("ext", WRITABLE)
def test_round_trip_uniform(ext, tmp_path):
    needs(ext)
    g = uniform_groom()
    path = tmp_path / f"groom{ext}"
    write_groom(path, g)
    h = read_groom(path)
    assert h.rest_positions is not None and h.rest_positions.shape == g.rest_positions.shape
    assert torch.equal(h.rest_positions, g.rest_positions)  # float32 written, float32 read: exact
    assert h.metadata["format"] == ext and h.metadata["source"] == str(path)
    if ext in (".npz", ".usda", ".usdc"):  # these keep the root binding
        assert torch.equal(h.root_triangles, g.root_triangles)
        assert torch.equal(h.root_face_vertices, g.root_face_vertices)
        assert torch.allclose(h.root_barycentrics, g.root_barycentrics, atol=0)
    else:
        assert not h.has_binding
    if ext == ".npz":
        assert torch.equal(h.root_rest_frames, g.root_rest_frames) and h.metadata["note"] == "test"


@pytest.mark.parametrize("ext", WRITABLE)
def test_round_trip_ragged_and_resample(ext, tmp_path):
    needs(ext)
    g = ragged_groom()
    path = tmp_path / f"ragged{ext}"
    write_groom(path, g)
    h = read_groom(path)
    assert h.rest_positions is None and len(h.strands) == 6
    assert [len(s) for s in h.strands] == [len(s) for s in g.strands]
    for a, b in zip(h.strands, g.strands):
        np.testing.assert_array_equal(a, b)
    r = read_groom(path, resample=16)
    assert r.rest_positions.shape == (6, 16, 3) and r.strands is None
    np.testing.assert_allclose(r.lengths(), strand_lengths(g.strands), rtol=1e-5)


def test_ply_ascii_round_trip(tmp_path):
    g = uniform_groom(bound=False)
    write_groom(tmp_path / "a.ply", g, ascii=True)
    assert (tmp_path / "a.ply").read_bytes().startswith(b"ply\nformat ascii 1.0")
    assert torch.equal(read_groom(tmp_path / "a.ply").rest_positions, g.rest_positions)


def test_hair_extra_arrays_round_trip(tmp_path):
    g = ragged_groom()
    p = sum(len(s) for s in g.strands)
    rng = np.random.default_rng(0)
    extras = dict(thickness=rng.random(p).astype(np.float32), color=rng.random((p, 3)).astype(np.float32))
    g.metadata.update(hair_arrays=extras, info="made by a test")
    write_groom(tmp_path / "x.hair", g)
    h = read_groom(tmp_path / "x.hair")
    np.testing.assert_array_equal(h.metadata["hair_arrays"]["thickness"], extras["thickness"])
    np.testing.assert_array_equal(h.metadata["hair_arrays"]["color"], extras["color"])
    assert "transparency" not in h.metadata["hair_arrays"] and h.metadata["info"] == "made by a test"


def test_ct2hair_bin_keeps_or_writes_point_attributes(tmp_path):
    g = uniform_groom(s=3, n=5, bound=False)
    write_groom(tmp_path / "a.bin", g)
    raw = np.frombuffer((tmp_path / "a.bin").read_bytes()[8:8 + 5 * 28], "<f4").reshape(5, 7)
    t = raw[:, 3:6]
    np.testing.assert_allclose(np.linalg.norm(t, axis=1), 1, atol=1e-6)  # written: unit tangents, label 0
    assert np.all(raw[:, 6] == 0)
    h = read_groom(tmp_path / "a.bin")
    assert h.metadata["bin_attributes"].shape == (15, 4)
    h.metadata["bin_attributes"][:, 3] = 7.0
    write_groom(tmp_path / "b.bin", h)
    assert np.all(read_groom(tmp_path / "b.bin").metadata["bin_attributes"][:, 3] == 7.0)


def write_tfx(path, strands_xyz, version=4.0, w=None):
    """A TressFX 4 file written independently of the reader: header, then float4 positions."""
    s, v, _ = strands_xyz.shape
    w = np.ones((s, v), np.float32) if w is None else w
    header = struct.pack("<f7I32I", version, s, v, 160, 0, 0, 0, 0, *([0] * 32))
    xyzw = np.concatenate([strands_xyz.astype(np.float32), w[..., None]], -1)
    path.write_bytes(header + xyzw.astype("<f4").tobytes())


def test_tfx_read(tmp_path):
    x = uniform_groom(s=8, n=16, bound=False).rest_positions.numpy()
    w = np.ones((8, 16), np.float32)
    w[:, :2] = 0
    write_tfx(tmp_path / "a.tfx", x, w=w)
    h = read_groom(tmp_path / "a.tfx")
    np.testing.assert_array_equal(h.rest_positions.numpy(), x)
    np.testing.assert_array_equal(h.metadata["tfx_w"], w)
    assert h.metadata["tfx_version"] == 4.0


def test_usc_single_point_strands_are_dropped(tmp_path):
    body = struct.pack("<i", 3)
    for pts in (np.zeros((1, 3)), np.ones((4, 3)) * [1, 2, 3], np.zeros((1, 3))):
        body += struct.pack("<i", len(pts)) + pts.astype("<f4").tobytes()
    (tmp_path / "u.data").write_bytes(body)
    h = read_groom(tmp_path / "u.data")
    assert h.num_strands == 1 and h.metadata["dropped_strands"] == 2
    assert h.rest_positions.shape == (1, 4, 3)


def test_ply_edges_in_any_order_and_big_endian(tmp_path):
    # two strands, vertices interleaved, edges shuffled, big-endian with an extra property
    pts = np.array([[0, 0, 0], [9, 9, 9], [0, 1, 0], [9, 8, 9], [0, 2, 0], [9, 7, 9]], np.float32)
    edges = np.array([[2, 4], [1, 3], [0, 2], [3, 5]], np.int32)
    head = (b"ply\nformat binary_big_endian 1.0\nelement vertex 6\nproperty float x\nproperty float y\n"
            b"property float z\nproperty uchar red\nelement edge 4\nproperty int vertex1\nproperty int vertex2\n"
            b"end_header\n")
    vert = b"".join(p.astype(">f4").tobytes() + b"\x07" for p in pts)
    (tmp_path / "be.ply").write_bytes(head + vert + edges.astype(">i4").tobytes())
    h = read_groom(tmp_path / "be.ply")
    assert h.rest_positions.shape == (2, 3, 3)
    np.testing.assert_array_equal(h.rest_positions[0].numpy(), pts[[0, 2, 4]])
    np.testing.assert_array_equal(h.rest_positions[1].numpy(), pts[[1, 3, 5]])


def test_unknown_extension(tmp_path):
    with pytest.raises(ValueError, match=r"unknown groom file extension '\.xyz'"):
        read_groom(tmp_path / "a.xyz")
    assert set(WRITABLE) <= set(FORMATS)


# ------------------------------------------------------------------------------------------
# broken files
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("ext", WRITABLE + [".tfx"])
@pytest.mark.parametrize("keep", [0.5, 0.97])
def test_truncated_files_raise_value_error_naming_the_file(ext, keep, tmp_path):
    needs(ext)
    path = tmp_path / f"cut{ext}"
    g = uniform_groom(s=20, n=10)
    if ext == ".tfx":
        write_tfx(path, g.rest_positions.numpy())
    else:
        write_groom(path, g)
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])
    with pytest.raises(ValueError) as err:
        read_groom(path)
    msg = str(err.value)
    assert str(path) in msg
    assert any(word in msg for word in ("truncated", "corrupt", "unreadable")), msg


def _corrupt_cases(tmp_path):
    g = uniform_groom(s=4, n=6, bound=False)
    cases = {}
    # .data: negative point count
    p = tmp_path / "neg.data"
    write_groom(p, g)
    b = bytearray(p.read_bytes())
    b[4:8] = struct.pack("<i", -3)
    p.write_bytes(bytes(b))
    cases[p] = "negative point count"
    # .data: strand count larger than the file can hold
    p = tmp_path / "huge.data"
    write_groom(p, g)
    b = bytearray(p.read_bytes())
    b[0:4] = struct.pack("<i", 10 ** 9)
    p.write_bytes(bytes(b))
    cases[p] = "header says 1000000000 strands"
    # .data: trailing bytes (counts do not match the size)
    p = tmp_path / "trail.data"
    write_groom(p, g)
    p.write_bytes(p.read_bytes() + b"\0" * 12)
    cases[p] = "trailing bytes"
    # .hair: wrong signature; point count disagreeing with the segments
    p = tmp_path / "sig.hair"
    write_groom(p, g)
    p.write_bytes(b"HAIX" + p.read_bytes()[4:])
    cases[p] = "signature"
    p = tmp_path / "count.hair"
    write_groom(p, g)
    b = bytearray(p.read_bytes())
    b[8:12] = struct.pack("<I", 25)
    p.write_bytes(bytes(b))
    cases[p] = "header says 4 strands and 25 points"
    # NaN coordinates
    p = tmp_path / "nan.bin"
    bad = uniform_groom(s=4, n=6, bound=False)
    bad.rest_positions[2, 3, 1] = float("nan")
    write_groom(p, bad)
    cases[p] = "non-finite coordinates at strand 2, point 3"
    # PLY: header garbage, edges that branch, edges that loop
    p = tmp_path / "garbage.ply"
    p.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty flot x\nend_header\n")
    cases[p] = "cannot parse"
    p = tmp_path / "branch.ply"
    p.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
                  b"element edge 2\nproperty int vertex1\nproperty int vertex2\nend_header\n"
                  b"0 0 0\n1 0 0\n2 0 0\n0 1\n0 2\n")
    cases[p] = "do not form polylines"
    p = tmp_path / "loop.ply"
    p.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
                  b"element edge 3\nproperty int vertex1\nproperty int vertex2\nend_header\n"
                  b"0 0 0\n1 0 0\n2 0 0\n0 1\n1 2\n2 0\n")
    cases[p] = "closed loop"
    # .npz: not a zip at all; a zip without our arrays
    p = tmp_path / "junk.npz"
    p.write_bytes(b"this is not a zip file" * 10)
    cases[p] = "not a zip archive"
    p = tmp_path / "other.npz"
    np.savez(p, a=np.zeros(3))
    cases[p] = "missing arrays"
    # .tfx: a version field that is not a version
    p = tmp_path / "ver.tfx"
    write_tfx(p, g.rest_positions.numpy(), version=float("nan"))
    cases[p] = "version"
    return cases


def test_corrupt_files_raise_value_error_naming_the_file_and_problem(tmp_path):
    for path, problem in _corrupt_cases(tmp_path).items():
        with pytest.raises(ValueError, match=problem) as err:
            read_groom(path)
        assert isinstance(err.value, GroomFileError)
        assert str(err.value).startswith(str(path)), str(err.value)


def test_corrupt_usd_raises_value_error(tmp_path):
    pytest.importorskip("pxr")
    p = tmp_path / "bad.usda"
    p.write_text("#usda 1.0\ndef BasisCurves \"c\" {\n  int[] curveVertexCounts = [3, 4\n")
    with pytest.raises(ValueError, match="bad.usda") as err:
        read_groom(p)
    assert "corrupt" in str(err.value)
    q = tmp_path / "empty.usda"
    q.write_text("#usda 1.0\ndef Xform \"x\" {\n}\n")
    with pytest.raises(ValueError, match="no BasisCurves"):
        read_groom(q)


def test_grown_groom_round_trips_with_binding(tmp_path):
    trimesh = pytest.importorskip("trimesh")
    from ams_torch.grooms.growth import grow
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=0.1)
    g = grow(mesh, region=None, strands=50, particles=8, seed=0, collide=False)
    write_groom(tmp_path / "g.npz", g)
    h = read_groom(tmp_path / "g.npz")
    assert torch.equal(h.rest_positions, g.rest_positions)
    assert torch.allclose(h.reattach(mesh.vertices * 2.0), g.reattach(mesh.vertices * 2.0))
    assert h.metadata["seed"] == 0 and h.metadata["params"]["spiral"] == 0.017


# ------------------------------------------------------------------------------------------
# import units, axes and transforms (SPEC §14)
# ------------------------------------------------------------------------------------------
def test_read_groom_units_up_axis_and_transform_in_that_order(tmp_path):
    g = uniform_groom(s=6, n=5, bound=False)
    write_groom(tmp_path / "g.data", g)
    x = g.rest_positions.numpy().astype(np.float64)
    cm = read_groom(tmp_path / "g.data", units="cm")
    np.testing.assert_array_equal(cm.rest_positions.numpy(), (x * 0.01).astype(np.float32))
    z = read_groom(tmp_path / "g.data", up_axis="z")  # (x, y, z) -> (x, z, -y)
    np.testing.assert_array_equal(z.rest_positions.numpy(), np.stack([x[..., 0], x[..., 2], -x[..., 1]], -1)
                                  .astype(np.float32))
    c, s_ = np.cos(0.3), np.sin(0.3)
    rot = np.array([[c, 0, s_], [0, 1, 0], [-s_, 0, c]])
    t = np.array([0.01, -0.02, 0.03])
    both = read_groom(tmp_path / "g.data", scale=0.5, up_axis="z", transform=(rot, t))
    expect = np.stack([x[..., 0], x[..., 2], -x[..., 1]], -1) * 0.5 @ rot.T + t
    np.testing.assert_allclose(both.rest_positions.numpy(), expect, atol=1e-7)
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = rot, t
    four = read_groom(tmp_path / "g.data", scale=0.5, up_axis="z", transform=m)
    assert torch.equal(four.rest_positions, both.rest_positions)
    table = read_groom(tmp_path / "g.data", scale=0.5, up_axis="z",
                       transform={"rotation": rot.tolist(), "translation": t.tolist()})  # as scene files give it
    assert torch.equal(table.rest_positions, both.rest_positions)
    np.testing.assert_allclose(np.asarray(four.metadata["import_transform"])[:3, 3], t)
    # lengths scale with the units, not with the rigid parts
    np.testing.assert_allclose(both.lengths(), 0.5 * g.lengths(), rtol=1e-5)


def test_import_keys_are_validated():
    from ams_torch.geometry.units import import_transform

    with pytest.raises(ValueError, match="units or scale, not both"):
        import_transform(units="cm", scale=0.01)
    with pytest.raises(ValueError, match=r"units must be one of \['cm', 'm', 'mm'\]; got 'inch'"):
        import_transform(units="inch")
    with pytest.raises(ValueError, match="scale must be a positive finite number; got -1"):
        import_transform(scale=-1)
    with pytest.raises(ValueError, match="up_axis must be 'y' or 'z'; got 'x'"):
        import_transform(up_axis="x")
    with pytest.raises(ValueError, match="reflection"):
        import_transform(transform=np.diag([1.0, 1.0, -1.0, 1.0]))
    with pytest.raises(ValueError, match="not orthonormal"):
        import_transform(transform=np.diag([2.0, 2.0, 2.0, 1.0]))
    with pytest.raises(ValueError, match=r"last row .* \[0, 0, 0, 1\]"):
        bad = np.eye(4)
        bad[3, 0] = 1.0
        import_transform(transform=bad)
    with pytest.raises(ValueError, match=r"4x4 matrix or a pair \(R \(3, 3\), t \(3,\)\); got shape \(3, 3\)"):
        import_transform(transform=np.eye(3))
    with pytest.raises(ValueError, match=r"unknown key\(s\) \['shift'\]"):
        import_transform(transform={"rotation": np.eye(3), "shift": [0, 0, 0]})
    # the tolerance follows the dtype: a float32 rotation is accepted at float32 precision
    c, s = np.float32(np.cos(0.7)), np.float32(np.sin(0.7))
    r32 = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=np.float32)
    import_transform(transform=(r32, np.zeros(3, np.float32)))
    with pytest.raises(ValueError, match="not orthonormal"):
        import_transform(transform=(r32.astype(np.float64), np.zeros(3)))
    z = import_transform(up_axis="z")
    assert np.linalg.det(z[:3, :3]) == pytest.approx(1.0) and np.array_equal(z[:3, :3] @ [0, 0, 1], [0, 1, 0])


def test_implausible_sizes_warn_with_the_measured_size(tmp_path):
    g = uniform_groom(s=4, n=8, bound=False)
    cm = Groom(rest_positions=g.rest_positions * 100 * 40)  # strands of metres in centimetres
    write_groom(tmp_path / "cm.data", cm)
    longest = float(cm.lengths().max())
    with pytest.warns(ImplausibleSizeWarning, match=rf"longest strand is {longest:.4g} m, more than 3 m"):
        read_groom(tmp_path / "cm.data")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        h = read_groom(tmp_path / "cm.data", units="cm")
    np.testing.assert_allclose(h.lengths().max(), longest * 0.01, rtol=1e-5)


def test_bin_directions_rotate_with_the_up_axis(tmp_path):
    g = uniform_groom(s=3, n=5, bound=False)
    write_groom(tmp_path / "a.bin", g)
    a = read_groom(tmp_path / "a.bin").metadata["bin_attributes"]
    b = read_groom(tmp_path / "a.bin", units="mm", up_axis="z").metadata["bin_attributes"]
    np.testing.assert_allclose(b[:, :3], np.stack([a[:, 0], a[:, 2], -a[:, 1]], 1), atol=1e-7)  # unit, unscaled
    np.testing.assert_array_equal(b[:, 3], a[:, 3])


# ------------------------------------------------------------------------------------------
# .hair: thickness in metres, LuxCore UVs, hostile counts
# ------------------------------------------------------------------------------------------
def test_hair_writes_the_groom_width_in_metres_and_reads_it_back(tmp_path):
    g = uniform_groom(s=5, n=6, bound=False)
    write_groom(tmp_path / "d.hair", g)
    d_thickness = struct.unpack_from("<f", (tmp_path / "d.hair").read_bytes(), 20)[0]
    assert d_thickness == np.float32(7e-5)  # 70 µm, not Yuksel's default of 1.0
    g.width = 5e-5
    write_groom(tmp_path / "w.hair", g)
    h = read_groom(tmp_path / "w.hair")
    assert h.width == pytest.approx(5e-5, rel=1e-6)
    assert read_groom(tmp_path / "w.hair", units="mm").width == pytest.approx(5e-8, rel=1e-6)
    # an implausible default thickness (Yuksel's 1.0) is not taken as a width
    raw = bytearray((tmp_path / "w.hair").read_bytes())
    raw[20:24] = struct.pack("<f", 1.0)
    (tmp_path / "one.hair").write_bytes(bytes(raw))
    one = read_groom(tmp_path / "one.hair")
    assert one.width == 7e-5 and one.metadata["hair_defaults"]["thickness"] == 1.0


def _luxcore_hair(path, strands, uv):
    """A .hair file with LuxCore's UV array (flag 32), written independently of the writer."""
    counts = [len(s) for s in strands]
    pts = np.concatenate(strands).astype("<f4")
    flags = 1 | 2 | 32
    header = struct.pack("<4sIIIIff3f88s", b"HAIR", len(strands), len(pts), flags, 0, 1e-4, 0.0, 1, 1, 1,
                         b"luxcore".ljust(88, b"\0"))
    segments = (np.array(counts, np.int64) - 1).astype("<u2").tobytes()
    path.write_bytes(header + segments + pts.tobytes() + np.asarray(uv, "<f4").tobytes())


def test_hair_luxcore_uv_flag_is_read_and_written_back(tmp_path):
    rng = np.random.default_rng(3)
    strands = [rng.normal(size=(n, 3)).astype(np.float32) * 0.01 for n in (3, 5, 4)]
    uv = rng.random((12, 2)).astype(np.float32)
    _luxcore_hair(tmp_path / "lux.hair", strands, uv)
    h = read_groom(tmp_path / "lux.hair")
    np.testing.assert_array_equal(h.metadata["hair_arrays"]["uv"], uv)
    for a, b in zip(h.strands, strands):
        np.testing.assert_array_equal(a, b)
    assert h.width == pytest.approx(1e-4)
    write_groom(tmp_path / "again.hair", h)
    raw = (tmp_path / "again.hair").read_bytes()
    assert struct.unpack_from("<I", raw, 12)[0] & 32
    np.testing.assert_array_equal(np.frombuffer(raw[-uv.nbytes:], "<f4").reshape(-1, 2), uv)
    np.testing.assert_array_equal(read_groom(tmp_path / "again.hair").metadata["hair_arrays"]["uv"], uv)


def test_hair_header_with_2_31_strands_fails_without_allocating(tmp_path):
    """The original reproduction: strand count 2³¹ made the reader allocate 16 GB (with and
    without a segments array)."""
    g = uniform_groom(s=4, n=6, bound=False)
    write_groom(tmp_path / "big.hair", g)
    raw = bytearray((tmp_path / "big.hair").read_bytes())
    raw[4:8] = struct.pack("<I", 2 ** 31)
    (tmp_path / "big.hair").write_bytes(bytes(raw))
    tracemalloc.start()
    try:
        with pytest.raises(GroomFileError, match=rf"says 2147483648 strands.*{len(raw)} bytes") as err:
            read_groom(tmp_path / "big.hair")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert str(err.value).startswith(str(tmp_path / "big.hair"))
    assert peak < 64 * len(raw) + (1 << 20), peak
    write_groom(tmp_path / "ragged.hair", ragged_groom())  # with a segments array
    raw = bytearray((tmp_path / "ragged.hair").read_bytes())
    raw[4:8] = struct.pack("<I", 2 ** 31)
    (tmp_path / "ragged.hair").write_bytes(bytes(raw))
    with pytest.raises(GroomFileError, match=rf"says 2147483648 strands and 111 points .* need 4294968756 bytes, "
                                             rf"but the file has {len(raw)} bytes"):
        read_groom(tmp_path / "ragged.hair")


# ------------------------------------------------------------------------------------------
# .tfx writing
# ------------------------------------------------------------------------------------------
def test_tfx_write_round_trip_and_pinned_flags(tmp_path):
    g = uniform_groom(s=9, n=16, bound=False)
    g.metadata["tfx_strand_uv"] = np.random.default_rng(0).random((9, 2)).astype(np.float32)
    assert write_groom(tmp_path / "a.tfx", g, num_pinned=3) == 16
    h = read_groom(tmp_path / "a.tfx")
    assert torch.equal(h.rest_positions, g.rest_positions)  # already 16 vertices: written exactly
    w = h.metadata["tfx_w"]
    assert np.all(w[:, :3] == 0) and np.all(w[:, 3:] == 1)
    np.testing.assert_array_equal(h.metadata["tfx_strand_uv"], g.metadata["tfx_strand_uv"])
    fields = struct.unpack_from("<f7I", (tmp_path / "a.tfx").read_bytes())
    assert fields == (4.0, 9, 16, 160, 160 + 9 * 16 * 16, 0, 0, 0)


def test_tfx_write_resamples_to_a_power_of_two(tmp_path):
    g = ragged_groom()  # 2 .. 64 points
    assert write_groom(tmp_path / "r.tfx", g) == 64  # next power of two of the longest, capped at 64
    h = read_groom(tmp_path / "r.tfx")
    assert h.rest_positions.shape == (6, 64, 3)
    np.testing.assert_allclose(h.lengths(), strand_lengths(g.strands), rtol=1e-5)
    np.testing.assert_array_equal(h.rest_positions[:, 0].numpy(), np.stack([s[0] for s in g.strands]))
    assert np.all(h.metadata["tfx_w"][:, :2] == 0) and np.all(h.metadata["tfx_w"][:, 2:] == 1)
    u = uniform_groom(s=3, n=12, bound=False)
    assert write_groom(tmp_path / "u.tfx", u) == 16
    assert write_groom(tmp_path / "e.tfx", u, vertices_per_strand=8) == 8
    for bad in (48, 128, 1):
        with pytest.raises(ValueError, match=rf"power-of-two number of vertices per strand, at most 64 .*got {bad}"):
            write_groom(tmp_path / "bad.tfx", u, vertices_per_strand=bad)
    with pytest.raises(ValueError, match=r"num_pinned must be an integer in \[0, 16\]"):
        write_groom(tmp_path / "bad.tfx", u, num_pinned=17)
    with pytest.raises(TypeError, match=r"unknown option\(s\) \['pinned'\]"):
        write_groom(tmp_path / "bad.tfx", u, pinned=2)


# ------------------------------------------------------------------------------------------
# USD: curve types and bases, wrap, widths, time samples, Z-up, corrupt text
# ------------------------------------------------------------------------------------------
def _usda(path, body, up="Y", mpu=None):
    meta = f'upAxis = "{up}"' + ("" if mpu is None else f"\n    metersPerUnit = {mpu}")
    path.write_text(f"#usda 1.0\n(\n    {meta}\n)\n\n{body}\n")
    return path


def _curves(points, counts, extra=""):
    pts = ", ".join(f"({float(a)!r}, {float(b)!r}, {float(c)!r})" for a, b, c in np.asarray(points, float))
    return (f'def BasisCurves "c"\n{{\n    int[] curveVertexCounts = {list(counts)}\n'
            f"    point3f[] points = [{pts}]\n{extra}\n}}")


def test_usd_cubic_bezier_is_evaluated_not_returned_as_control_points(tmp_path):
    pytest.importorskip("pxr")
    from ams_torch.grooms.io.usd import SPAN_SAMPLES

    # Bézier control points of (t, t³, 0), t in [0, 1]
    ctrl = [(0, 0, 0), (1 / 3, 0, 0), (2 / 3, 0, 0), (1, 1, 0)]
    p = _usda(tmp_path / "bez.usda", _curves(ctrl, [4], '    uniform token type = "cubic"\n'
                                              '    uniform token basis = "bezier"'))
    g = read_groom(p)
    t = np.arange(SPAN_SAMPLES + 1) / SPAN_SAMPLES
    np.testing.assert_allclose(g.rest_positions[0].numpy(), np.stack([t, t ** 3, 0 * t], 1), atol=1e-7)
    assert g.metadata["usd_curves"][0]["basis"] == "bezier"


def test_usd_bspline_matches_scipy_and_pinned_reaches_the_end_points(tmp_path):
    pytest.importorskip("pxr")
    from scipy.interpolate import BSpline

    from ams_torch.grooms.io.usd import SPAN_SAMPLES

    rng = np.random.default_rng(5)
    ctrl = rng.normal(size=(7, 3)) * 0.01
    body = _curves(ctrl, [7], '    uniform token type = "cubic"\n    uniform token basis = "bspline"')
    g = read_groom(_usda(tmp_path / "bs.usda", body))
    ref = BSpline(np.arange(11.0), ctrl, 3)(np.linspace(3.0, 7.0, 4 * SPAN_SAMPLES + 1))
    np.testing.assert_allclose(g.rest_positions[0].numpy(), ref, atol=1e-8)
    pinned = body.replace('basis = "bspline"', 'basis = "bspline"\n    uniform token wrap = "pinned"')
    h = read_groom(_usda(tmp_path / "pin.usda", pinned))
    np.testing.assert_allclose(h.rest_positions[0, 0].numpy(), ctrl[0], atol=1e-8)
    np.testing.assert_allclose(h.rest_positions[0, -1].numpy(), ctrl[-1], atol=1e-8)
    assert h.num_particles == 6 * SPAN_SAMPLES + 1
    cr = pinned.replace('"bspline"', '"catmullRom"')
    k = read_groom(_usda(tmp_path / "cr.usda", cr))
    np.testing.assert_allclose(k.rest_positions[0, ::SPAN_SAMPLES].numpy(), ctrl, atol=1e-8)  # interpolating


def test_usd_refuses_periodic_curves_and_unknown_bases(tmp_path):
    pytest.importorskip("pxr")
    ctrl = np.eye(3)[[0, 1, 2, 0, 1]] * 0.01
    lin = _curves(ctrl, [5], '    uniform token type = "linear"\n    uniform token wrap = "periodic"')
    with pytest.raises(GroomFileError, match="periodic \\(closed\\) curves are not read"):
        read_groom(_usda(tmp_path / "loop.usda", lin))
    herm = _curves(ctrl[:4], [4], '    uniform token type = "cubic"\n    uniform token basis = "hermite"')
    with pytest.raises(GroomFileError, match="basis 'hermite' are not supported"):
        read_groom(_usda(tmp_path / "herm.usda", herm))
    bez = _curves(ctrl, [5], '    uniform token type = "cubic"\n    uniform token basis = "bezier"')
    with pytest.raises(GroomFileError, match="curve 0: a nonperiodic bezier curve needs 4 \\+ 3k control points; got 5"):
        read_groom(_usda(tmp_path / "bez5.usda", bez))


def test_usd_widths_time_samples_z_up_and_units(tmp_path):
    pytest.importorskip("pxr")
    pts = np.array([[0, 0, 0], [0, 0, 10], [0, 1, 20], [5, 0, 0], [5, 0, 8]], float)  # cm, Z up
    sampled = ", ".join(f"({a}, {b}, {c})" for a, b, c in pts)
    body = ('def BasisCurves "c"\n{\n    uniform token type = "linear"\n    int[] curveVertexCounts = [3, 2]\n'
            f"    point3f[] points.timeSamples = {{\n        10: [{sampled}],\n        20: [{sampled.replace('5,', '6,')}],\n    }}\n"
            '    float[] widths = [0.004, 0.005, 0.006, 0.007, 0.008] (interpolation = "vertex")\n}')
    p = _usda(tmp_path / "zup.usda", body, up="Z", mpu=0.01)
    g = read_groom(p)
    expect = np.stack([pts[:, 0], pts[:, 2], -pts[:, 1]], 1) * 0.01  # first sample, +y up, metres
    got = np.concatenate(g.polylines())
    np.testing.assert_allclose(got, expect, atol=1e-7)
    assert g.metadata["usd_time"] == 10.0 and g.metadata["usd_up_axis"] == "Z"
    np.testing.assert_allclose(g.metadata["usd_widths"], [4e-5, 5e-5, 6e-5, 7e-5, 8e-5], rtol=1e-6)
    assert g.metadata["usd_widths_interpolation"] == "vertex" and g.width == pytest.approx(6e-5)
    with pytest.raises(ValueError, match="declares metersPerUnit = 0.01.*do not pass units"):
        read_groom(p, units="cm")
    with pytest.raises(ValueError, match="declares upAxis = Z.*do not pass up_axis='z'"):
        read_groom(p, up_axis="z")
    # written back: per-point widths survive, the stage says metres and Y up
    write_groom(tmp_path / "back.usda", g)
    h = read_groom(tmp_path / "back.usda")
    np.testing.assert_array_equal(np.concatenate(h.polylines()), got)
    np.testing.assert_array_equal(h.metadata["usd_widths"], g.metadata["usd_widths"])


def test_usd_width_round_trip(tmp_path):
    pytest.importorskip("pxr")
    g = uniform_groom(s=3, n=4, bound=False)
    g.width = 9e-5
    write_groom(tmp_path / "w.usdc", g)
    assert read_groom(tmp_path / "w.usdc").width == pytest.approx(9e-5)


def test_usda_with_flipped_bytes_is_a_groom_file_error(tmp_path):
    """The original reproduction: flipped bytes in a .usda gave a raw UnicodeDecodeError."""
    pytest.importorskip("pxr")
    g = uniform_groom(s=3, n=4, bound=False)
    write_groom(tmp_path / "ok.usda", g)
    raw = bytearray((tmp_path / "ok.usda").read_bytes())
    at = raw.index(b"points") + 2
    raw[at] ^= 0xFF
    raw[at + 1] ^= 0xFF
    (tmp_path / "flip.usda").write_bytes(bytes(raw))
    with pytest.raises(GroomFileError) as err:
        read_groom(tmp_path / "flip.usda")
    assert str(err.value).startswith(str(tmp_path / "flip.usda")) and "corrupt" in str(err.value)


def test_npz_is_stored_uncompressed_and_old_compressed_files_still_read(tmp_path):
    import zipfile

    g = uniform_groom(s=4, n=5)
    g.width = 6e-5
    write_groom(tmp_path / "new.npz", g)
    with zipfile.ZipFile(tmp_path / "new.npz") as z:
        assert {i.compress_type for i in z.infolist()} == {zipfile.ZIP_STORED}
    assert read_groom(tmp_path / "new.npz").width == pytest.approx(6e-5)
    pts = g.rest_positions.numpy().reshape(-1, 3)
    np.savez_compressed(tmp_path / "old.npz", format=np.array("ams_torch-groom-v1"), points=pts,
                        counts=np.full(4, 5, np.int64), metadata=np.array("{}"))
    old = read_groom(tmp_path / "old.npz")
    assert torch.equal(old.rest_positions, g.rest_positions) and old.width == 7e-5
    with pytest.raises(ValueError, match="Groom.width must be a positive finite number of metres; got -1"):
        Groom(rest_positions=g.rest_positions, width=-1)
