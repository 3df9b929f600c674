"""Loading triangle meshes (heads, collision bodies) for colliders, growth and root binding.

:func:`load_mesh` reads any format trimesh reads (OBJ, PLY, STL, GLB, OFF ...; scenes are
concatenated) and TressFX collision meshes (``.tfxmesh``, read here), checks them, and brings
them into the library frame (metres, +y up) with the import keys of
:mod:`ams_torch.geometry.units` (``units``/``scale``, ``up_axis``, ``transform``, in that order).

Meshes need not be closed: real heads are open at the neck, have separate eyes and a few
flipped triangles. The collision SDF (:meth:`ams_torch.geometry.sdf.SDFGrid.from_mesh`) takes
inside/outside from the generalised winding number after orienting every connected part
consistently, which is robust to all three.
"""
from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Optional, Union

import numpy as np
import trimesh

from ams_torch.geometry.units import MAX_MESH_WIDTH, apply_transform, check_plausible_size, import_transform

__all__ = ["load_mesh", "read_tfxmesh", "check_mesh_arrays", "closest_points", "mesh_width"]

log = logging.getLogger(__name__)


def check_mesh_arrays(path: str, vertices: np.ndarray, faces: np.ndarray) -> None:
    """Raise ``ValueError`` naming ``path`` unless vertices (V, 3) are finite, faces (F, 3) a
    non-empty array of indices in [0, V), and at least one triangle has a non-zero area."""
    v = np.asarray(vertices)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"{path}: mesh vertices must be (V, 3); got shape {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise ValueError(f"{path}: no triangle faces found (faces shape {f.shape}); a mesh needs at least one "
                         "triangle")
    bad = ~np.isfinite(v).all(1)
    if bad.any():
        raise ValueError(f"{path}: {int(bad.sum())} of {len(v)} vertices have NaN/Inf coordinates (first: vertex "
                         f"{int(np.flatnonzero(bad)[0])})")
    lo, hi = int(f.min()), int(f.max())
    if lo < 0 or hi >= len(v):
        row = int(np.flatnonzero((f < 0).any(1) | (f >= len(v)).any(1))[0])
        raise ValueError(f"{path}: face {row} refers to vertex {int(f[row][(f[row] < 0) | (f[row] >= len(v))][0])}, "
                         f"outside [0, {len(v)}) (face indices out of range)")
    tri = v.astype(np.float64)[f]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    if not (area > 0).any():
        extent = float(np.ptp(v.astype(np.float64)[np.unique(f)], axis=0).max())
        raise ValueError(f"{path}: a degenerate mesh: every one of its {len(f)} triangle(s) has zero area (its used "
                         f"vertices span {extent:.3g} along their longest side); a head or collider needs a surface")


def closest_points(mesh, points):
    """Closest points of a triangle mesh to query points (point-cloud-utils' AABB tree).

    mesh: anything with ``vertices`` (V, 3) and ``faces`` (F, 3), metres; points: (P, 3) metres.
    Returns ``(distance (P,) float64 metres, face (P,) int64, barycentric (P, 3) float64,
    closest (P, 3) float64 metres)``. Raises ``TypeError``/``ValueError`` for a bad mesh.
    """
    try:
        import point_cloud_utils as pcu
    except ImportError as err:  # pragma: no cover - dependency missing
        raise ImportError("closest_points needs point-cloud-utils: pip install point-cloud-utils") from err
    if not (hasattr(mesh, "vertices") and hasattr(mesh, "faces")):
        raise TypeError(f"need a mesh with vertices and faces (e.g. trimesh.Trimesh); got {type(mesh).__name__}")
    name = str(getattr(mesh, "metadata", {}).get("source") or "mesh")
    v = np.ascontiguousarray(np.asarray(mesh.vertices, dtype=np.float64))
    f = np.ascontiguousarray(np.asarray(mesh.faces, dtype=np.int64))
    check_mesh_arrays(name, v, f)
    p = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
    if len(p) == 0:
        return np.zeros(0), np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3))
    dist, fid, bary = pcu.closest_points_on_mesh(p, v, f)
    dist, fid, bary = np.atleast_1d(dist), np.atleast_1d(fid).astype(np.int64), np.atleast_2d(bary)
    closest = np.einsum("pk,pkd->pd", bary, v[f[fid]])
    return dist.astype(np.float64), fid, bary.astype(np.float64), closest


