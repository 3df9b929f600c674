"""Groom file formats: round trips, ragged strands, and clear errors on broken files."""
import struct

import numpy as np
import pytest
import torch

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
    with pytest.raises(ValueError, match="read only"):
        write_groom(tmp_path / "b.tfx", h)


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
    cases[p] = "header says 25"
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
    g.save(tmp_path / "g.npz")
    h = Groom.load(tmp_path / "g.npz")
    assert torch.equal(h.rest_positions, g.rest_positions)
    assert torch.allclose(h.reattach(mesh.vertices * 2.0), g.reattach(mesh.vertices * 2.0))
    assert h.metadata["seed"] == 0 and h.metadata["params"]["spiral"] == 0.017
