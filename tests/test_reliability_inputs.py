"""Input files that were misread or failed with a raw error (issue 28, items 13 and 14): TressFX
headers that do not describe their file, a groom .npz with negative counts, TOML with a byte-order
mark or nested thousands deep, degenerate head meshes, and the progress of a long SDF build."""
import os
import struct

import numpy as np
import pytest
import torch
import trimesh

from ams_torch.apps.recipe import RecipeError, load_recipe
from ams_torch.apps.scene import SceneError, load_scene
from ams_torch.geometry.mesh import load_mesh
from ams_torch.geometry.sdf import SDFGrid
from ams_torch.grooms.io import GroomFileError, read_groom
from ams_torch.grooms.io.npz import write_npz
from ams_torch.grooms.io.tressfx import read_tfx, write_tfx

RATBOY = "/work/shared/assets/Ratboy_mohawk.tfx"


def _tfx(tmp_path, strands=40, uv=True):
    rng = np.random.default_rng(0)
    curls = [np.cumsum(rng.normal(0, 0.01, (8, 3)), 0).astype(np.float32) for _ in range(strands)]
    meta = {"tfx_strand_uv": rng.uniform(0, 1, (strands, 2))} if uv else {}
    path = tmp_path / "hair.tfx"
    write_tfx(str(path), curls, meta)
    return path


def _patch(path, offset, value, name):
    data = bytearray(path.read_bytes())
    struct.pack_into("<I", data, offset, value)
    out = path.with_name(name)
    out.write_bytes(bytes(data))
    return out


def test_tressfx_with_a_lowered_strand_count_is_refused(tmp_path):
    """Item 13: numHairStrands lowered from 2228 to 1114 read half of Ratboy with no warning."""
    for uv in (True, False):
        path = _tfx(tmp_path, uv=uv)
        assert len(read_tfx(str(path))[0]) == 40
        low = _patch(path, 4, 20, f"low{uv}.tfx")
        with pytest.raises(GroomFileError, match=r"numHairStrands = 20 .* unread \(room for about 40 strands\)"):
            read_tfx(str(low))
    if os.path.isfile(RATBOY):
        strands, _ = read_tfx(RATBOY)
        assert len(strands) == 2228
        data = bytearray(open(RATBOY, "rb").read())
        struct.pack_into("<I", data, 4, 1114)
        (tmp_path / "ratboy_low.tfx").write_bytes(bytes(data))
        with pytest.raises(GroomFileError, match="room for about 2228 strands"):
            read_groom(str(tmp_path / "ratboy_low.tfx"))


def test_tressfx_optional_arrays_inside_the_header_or_overlapping_are_refused(tmp_path):
    """Item 13: an optional-array offset pointing into the header read header bytes as UVs."""
    path = _tfx(tmp_path)
    for offset, name in ((16, "offsetStrandUV"), (20, "offsetVertexUV"), (24, "offsetStrandThickness"),
                         (28, "offsetVertexColor")):
        bad = _patch(path, offset, 8, f"hdr{offset}.tfx")
        with pytest.raises(GroomFileError, match=f"{name} = 8 points into the 160-byte header"):
            read_tfx(str(bad))
    over = _patch(path, 24, 200, "overlap.tfx")  # thickness inside the positions
    with pytest.raises(GroomFileError, match="offsetVertexPosition .* and offsetStrandThickness .* overlap"):
        read_tfx(str(over))


def test_npz_with_a_negative_count_says_so(tmp_path):
    """Item 14: counts [-1, 5] with 4 points said "counts add up to 4 but there are 4 points"."""
    path = tmp_path / "g.npz"
    write_npz(str(path), [np.zeros((4, 3), np.float32)])
    with np.load(path) as z:
        arrays = dict(z)
    arrays["counts"] = np.array([-1, 5], np.int64)
    with open(path, "wb") as fh:
        np.savez(fh, **arrays)
    with pytest.raises(GroomFileError, match=r"strand 0 has a negative point count \(-1\)"):
        read_groom(str(path))


SCENE = 'frames = 2\n[head]\nmesh = "none"\n[groom]\nkind = "strand"\nstrands = 2\nparticles = 8\n'


def test_toml_with_a_byte_order_mark_or_deep_nesting(tmp_path):
    """Item 14: a UTF-8 BOM was "Invalid statement"; deep nesting a RecursionError traceback."""
    bom = tmp_path / "bom.toml"
    bom.write_bytes(b"\xef\xbb\xbf" + SCENE.encode())
    assert load_scene(str(bom))["groom"]["strands"] == 2
    for depth, said in ((100000, "nested too deeply"), (40, "nested more than 32 levels deep")):
        deep = tmp_path / f"deep{depth}.toml"
        deep.write_text("x = " + "[" * depth + "]" * depth + "\n")
        with pytest.raises(SceneError, match=said):
            load_scene(str(deep))
        with pytest.raises(RecipeError, match=said):
            load_recipe(str(deep))


def test_a_degenerate_head_mesh_is_named(tmp_path):
    """Item 14: a head mesh whose vertices are one point failed with "cannot convert float NaN to
    integer"."""
    for name, verts in (("point", [[0, 0, 0]] * 3), ("line", [[0, 0, 0], [0.1, 0, 0], [0.2, 0, 0]])):
        obj = tmp_path / f"{name}.obj"
        obj.write_text("".join(f"v {x} {y} {z}\n" for x, y, z in verts) + "f 1 2 3\n")
        with pytest.raises(ValueError, match=rf"{name}.obj: a degenerate mesh: every one of its 1 triangle\(s\) has zero area"):
            load_mesh(str(obj), units="m")
    point = trimesh.Trimesh(np.zeros((3, 3)), [[0, 1, 2]], process=False)
    with pytest.raises(ValueError, match="all its vertices are at one point"):
        SDFGrid.from_mesh(point, resolution=8, cache=False)


def test_a_long_sdf_build_shows_its_progress_and_computes_the_same(capsys, monkeypatch):
    """Item 14: a 1.3M-triangle mesh built its SDF for 560 s with no sign of progress. Long builds
    (faces × samples over PROGRESS_WORK) go in chunks under a bar; the values are the same."""
    from ams_torch.geometry import sdf

    mesh = trimesh.creation.icosphere(2, radius=0.1)
    quiet = SDFGrid.from_mesh(mesh, resolution=24, cache=False)
    assert "SDF" not in capsys.readouterr().err
    monkeypatch.setattr(sdf, "PROGRESS_WORK", 0)
    shown = SDFGrid.from_mesh(mesh, resolution=24, cache=False)
    err = capsys.readouterr().err
    assert "-triangle mesh (cached afterwards)" in err and "SDF" in err
    assert torch.equal(shown.values, quiet.values)