def mesh_width(vertices: np.ndarray) -> float:
    """Horizontal width of a +y-up mesh, metres: the larger of its x and z extents (the height
    is not counted, so a full body is not "too wide")."""
    v = np.asarray(vertices, dtype=np.float64)
    ext = v.max(0) - v.min(0)
    return float(max(ext[0], ext[2]))


# --------------------------------------------------------------------------------------------
# TressFX .tfxmesh
# --------------------------------------------------------------------------------------------
def _tfx_fail(path, problem: str) -> ValueError:
    return ValueError(f"{path}: {problem}")


def _numbers(path, lines, first: int, count: int, width: int, section: str, line_no) -> np.ndarray:
    """(count, width) float64 from ``count`` lines of ``width`` numbers each."""
    block = lines[first:first + count]
    tokens = [ln.split() for ln in block]
    for k, tok in enumerate(tokens):
        if len(tok) != width:
            raise _tfx_fail(path, f"corrupt .tfxmesh file: line {line_no[first + k]} of the {section} block has "
                                  f"{len(tok)} values, expected {width}")
    try:
        return np.array([t for tok in tokens for t in tok], dtype=np.float64).reshape(count, width)
    except ValueError:
        for k, tok in enumerate(tokens):
            try:
                np.array(tok, dtype=np.float64)
            except ValueError:
                raise _tfx_fail(path, f"corrupt .tfxmesh file: non-numeric value on line {line_no[first + k]} "
                                      f"({section} block)") from None
        raise


