"""Writing a batch group's sequences (arrays, per-array and per-frame checksums, units and dims,
the scene's meshes) and assembling a shard file from its groups; layout: docs/dataset_format.md."""
from __future__ import annotations

import hashlib
import json
import os
from typing import Callable, List, Optional

import numpy as np
import torch

from ams_torch import __version__
from ams_torch.apps.atomic import check_writes, h5_file
from ams_torch.apps.data import (FORMAT, FORMAT_VERSION, FRAME_DIGESTS, POSE_FIELDS, SPLITS, array_digest,
                                 sequence_checksum, sequence_name)
from ams_torch.apps.data.format import alone_name, array_info
from ams_torch.apps.data.metadata import ATTRS_DIGEST, attrs_digest
from ams_torch.apps.datagen.simulate import guide_order, simulate_group
from ams_torch.apps.recipe import Recipe

__all__ = ["write_group", "copy_groups", "atomic_write"]


# -- writing ------------------------------------------------------------------------------------
def _json(v) -> str:
    return json.dumps(v, sort_keys=True, default=str)


def _labelled(d, name: str, digest: Optional[str] = None) -> None:
    """The ``units``, ``dims`` (and ``sha256``) attributes of a stored array."""
    d.attrs["units"], d.attrs["dims"] = array_info(name)
    if digest is not None:
        d.attrs["sha256"] = digest


class _SequenceWriter:
    """Writes one sequence group incrementally (frame by frame) with its checksums."""

    def __init__(self, h5, recipe: Recipe, spec: dict, strands: int, particles: int, guide_idx, colliders: int):
        st = recipe.store
        self.g = h5.create_group(sequence_name(spec["index"]))
        self.prec = np.float16 if st["precision"] == "float16" else np.float32
        self.guides = guide_idx
        self.digests, self.hashers, self.frame_digests = {}, {}, {}
        filters = {} if st["compression"] == "none" else {
            "compression": st["compression"], "shuffle": True,
            **({"compression_opts": st["compression_level"]} if st["compression"] == "gzip" else {})}
        shapes = {"positions": (strands, particles, 3), "velocities": (strands, particles, 3),
                  "motion_velocities": (strands, particles, 3),
                  "guide_positions": (0 if guide_idx is None else len(guide_idx), particles, 3),
                  **{alone_name(g): (g, particles, 3) for g in recipe.alone_counts}}
        self.framed = [k for k, on in (("positions", st["positions"]), ("velocities", st["velocities"]),
                                       ("motion_velocities", st["motion_velocities"]),
                                       ("guide_positions", guide_idx is not None)) if on]
        self.framed += [alone_name(g) for g in recipe.alone_counts]
        f = recipe.frames
        for name in self.framed:
            d = self.g.create_dataset(name, shape=(f,) + shapes[name], dtype=self.prec, chunks=(1,) + shapes[name],
                                      fletcher32=True, **filters)
            _labelled(d, name)
            self.hashers[name] = hashlib.sha256()
            self.frame_digests[name] = np.zeros((f, 32), np.uint8)
        small = {k: (f, 3, 3) if k == "rotations" else (f, 3) for k in POSE_FIELDS} if st["poses"] else {}
        if colliders:
            small.update(collider_rotations=(f, colliders, 3, 3), collider_translations=(f, colliders, 3))
        self.small = {k: np.zeros(shape, np.float32) for k, shape in small.items()}

    def frame(self, k: int, x: np.ndarray, v: Optional[np.ndarray], small: dict,
              motion_v: Optional[np.ndarray] = None) -> None:
        """x, v: (S, N, 3) float32 (m, m/s); small: this frame's head pose (rotation (3, 3),
        translation (3,), velocities (3,)) and collider poses ((C, 3, 3), (C, 3)); motion_v:
        (S, N, 3) m/s, the velocity the positions imply over frame k (stored when asked)."""
        arrays = {"positions": x, "velocities": v, "motion_velocities": motion_v,
                  "guide_positions": None if self.guides is None else x[self.guides]}
        for name in self.framed:
            if name in arrays:
                self._put(name, k, arrays[name])
        for name, buf in self.small.items():
            buf[k] = small[name]

    def guides_frame(self, k: int, alone: dict) -> None:
        """alone: {G: (G, N, 3) float32 m}, frame k of the first G guides simulated alone."""
        for g, x in alone.items():
            self._put(alone_name(g), k, x)

    def _put(self, name: str, k: int, array: np.ndarray) -> None:
        a = np.ascontiguousarray(array.astype(self.prec))
        self.g[name][k] = a
        self.hashers[name].update(a.tobytes())
        self.frame_digests[name][k] = np.frombuffer(hashlib.sha256(a.tobytes()).digest(), np.uint8)

    def static(self, name: str, array: np.ndarray) -> None:
        a = np.ascontiguousarray(array)
        self.digests[name] = (a.dtype.str, a.shape, array_digest([a]))
        _labelled(self.g.create_dataset(name, data=a), name, self.digests[name][2])

    def finish(self, attrs: dict) -> None:
        for name, buf in self.small.items():
            self.static(name, buf)
        for name, h in self.hashers.items():
            d = self.g[name]
            self.digests[name] = (d.dtype.str, d.shape, h.hexdigest())
            d.attrs["sha256"] = h.hexdigest()
            self.g.create_dataset(f"{FRAME_DIGESTS}/{name}", data=self.frame_digests[name])
        for k, val in attrs.items():
            self.g.attrs[k] = val
        self.g.attrs["checksum"] = sequence_checksum(self.digests)
        self.g.attrs[ATTRS_DIGEST] = attrs_digest(self.g.attrs)  # last: covers every attribute above


