"""Loading triangle meshes (heads, collision bodies) for colliders and growth."""
from __future__ import annotations

import logging
import os
from typing import Union

import trimesh

__all__ = ["load_mesh"]

log = logging.getLogger(__name__)


def load_mesh(path: Union[str, os.PathLike], repair: bool = False) -> trimesh.Trimesh:
    """Load a triangle mesh (any format trimesh reads; scenes are concatenated), units as stored.

    The collision SDF needs a closed surface: a mesh that is not watertight raises ``ValueError``
    naming the file, unless ``repair=True``, which merges duplicate vertices, fixes winding and
    normals, fills holes, and logs a warning (and still raises if that does not close it).
    """
    path = os.fspath(path)
    loaded = trimesh.load(path, force="mesh", process=True)
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise ValueError(f"{path}: no triangle mesh found")
    mesh = loaded
    if mesh.is_watertight and mesh.is_winding_consistent:
        if mesh.volume < 0:
            mesh.invert()
        return mesh
    if not repair:
        raise ValueError(
            f"{path}: mesh is not watertight ({len(mesh.faces)} faces, "
            f"{int(len(trimesh.grouping.group_rows(mesh.edges_sorted, require_count=1)))} boundary edges); "
            "collisions need a closed surface. Pass repair=True to try to fix it."
        )
    log.warning("%s: mesh is not watertight; repairing (merge vertices, fix winding, fill holes)", path)
    mesh.merge_vertices()
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.update_faces(mesh.unique_faces())
    mesh.remove_unreferenced_vertices()
    trimesh.repair.fix_winding(mesh)
    trimesh.repair.fill_holes(mesh)
    trimesh.repair.fix_normals(mesh)
    if not mesh.is_watertight:
        raise ValueError(f"{path}: mesh is not watertight and repair could not close it")
    if mesh.volume < 0:
        mesh.invert()
    return mesh