def read_tfxmesh(path) -> trimesh.Trimesh:
    """Read a TressFX collision mesh (``.tfxmesh``, text) as stored (no unit or axis change).

    Layout (comment lines start with ``#``)::

        numOfBones B       then B lines:  index name
        numOfVertices V    then V lines:  index x y z nx ny nz j0 j1 j2 j3 w0 w1 w2 w3
        numOfTriangles T   then T lines:  index i j k

    Returns a ``trimesh.Trimesh`` built with ``process=False`` (vertex order and count as in
    the file, so bone data and vertex indices line up), with ``metadata``: ``tfx_bones`` (list
    of B bone names), ``tfx_bone_indices`` (V, 4) int64, ``tfx_bone_weights`` (V, 4) float32,
    ``tfx_normals`` (V, 3) float32. The skinning data is kept but **not simulated**: the mesh
    moves rigidly with its pose.

    Raises:
        ValueError naming the file: not UTF-8 text, a missing section, a count larger than
        the lines present, a line with the wrong number of values, non-numeric values, vertex
        indices out of range, NaN coordinates.
    """
    path = os.fspath(path)
    with open(path, "rb") as fh:
        raw = fh.read()
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as err:
        raise _tfx_fail(path, f"not a text .tfxmesh file: byte {err.start} (0x{raw[err.start]:02x}) is not UTF-8 "
                              "text (corrupt or binary file)") from None
    lines, line_no = [], []
    for k, ln in enumerate(text.splitlines(), 1):
        s = ln.strip()
        if s and not s.startswith("#"):
            lines.append(s)
            line_no.append(k)
    sections = {}
    i = 0
    while i < len(lines):
        tok = lines[i].split()
        key = tok[0]
        if key not in ("numOfBones", "numOfVertices", "numOfTriangles"):
            raise _tfx_fail(path, f"corrupt .tfxmesh file: line {line_no[i]} ({lines[i][:60]!r}) is not a section "
                                  "header (numOfBones/numOfVertices/numOfTriangles)")
        if key in sections:
            raise _tfx_fail(path, f"corrupt .tfxmesh file: section {key} appears twice (line {line_no[i]})")
        if len(tok) != 2 or not tok[1].isdigit():
            raise _tfx_fail(path, f"corrupt .tfxmesh file: line {line_no[i]}: {key} needs one non-negative integer "
                                  f"count; got {lines[i][:60]!r}")
        n = int(tok[1])
        left = len(lines) - i - 1
        if n > left:
            raise _tfx_fail(path, f"truncated or corrupt .tfxmesh file: {key} {n} (line {line_no[i]}) but only "
                                  f"{left} data lines follow")
        sections[key] = (i + 1, n)
        # a section's data ends where its count says
        i += 1 + n
    for key in ("numOfVertices", "numOfTriangles"):
        if key not in sections:
            raise _tfx_fail(path, f"not a .tfxmesh file or truncated: no {key} section")
    bones = []
    if "numOfBones" in sections:
        first, n = sections["numOfBones"]
        for k in range(n):
            tok = lines[first + k].split(None, 1)
            if len(tok) != 2 or tok[0] != str(k):
                raise _tfx_fail(path, f"corrupt .tfxmesh file: line {line_no[first + k]} should be bone {k} "
                                      f"('{k} name'); got {lines[first + k][:60]!r}")
            bones.append(tok[1])
    first, nv = sections["numOfVertices"]
    vert = _numbers(path, lines, first, nv, 15, "numOfVertices", line_no)
    first_t, nt = sections["numOfTriangles"]
    tri = _numbers(path, lines, first_t, nt, 4, "numOfTriangles", line_no)
    for name, block, n in (("vertex", vert, nv), ("triangle", tri, nt)):
        bad = np.flatnonzero(block[:, 0] != np.arange(n))
        if len(bad):
            raise _tfx_fail(path, f"corrupt .tfxmesh file: {name} line {int(bad[0])} carries index "
                                  f"{block[int(bad[0]), 0]:g} (the indices must count 0, 1, 2 ...)")
    joints = vert[:, 7:11]
    if not np.all(joints == np.round(joints)) or (len(joints) and joints.min() < 0) or \
            (bones and len(joints) and joints.max() >= len(bones)):
        raise _tfx_fail(path, f"corrupt .tfxmesh file: vertex bone indices must be integers in [0, {len(bones)})")
    faces = tri[:, 1:]
    if not np.all(faces == np.round(faces)):
        raise _tfx_fail(path, "corrupt .tfxmesh file: triangle vertex indices must be integers")
    faces = faces.astype(np.int64)
    vertices = vert[:, 1:4]
    check_mesh_arrays(path, vertices, faces)
    normals = vert[:, 4:7]
    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
    mesh.metadata.update(
        name=Path(path).stem,
        tfx_bones=bones,
        tfx_bone_indices=joints.astype(np.int64),
        tfx_bone_weights=vert[:, 11:15].astype(np.float32),
        tfx_normals=normals.astype(np.float32),
    )
    return mesh


# --------------------------------------------------------------------------------------------
# load_mesh
# --------------------------------------------------------------------------------------------
def _read_any(path: str) -> trimesh.Trimesh:
    try:
        loaded = trimesh.load(path, force="mesh", process=False)
    except IndexError as err:
        raise ValueError(f"{path}: corrupt mesh: a face index is out of range ({err})") from None
    except UnicodeDecodeError as err:
        raise ValueError(f"{path}: corrupt mesh: byte {err.start} is not valid text ({err.reason})") from None
    except Exception as err:  # noqa: BLE001 - trimesh raises many types on bad input; name the file
        raise ValueError(f"{path}: cannot read the mesh ({type(err).__name__}: {err})") from None
    if not isinstance(loaded, trimesh.Trimesh):
        raise ValueError(f"{path}: no triangle mesh found (trimesh loaded a {type(loaded).__name__})")
    check_mesh_arrays(path, loaded.vertices, loaded.faces)
    loaded.process()  # merge duplicate vertices (as trimesh's default load does)
    return loaded


