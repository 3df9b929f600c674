"""The scene of a dataset sequence as the benchmark's samples carry it: the colliders (the head
first when it collides) rebuilt from what the dataset stores, and their world poses per frame.

:func:`sequence_colliders` rebuilds the colliders of a sequence once (mesh SDFs are cached per
file and scene); :func:`make_sample` turns a dataset item (a window, see
:class:`~ams_torch.apps.data.HairSequenceDataset` with ``guides=G``) into a protocol sample
(:mod:`baselines.protocol`).
"""
from __future__ import annotations

import hashlib
import json
from typing import Dict, List, Optional, Tuple

import torch

from ams_torch.geometry.pose import Pose

__all__ = ["sequence_colliders", "collider_poses", "make_sample", "clear_cache"]

_CACHE: Dict[tuple, Tuple[list, int]] = {}


def clear_cache() -> None:
    """Forget the colliders rebuilt so far (their SDF grids)."""
    _CACHE.clear()


def _head_collider(scene: dict, meshes: dict):
    import trimesh

    from ams_torch.stages.collide import MeshCollider, SphereCollider

    head = scene["head"]
    if not (head.get("collide", True) and scene["stages"].get("collisions", False)):
        return None
    if head["mesh"] == "sphere":
        return SphereCollider(radius=head["radius"], follow_head=True)
    stored = meshes["head"]
    if "vertices" not in stored:
        return None
    mesh = trimesh.Trimesh(stored["vertices"], stored["faces"], process=False)
    return MeshCollider(mesh, resolution=head.get("sdf_resolution", 64), follow_head=True)


def sequence_colliders(dataset, index: int, device=None, dtype=torch.float32) -> Tuple[list, int]:
    """The colliders of sequence ``index`` of ``dataset`` (a HairSequenceDataset) in their own
    frames, the head's first when the scene's head collides: ``(colliders, head_index)`` with
    ``head_index`` 0 or −1. Mesh SDFs are built once per (file, scene) and cached."""
    from ams_torch.apps.data import read_scene_meshes
    from ams_torch.apps.scene.schema import make_collider

    fi, name = dataset._slot(index)
    path = dataset.files[fi]
    text = str(dataset._file(fi)[name].attrs["scene"])
    key = (path, hashlib.sha256(text.encode()).hexdigest(), str(device), dtype)
    if key not in _CACHE:
        scene = json.loads(text)
        cols: List = []
        head = _head_collider(scene, read_scene_meshes(path, index))
        if head is not None:
            cols.append(head)
        if scene["stages"].get("collisions", False):
            cols += [make_collider(c) for c in scene.get("colliders", [])]
        built = []
        for c in cols:
            c = c.to(device=device or "cpu", dtype=dtype)
            if hasattr(c, "build"):
                c.build()
            built.append(c)
        _CACHE[key] = (built, 0 if head is not None else -1)
    return _CACHE[key]


def collider_poses(colliders: list, head_index: int, rotations: torch.Tensor, translations: torch.Tensor,
                   collider_rotations: Optional[torch.Tensor] = None,
                   collider_translations: Optional[torch.Tensor] = None) -> List[Pose]:
    """World poses (batch (T,)) of ``colliders``: the head pose (rotations (T, 3, 3), translations
    (T, 3) m) for the head collider, the stored world poses (T, C, 3, 3), (T, C, 3) for the scene's
    other colliders, in order."""
    out = []
    c = 0
    for i, _ in enumerate(colliders):
        if i == head_index:
            out.append(Pose(rotations, translations, check=False))
        else:
            if collider_rotations is None:
                raise ValueError("the sequence has colliders but no stored collider poses (collider_rotations)")
            out.append(Pose(collider_rotations[:, c], collider_translations[:, c], check=False))
            c += 1
    return out


def make_sample(item: dict, dataset, device=None, dtype=torch.float32) -> dict:
    """A protocol sample (:mod:`baselines.protocol`) from a dataset item of a HairSequenceDataset
    opened with ``guides=G``: the item's tensors moved to ``device``, plus ``colliders``,
    ``collider_poses``, ``head_collider`` and ``dt``. The dense target ``positions`` stays in the
    sample when the item has it (methods must not read it in ``predict``: the benchmark removes it
    before calling them)."""
    dev = torch.device(device or "cpu")
    out = {k: (v.to(dev, dtype) if isinstance(v, torch.Tensor) and v.is_floating_point() else
               v.to(dev) if isinstance(v, torch.Tensor) else v) for k, v in item.items()}
    cols, head = sequence_colliders(dataset, int(item["sequence"]), device=dev, dtype=dtype)
    out["colliders"], out["head_collider"] = cols, head
    out["collider_poses"] = collider_poses(cols, head, out["rotations"], out["translations"],
                                           out.get("collider_rotations"), out.get("collider_translations"))
    out["dt"] = float(dataset.sequence_arrays(int(item["sequence"]))["dt"])
    return out