def _collider_mesh(c: dict):
    """A tessellation (trimesh) of an analytic collider in its own frame, for pictures and for
    reading the scene back; the simulation uses the exact signed distance."""
    import trimesh

    kind = c["type"]
    if kind == "sphere":
        return trimesh.creation.icosphere(3, radius=c.get("radius", 0.1)).apply_translation(c.get("center", (0, 0, 0)))
    if kind == "capsule":
        a, b = np.asarray(c.get("a", (0, 0, 0)), float), np.asarray(c.get("b", (0, 0.1, 0)), float)
        m = trimesh.creation.capsule(height=float(np.linalg.norm(b - a)), radius=c.get("radius", 0.05), count=[16, 16])
        m.apply_transform(trimesh.geometry.align_vectors([0, 0, 1], (b - a) if np.any(b != a) else [0, 0, 1]))
        return m.apply_translation((a + b) / 2)
    if kind == "plane":
        m = trimesh.creation.box(extents=(2.0, 1e-3, 2.0))  # 2 m x 2 m of the infinite plane
        m.apply_transform(trimesh.geometry.align_vectors([0, 1, 0], c.get("normal", (0, 1, 0))))
        return m.apply_translation(c.get("point", (0, 0, 0)))
    r, t = c.get("radius", 0.2), c.get("thickness", 0.02)
    outer, inner = trimesh.creation.icosphere(3, radius=r + t / 2), trimesh.creation.icosphere(3, radius=r - t / 2)
    inner.invert()
    m = trimesh.util.concatenate([outer, inner])
    axis = np.asarray(c.get("axis", (0, 1, 0)), float)
    if c.get("cut_height", 0.1) is not None:
        m.update_faces(m.triangles_center @ (axis / np.linalg.norm(axis)) <= c.get("cut_height", 0.1))
        m.remove_unreferenced_vertices()
    return m.apply_translation(c.get("center", (0, 0, 0)))


def _mesh_group(g, mesh, **attrs) -> None:
    for k, v in attrs.items():
        g.attrs[k] = v
    g.attrs["units"] = "m"
    if mesh is not None:
        for name, a in (("vertices", np.asarray(mesh.vertices, np.float32)), ("faces", np.asarray(mesh.faces, np.int64))):
            _labelled(g.create_dataset(name, data=a), name, array_digest([a]))