def _repair(mesh: trimesh.Trimesh, path: str) -> None:
    holes_before = len(trimesh.grouping.group_rows(mesh.edges_sorted, require_count=1))
    mesh.merge_vertices()
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.update_faces(mesh.unique_faces())
    mesh.remove_unreferenced_vertices()
    trimesh.repair.fix_winding(mesh)
    trimesh.repair.fill_holes(mesh)
    trimesh.repair.fix_normals(mesh)
    if mesh.is_watertight:
        log.info("%s: repaired (merged vertices, fixed winding, closed %d boundary edges)", path, holes_before)
    else:
        open_edges = len(trimesh.grouping.group_rows(mesh.edges_sorted, require_count=1))
        log.warning("%s: repaired (merged vertices, fixed winding and normals); %d boundary edges stay open "
                    "(fine for collisions: the SDF sign comes from the winding number)", path, open_edges)


def load_mesh(path: Union[str, os.PathLike], *, units: Optional[str] = None, scale: Optional[float] = None,
              up_axis: str = "y", transform=None, repair: bool = False) -> trimesh.Trimesh:
    """Load a triangle mesh into the library frame (metres, +y up).

    Args:
        path: mesh file: any format trimesh reads, or a TressFX ``.tfxmesh`` (see
            :func:`read_tfxmesh`; vertex order kept, bone data in ``metadata``).
        units, scale, up_axis, transform: the import keys of
            :func:`ams_torch.geometry.units.import_transform` (scale → up axis → rigid
            transform). Defaults: the file is in metres, +y up.
        repair: optional clean-up: merge duplicate vertices, drop degenerate/duplicate faces,
            make the winding consistent, fill the holes trimesh can fill, fix normals. Holes
            that stay open are logged, not an error (open meshes are fine for collisions).
            It renumbers vertices, so a ``.tfxmesh``'s per-vertex bone data is dropped.

    Returns:
        ``trimesh.Trimesh`` in metres, +y up. Open meshes are returned as they are; a closed,
        consistently wound mesh is oriented outward (positive volume). ``metadata`` gains
        ``source`` (the path) and ``import_transform`` ((4, 4) list); for ``.tfxmesh`` also
        ``tfx_bones``, ``tfx_bone_indices``, ``tfx_bone_weights``, ``tfx_normals`` (rotated
        with the mesh).

    Warns:
        :class:`~ams_torch.geometry.units.ImplausibleSizeWarning` when the mesh is wider than
        1 m (the larger of its x and z extents after import): probably not metres.

    Raises:
        FileNotFoundError: no such file. ValueError naming the file: unreadable or corrupt,
        no faces, NaN/Inf vertices, face indices out of range, bad import keys.
    """
    path = os.fspath(path)
    matrix = import_transform(units=units, scale=scale, up_axis=up_axis, transform=transform)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"{path}: no such mesh file")
    if Path(path).suffix.lower() == ".tfxmesh":
        mesh = read_tfxmesh(path)
    else:
        mesh = _read_any(path)
    if repair:
        per_vertex = [k for k in ("tfx_bone_indices", "tfx_bone_weights", "tfx_normals") if k in mesh.metadata]
        _repair(mesh, path)
        if per_vertex:  # merging vertices breaks the one-row-per-file-vertex layout
            for k in per_vertex:
                del mesh.metadata[k]
            log.warning("%s: repair=True renumbers the vertices; the per-vertex bone data was dropped", path)
    elif mesh.is_watertight and mesh.is_winding_consistent and mesh.volume < 0:
        mesh.invert()
    if not np.array_equal(matrix, np.eye(4)):
        mesh.apply_transform(matrix)
        if "tfx_normals" in mesh.metadata:
            mesh.metadata["tfx_normals"] = apply_transform(mesh.metadata["tfx_normals"], matrix, direction=True)
    mesh.metadata["source"] = path
    mesh.metadata["import_transform"] = matrix.tolist()
    check_plausible_size("mesh width (max of x and z extents)", mesh_width(mesh.vertices), MAX_MESH_WIDTH,
                         source=path)
    return mesh