def _write_scene(h5, run) -> None:
    """``/scene``: the head (its mesh, or the sphere and its tessellation) and each collider's
    parameters and tessellation, so a dataset file describes the scene that produced it."""
    head = run.scene["head"]
    g = h5.create_group("scene/head")
    if head["mesh"] == "sphere":
        import trimesh

        _mesh_group(g, trimesh.creation.icosphere(3, radius=head["radius"]), type="sphere", radius=head["radius"],
                    center=np.zeros(3))
    else:
        _mesh_group(g, run.head_mesh, type="mesh" if run.head_mesh is not None else "none", source=head["mesh"])
    g.attrs["collide"] = bool(head["collide"] and run.scene["stages"]["collisions"])
    for i, c in enumerate(run.scene["colliders"]):
        params = {k: v for k, v in c.items() if k not in ("type", "motion")}
        _mesh_group(h5.create_group(f"scene/colliders/{i:02d}"), _collider_mesh(c), type=c["type"],
                    params=_json(params), motion=_json(c.get("motion")),
                    **{k: np.asarray(v, np.float64) for k, v in params.items() if not isinstance(v, bool)})


def _collider_poses(run, t: float, head) -> tuple:
    """World rotations (B, C, 3, 3) and translations (B, C, 3) m of the scene's [[colliders]] at t."""
    specs = run.scene["colliders"]
    motions = run.collider_motions[len(run.collider_motions) - len(specs):]
    hr, ht = head.rotation.detach().cpu().double().numpy(), head.translation.detach().cpu().double().numpy()
    rots, trans = np.zeros(hr.shape[:1] + (len(specs), 3, 3)), np.zeros(hr.shape[:1] + (len(specs), 3))
    for i, (spec, m) in enumerate(zip(specs, motions)):
        p = m(t, dtype=torch.float64) if m is not None else None
        r, tr = (p.rotation.numpy(), p.translation.numpy()) if p is not None else (np.eye(3), np.zeros(3))
        if spec.get("follow_head", False):
            rots[:, i], trans[:, i] = hr @ r, hr @ tr + ht
        else:
            rots[:, i], trans[:, i] = r, tr
    return rots, trans


def _write_group_file(recipe: Recipe, group: int, tmp: str, device=None) -> float:
    """Simulate batch group ``group`` into the HDF5 file ``tmp``. Returns ms/frame."""
    writers: List[_SequenceWriter] = []
    guides, keep_v = max(recipe.guide_counts, default=0), recipe.store["velocities"]
    keep_mv = recipe.store["motion_velocities"]
    holder = {}
    with h5_file(tmp) as h5:  # a full disk is one OSError, not a crash of the HDF5 library
        def on_start(run, specs):
            holder["run"] = run
            rest = run.sim.model.rest_positions
            gidx = guide_order(run, guides) if guides else None
            writers.extend(_SequenceWriter(h5, recipe, spec, rest.shape[0], rest.shape[1], gidx,
                                           len(run.scene["colliders"])) for spec in specs)

        def on_initial(state):
            holder["x"] = state.x.detach().clone()

        def on_guides(k, states):
            xs = {g: st.x.detach().to("cpu", torch.float32).numpy() for g, st in states.items()}
            for b, w in enumerate(writers):
                w.guides_frame(k, {g: x[b] for g, x in xs.items()})

        def on_frame(k, state):
            x = state.x.detach().to("cpu", torch.float32).numpy()
            v = state.v.detach().to("cpu", torch.float32).numpy() if keep_v else None
            mv = None
            if keep_mv:  # backward difference over frame k, in the simulation's precision: (x_k − x_{k−1}) / dt
                mv = ((state.x.detach() - holder["x"]) / holder["run"].sim.params.dt).to("cpu", torch.float32).numpy()
                holder["x"] = state.x.detach().clone()
            p = state.pose
            small = {"rotations": p.rotation, "translations": p.translation, "linear_velocities": p.linear_velocity,
                     "angular_velocities": p.angular_velocity}
            small = {n: t.detach().to("cpu", torch.float32).numpy() for n, t in small.items()}
            if holder["run"].scene["colliders"]:
                small["collider_rotations"], small["collider_translations"] = \
                    _collider_poses(holder["run"], (k + 1) * holder["run"].sim.params.dt, p)
            for b, w in enumerate(writers):
                w.frame(k, x[b], None if v is None else v[b], {n: a[b] for n, a in small.items()},
                        None if mv is None else mv[b])
            check_writes(h5)  # stop at the frame a write failed

        out = simulate_group(recipe, group, device=device, on_frame=on_frame, on_start=on_start, on_guides=on_guides,
                             on_initial=on_initial)
        run = out["run"]
        rest = run.sim.model.rest_positions.detach().cpu().float().numpy()
        for w, spec in zip(writers, out["specs"]):
            w.static("rest_positions", rest)
            if run.groom is not None and run.groom.root_triangles is not None:
                w.static("root_triangles", run.groom.root_triangles.numpy().astype(np.int64))
                w.static("root_barycentrics", run.groom.root_barycentrics.numpy().astype(np.float32))
            if w.guides is not None:
                w.static("guide_indices", np.asarray(w.guides, dtype=np.int64))
            w.static("num_pinned", run.sim.model.num_pinned.detach().cpu().numpy().astype(np.int64))
            w.finish({"index": spec["index"], "group": group, "split": recipe.sequence_split(spec["index"]),
                      "holdout": _json(recipe.sequence_holdout(spec["index"])), "motion_type": spec["motion_type"],
                      "guides_alone": np.asarray(recipe.alone_counts, dtype=np.int64),
                      "seed": spec["seed"], "frames": recipe.frames, "dt": float(run.sim.params.dt),
                      "strands": rest.shape[0], "particles": rest.shape[1], "motion": _json(spec["motion"]),
                      "wind": _json(spec["wind"]), "groom": _json(out["group"]["groom"]),
                      "params": _json(run.sim.params.to_dict()), "scene": _json(run.scene),
                      "library_version": __version__, "units": "metres, seconds; world frame, +y up"})
        _write_scene(h5, run)
        h5.attrs.update(recipe_digest=recipe.digest, group=group, complete=True)
    return out["ms_per_frame"]


def write_group(recipe: Recipe, group: int, path: str, device=None) -> float:
    """Simulate batch group ``group`` and write its sequences to ``path`` atomically. Returns ms/frame."""
    tmp = f"{path}.tmp{os.getpid()}"
    try:
        ms = _write_group_file(recipe, group, tmp, device)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise
    os.replace(tmp, path)
    return ms


def copy_groups(recipe: Recipe, parts: List[str], tmp: str, shard: int, num_shards: int) -> None:
    import h5py

    indices = []
    with h5_file(tmp) as dst:
        for j, p in enumerate(parts):
            check_writes(dst)
            with h5py.File(p, "r") as src:
                for name in sorted(k for k in src.keys() if k.startswith("seq_")):
                    src.copy(src[name], dst, name=name)
                    indices.append(int(src[name].attrs["index"]))
                if j == 0:
                    src.copy(src["scene"], dst, name="scene")
                    if recipe.colliders_vary and "scene/colliders" in dst:
                        del dst["scene/colliders"]  # each batch group has its own: scene/groups/<g>/colliders
                if recipe.colliders_vary:
                    dst["scene"].attrs["colliders_by_group"] = True
                    g = int(src.attrs["group"])
                    dst.require_group(f"scene/groups/{g:06d}")
                    if "scene/colliders" in src:
                        src.copy(src["scene/colliders"], dst[f"scene/groups/{g:06d}"], name="colliders")
        indices.sort()
        for split in SPLITS:
            dst.create_dataset(f"mask/{split}", data=np.array([recipe.sequence_split(i) == split for i in indices], bool))
        dst.attrs.update(format=FORMAT, format_version=FORMAT_VERSION, library_version=__version__,
                         torch_version=str(torch.__version__), recipe_name=recipe.name, recipe=recipe.to_json(),
                         recipe_hash=recipe.hash, recipe_digest=recipe.digest, store=_json(recipe.store),
                         split=_json(recipe.split_rules), shard=shard, num_shards=num_shards,
                         num_sequences=recipe.num_sequences, batch=recipe.batch, frames=recipe.frames,
                         sequences=np.asarray(indices, dtype=np.int64))
        dst.attrs[ATTRS_DIGEST] = attrs_digest(dst.attrs)  # last: covers every attribute above


def atomic_write(final: str, write: Callable[[str], None]) -> None:
    tmp = f"{final}.tmp{os.getpid()}"
    try:
        write(tmp)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise
    os.replace(tmp, final)
