"""Reading datasets: the torch ``Dataset`` of frame windows (splits, checksum verification, lazy
per-process handles), one sequence for rendering, and the stored scene meshes."""
from __future__ import annotations

import hashlib
import json
import os
from typing import Dict, Iterable, List, Optional, Sequence, Tuple, Union

import numpy as np
import torch

from ams_torch.apps.data.metadata import check_metadata, refuse_duplicates
from ams_torch.apps.data.format import (FRAME_DIGESTS, PER_FRAME, PER_SEQUENCE, SEQ_PREFIX, SPLITS, DatasetError,
                                        alone_count, alone_name, check_together, is_framed, list_files, open_dataset,
                                        read_header)

__all__ = ["HairSequenceDataset", "read_dataset_sequence", "read_scene_meshes", "stored_pinned_counts"]


def read_scene_meshes(path: str, sequence: Optional[int] = None) -> dict:
    """The scene description stored in a dataset file: ``{"head": {"type", "vertices" (V, 3) m,
    "faces" (F, 3), parameters...}, "colliders": [{"type", parameters..., "vertices", "faces"}]}``
    (metres; the head's in the head frame, a collider's in its own frame: its world pose at
    frame f is ``collider_rotations[f, c]``, ``collider_translations[f, c]`` of a sequence).
    When the recipe draws its colliders per batch group (``/scene`` attribute
    ``colliders_by_group``), the colliders are those of sequence ``sequence``'s group, and
    ``None`` when no sequence is given."""
    def part(g):
        out = {k: (json.loads(v) if k == "params" else v) for k, v in g.attrs.items()}
        out.update({k: g[k][()] for k in ("vertices", "faces") if k in g})
        return out

    with open_dataset(path) as f:
        if f["scene"].attrs.get("colliders_by_group", False):
            if sequence is None:
                return {"head": part(f["scene/head"]), "colliders": None}
            group = int(f[f"{SEQ_PREFIX}{int(sequence):06d}"].attrs["group"])
            cols = f.get(f"scene/groups/{group:06d}/colliders", {})
        else:
            cols = f.get("scene/colliders", {})
        return {"head": part(f["scene/head"]), "colliders": [part(cols[k]) for k in sorted(cols)]}


def read_dataset_sequence(root, index: Optional[int] = None) -> dict:
    """One sequence of a dataset (a folder or a file) in the form :func:`ams_torch.apps.cli.read_sequence`
    returns: ``positions`` (F, S, N, 3) float32 m (guide positions when only guides are stored),
    ``rotations`` (F, 3, 3), ``translations`` (F, 3) m, ``rest_positions``, collider poses,
    ``scene`` (dict), ``dt`` s, ``index``, ``meshes`` (:func:`read_scene_meshes`). ``index`` None:
    the first sequence. Raises :class:`DatasetError` (naming the file) or KeyError."""
    ds = HairSequenceDataset(root, window=1, fields=(), sequences=None if index is None else [index])
    fi, name, idx, _ = ds.sequences[0]
    g = ds._file(fi)[name]
    keys = [k for k in ("positions", "guide_positions", "rotations", "translations", "collider_rotations",
                        "collider_translations") if k in g]
    out = ds.sequence_frames(idx, keys)
    out["rest_positions"] = ds.sequence_arrays(idx)["rest_positions"]
    if "positions" not in out:
        out["positions"] = out.pop("guide_positions")
    out["positions"] = out["positions"].astype(np.float32)
    out.update(scene=json.loads(g.attrs["scene"]), dt=float(g.attrs["dt"]), index=idx, file=ds.files[fi],
               meshes=read_scene_meshes(ds.files[fi], idx))
    ds.close()
    return out


#: sample keys a guides=G item always makes itself (not through ``fields``)
_SAMPLE_OWN = ("guide_positions", "collider_rotations", "collider_translations")


def stored_pinned_counts(params: dict, rest: np.ndarray) -> np.ndarray:
    """(S,) int64: the pinned prefix of every strand as the simulator counts it
    (:func:`ams_torch.sim.model.pinned_counts`) from a sequence's stored ``params`` JSON and
    rest shape (S, N, 3) m; format 3 stores it as ``num_pinned``."""
    from ams_torch.sim.model import pinned_counts
    from ams_torch.sim.params import Params

    p = dict(params)
    if "gravity" in p:
        p["gravity"] = tuple(p["gravity"])
    return pinned_counts(Params(**p), torch.from_numpy(np.asarray(rest))).numpy().astype(np.int64)


def _check_choice(value, allowed, what: str):
    if value not in allowed:
        raise ValueError(f"{what} must be one of {list(allowed)}; got {value!r}")
    return value


class HairSequenceDataset(torch.utils.data.Dataset):
    """Windows of consecutive frames from a dataset written by ``ams-torch generate``.

    Args:
        root: a directory (every ``*.h5`` in it), one file, or a list of files. The files must
            make one dataset: the same recipe (``recipe_digest``) and no sequence in two files
            (else :class:`DatasetError` naming the files).
        window: W, frames per item (≥ 1), or ``None``: one item per whole sequence (W = its
            frame count; the benchmark scores whole sequences).
        stride: frames between the starts of consecutive windows (≥ 1).
        fields: per-frame arrays to return. Default: ``positions`` (when stored),
            ``guide_positions`` (when stored), ``rotations``, ``translations``. Also available:
            ``velocities``, ``linear_velocities``, ``angular_velocities`` and the collider poses.
        static_fields: per-sequence arrays returned with every item, e.g. ``("rest_positions",
            "guide_indices")``. Default none (read them once with :meth:`sequence_arrays`).
        sequences: keep only these sequence indices; default all.
        split: ``"train"``, ``"valid"``, ``"test"`` (or a list of them): keep the sequences of
            that split (the recipe's ``[split]``, by batch group); default all.
        verify: ``"first_read"`` (default): the first read of each frame of each array in a
            process checks it against its stored SHA-256 (per-frame digests for positions,
            velocities and guide positions; per-array digests for the small arrays), so a
            worker hashes only what it reads, once; ``"always"``: every read; ``"never"``.
        dtype: dtype of the floating outputs (float16 storage is upcast). Default float32.
        guides: G: make every item a *sample* of the interpolation benchmark (below) with the
            first G guides of the stored guide order. Default None (items hold ``fields`` only).
        guide_source: where a sample's guide positions come from: ``"alone"`` (default): the G
            guides simulated alone (``guides_alone_<G>``, stored for each count of the recipe's
            ``[store].guides``); ``"dense"``: the dense run's copies of the first G guides
            (``guide_positions[:, :G]``).

    With ``guides=G`` item ``i`` holds: ``guide_positions`` (W, G, N, 3) m world (from
    ``guide_source``), ``guide_index`` (G,) long (the first G of ``guide_indices``),
    ``rest_positions`` (S, N, 3) m head frame, ``num_pinned`` (S,) long (particles per strand
    that follow the head, as the simulator counts them), ``rotations`` (W, 3, 3),
    ``translations`` (W, 3) m, ``collider_rotations`` (W, C, 3, 3) and
    ``collider_translations`` (W, C, 3) m of the scene's ``[[colliders]]`` (C = 0 when the
    sequence has none; a recipe may draw its colliders per batch group), ``positions``
    (W, S, N, 3) m (the dense target) when stored, the per-frame ``fields`` asked for (e.g.
    ``["velocities"]``), ``sequence`` and ``start``. Without ``guides``:

    Item ``i`` is a dict of tensors: ``positions`` (W, S, N, 3) m (world frame),
    ``guide_positions`` (W, G, N, 3) m, ``rotations`` (W, 3, 3), ``translations`` (W, 3) m,
    ``velocities`` (W, S, N, 3) m/s, ``linear_velocities`` (W, 3) m/s, ``angular_velocities``
    (W, 3) rad/s, the static fields, plus ``sequence`` (the sequence index) and ``start`` (its
    first frame). Items are ordered by file, then sequence, then start. Corrupt data and
    checksum mismatches raise :class:`DatasetError` naming the file, sequence, array and frame.

    Files are opened lazily, once per process: a ``DataLoader`` worker opens its own handles on
    its first item and never uses a handle inherited from another process.
    """

    def __init__(self, root, window: Optional[int] = 1, stride: int = 1, fields: Optional[Sequence[str]] = None,
                 static_fields: Sequence[str] = (), sequences: Optional[Iterable[int]] = None,
                 split: Union[None, str, Sequence[str]] = None, verify: str = "first_read",
                 dtype: torch.dtype = torch.float32, guides: Optional[int] = None, guide_source: str = "alone"):
        for name, v in (("window", 1 if window is None else window), ("stride", stride)):
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                whole = " (or None: whole sequences)" if name == "window" else ""
                raise ValueError(f"{name} must be an integer >= 1{whole}; got {v!r}")
        if guides is not None and (isinstance(guides, bool) or not isinstance(guides, int) or guides < 1):
            raise ValueError(f"guides must be an integer >= 1 (the guide count G) or None; got {guides!r}")
        self.guide_source = _check_choice(guide_source, ("alone", "dense"), "guide_source")
        self.guides = guides
        self.verify = _check_choice(verify, ("first_read", "always", "never"), "verify")
        splits = None if split is None else [split] if isinstance(split, str) else list(split)
        for sp in splits or []:
            _check_choice(sp, SPLITS, "split")
        self.files = list_files(root)
        refuse_duplicates(self.files)
        self.window, self.stride, self.dtype = window, stride, dtype
        keep = None if sequences is None else {int(i) for i in sequences}
        self.sequences: List[Tuple[int, str, int, int]] = []  # (file, group name, index, frames)
        available, headers, dense_guides = None, {}, None
        for fi, path in enumerate(self.files):
            with open_dataset(path) as f:
                check_metadata(f, path)  # attributes as written: frames, index, digests, recipe_digest...
                headers[path] = read_header(path) or {"digest": "?", "num_shards": -1, "sequences": []}
                masks = {sp: dict(zip(headers[path]["sequences"], f[f"mask/{sp}"][()].tolist())) for sp in SPLITS}
                for name in sorted(k for k in f.keys() if k.startswith(SEQ_PREFIX)):
                    g = f[name]
                    index = int(g.attrs["index"])
                    if (keep is not None and index not in keep) or (splits and not any(masks[sp].get(index) for sp in splits)):
                        continue
                    have = {k for k in g.keys() if k in PER_FRAME or is_framed(k)}
                    available = have if available is None else available & have
                    gi = int(g["guide_indices"].shape[0]) if "guide_indices" in g else 0
                    dense_guides = gi if dense_guides is None else min(dense_guides, gi)
                    self.sequences.append((fi, name, index, int(g.attrs["frames"])))
        together = check_together(headers)
        if together:
            raise DatasetError(f"{root}: these files are not one dataset: {together[0]} (run `ams-torch validate`)")
        if not self.sequences:
            what = " for the requested indices" if keep else f" in split {splits}" if splits else ""
            raise ValueError(f"no sequences found in {root!r}{what}")
        available = available or set()
        #: the guide counts simulated alone in every selected sequence, and the dense guide copies stored
        self.alone_counts = sorted(c for k in available if (c := alone_count(k)) is not None)
        self.dense_guides = dense_guides or 0
        if guides is not None:
            self._check_guides(root, guides, available)
            sample = ["positions"] * ("positions" in available) + ["rotations", "translations"]
            fields = sample + [k for k in (fields or ()) if k not in sample and k not in _SAMPLE_OWN]
        elif fields is None:
            fields = [k for k in ("positions", "guide_positions", "rotations", "translations") if k in available]
        missing = [k for k in fields if k not in available]
        if missing:
            raise ValueError(f"field(s) {missing} are not stored in every sequence (available: {sorted(available)})")
        bad_static = [k for k in static_fields if k not in PER_SEQUENCE]
        if bad_static:
            raise ValueError(f"unknown static field(s) {bad_static}; choose from {list(PER_SEQUENCE)}")
        self.fields, self.static_fields = list(fields), list(static_fields)
        if window is None:  # whole sequences
            self.items: List[Tuple[int, int]] = [(q, 0) for q in range(len(self.sequences))]
        else:
            self.items = [(q, s) for q, (_, _, _, frames) in enumerate(self.sequences)
                          for s in range(0, frames - window + 1, stride)]
        if not self.items:
            raise ValueError(f"window = {window} is longer than every sequence "
                             f"(at most {max(s[3] for s in self.sequences)} frames)")
        self._static_cache: Tuple = (None, {})
        self._handles: Dict[int, object] = {}
        self._verified: set = set()
        self._digests: Dict[tuple, np.ndarray] = {}
        self._pid = os.getpid()

    def __len__(self) -> int:
        return len(self.items)

    def _check_guides(self, root, guides: int, available: set) -> None:
        """The stored data can make samples with ``guides`` guides from ``guide_source``."""
        if not {"rotations", "translations"} <= available:
            raise ValueError(f"{root}: guides={guides} needs the head poses; this dataset was written with "
                             f"[store] poses = false")
        if self.guide_source == "dense":
            if guides > self.dense_guides:
                raise ValueError(f"{root}: guides={guides} with guide_source='dense', but the dataset stores the dense "
                                 f"run's copies of {self.dense_guides} guide(s) ([store] guides); ask for at most "
                                 f"{self.dense_guides}")
        elif guides not in self.alone_counts:
            stored = self.alone_counts or "none"
            raise ValueError(f"{root}: guides={guides} was not simulated alone in this dataset (guide counts simulated "
                             f"alone: {stored}); ask for one of those, use guide_source='dense' for the dense run's "
                             f"copies of the first {guides} guides"
                             f"{f' (stored up to {self.dense_guides})' if self.dense_guides else ''}, or regenerate "
                             f"with [store] guides including {guides}")

    def _file(self, fi: int):
        import h5py

        if self._pid != os.getpid():  # a forked worker: never touch the parent's handles or caches
            self._handles, self._verified, self._digests, self._pid = {}, set(), {}, os.getpid()
        h = self._handles.get(fi)
        if h is None:
            h = self._handles[fi] = h5py.File(self.files[fi], "r")
        return h

    def _fail(self, fi: int, name: str, key: str, where: str, problem: str):
        raise DatasetError(f"{self.files[fi]}: {name}/{key}{where}: {problem}; run `ams-torch validate` on the "
                           f"dataset") from None

    def _read(self, fi: int, name: str, key: str, sel: slice) -> np.ndarray:
        """Read ``g[key][sel]`` (sel a frame slice, or slice(None) for the whole array), verified."""
        g = self._file(fi)[name]
        d = g[key]
        start, stop, _ = sel.indices(d.shape[0] if d.ndim else 1)
        where = f" frames {start}-{stop - 1}" if sel != slice(None) else ""
        try:
            a = np.ascontiguousarray(d[sel] if d.ndim else d[()])
        except (OSError, RuntimeError, ValueError) as err:
            self._fail(fi, name, key, where, f"unreadable (corrupt data: {err})")
        if self.verify == "never":
            return a
        if is_framed(key):
            dig = self._digests.get((fi, name, key))
            if dig is None:
                dig = self._digests[(fi, name, key)] = g[FRAME_DIGESTS][key][()]
            for j, k in enumerate(range(start, stop)):
                if self.verify == "always" or (fi, name, key, k) not in self._verified:
                    if hashlib.sha256(a[j].tobytes()).digest() != dig[k].tobytes():
                        self._fail(fi, name, key, f" frame {k}", "checksum mismatch (the stored values changed "
                                                                  "after writing)")
                    self._verified.add((fi, name, key, k))
        elif self.verify == "always" or (fi, name, key) not in self._verified:
            whole = a if sel == slice(None) or not d.ndim else np.ascontiguousarray(d[()])
            if hashlib.sha256(whole.tobytes()).hexdigest() != d.attrs.get("sha256"):
                self._fail(fi, name, key, "", "checksum mismatch (the stored values changed after writing)")
            self._verified.add((fi, name, key))
        return a

    def _tensor(self, a: np.ndarray) -> torch.Tensor:
        t = torch.from_numpy(a)
        return t.to(self.dtype) if t.is_floating_point() else t

    def __getitem__(self, i: int) -> Dict[str, torch.Tensor]:
        if not -len(self.items) <= i < len(self.items):
            raise IndexError(f"item {i} out of range ({len(self.items)} windows)")
        q, start = self.items[i]
        fi, name, index, frames = self.sequences[q]
        g = self._file(fi)[name]
        w = slice(start, frames if self.window is None else start + self.window)
        out = {k: self._tensor(self._read(fi, name, k, w)) for k in self.fields}
        for k in self.static_fields:
            if k in g:
                out[k] = self._tensor(self._read(fi, name, k, slice(None)))
        if self.guides is not None:
            out.update(self._sample_static(fi, name))
            for k, tail in (("collider_rotations", (3, 3)), ("collider_translations", (3,))):
                # per sequence: colliders may be drawn per batch group; none stored -> C = 0
                a = self._read(fi, name, k, w) if k in g else np.zeros((w.stop - w.start, 0) + tail, np.float32)
                out[k] = self._tensor(a)
            if self.guide_source == "alone":
                gp = self._read(fi, name, alone_name(self.guides), w)
            else:
                gp = self._read(fi, name, "guide_positions", w)[:, :self.guides]
            out["guide_positions"] = self._tensor(np.ascontiguousarray(gp))
        out["sequence"] = index
        out["start"] = start
        return out

    def _sample_static(self, fi: int, name: str) -> Dict[str, torch.Tensor]:
        """rest_positions, num_pinned and guide_index of a sequence (the last one kept in memory)."""
        key, cached = self._static_cache
        if key != (fi, name, os.getpid()):
            g = self._file(fi)[name]
            rest = self._read(fi, name, "rest_positions", slice(None))
            if "num_pinned" in g:
                pinned = self._read(fi, name, "num_pinned", slice(None))
            else:  # format 2: the simulator's count from the stored params and rest shape
                pinned = stored_pinned_counts(json.loads(g.attrs["params"]), rest)
            gi = self._read(fi, name, "guide_indices", slice(None))[:self.guides]
            cached = {"rest_positions": self._tensor(rest), "num_pinned": torch.from_numpy(pinned).long(),
                      "guide_index": torch.from_numpy(np.ascontiguousarray(gi)).long()}
            self._static_cache = ((fi, name, os.getpid()), cached)
        return {k: v.clone() for k, v in cached.items()}

    def grooms(self) -> Dict[str, List[int]]:
        """The distinct grooms of the selected sequences: ``{groom (the group's [groom] table as
        JSON): [sequence indices]}``. A recipe whose ``[groom]`` has samplers, or a preset without
        ``seed``, grows one groom per batch group."""
        out: Dict[str, List[int]] = {}
        for fi, name, index, _ in self.sequences:
            out.setdefault(str(self._file(fi)[name].attrs["groom"]), []).append(index)
        return out

    def _slot(self, index: int) -> Tuple[int, str]:
        for fi, name, idx, _ in self.sequences:
            if idx == index:
                return fi, name
        raise KeyError(f"sequence {index} is not in this dataset")

    def sequence_frames(self, index: int, fields: Optional[Sequence[str]] = None) -> Dict[str, np.ndarray]:
        """Every frame of the per-frame arrays ``fields`` (default: this dataset's fields) of
        sequence ``index``, as stored (float16 stays float16), verified like items."""
        fi, name = self._slot(index)
        return {k: self._read(fi, name, k, slice(None)) for k in (self.fields if fields is None else fields)}

    def sequence_arrays(self, index: int) -> Dict[str, np.ndarray]:
        """The per-sequence arrays (rest_positions (S, N, 3) m, root binding, guide_indices), the
        parsed JSON attributes (motion, wind, groom, params) and the ``split`` of sequence ``index``."""
        fi, name = self._slot(index)
        g = self._file(fi)[name]
        out = {k: self._read(fi, name, k, slice(None)) for k in PER_SEQUENCE if k in g}
        for k in ("motion", "wind", "groom", "params", "holdout"):
            if k in g.attrs:
                out[k] = json.loads(g.attrs[k])
        if "num_pinned" not in out and "params" in out:  # format 2
            out["num_pinned"] = stored_pinned_counts(out["params"], out["rest_positions"])
        out.update(split=str(g.attrs.get("split", "")), group=int(g.attrs["group"]), dt=float(g.attrs["dt"]),
                   motion_type=str(g.attrs.get("motion_type", out.get("motion", {}).get("type", ""))))
        return out

    def close(self) -> None:
        for h in getattr(self, "_handles", {}).values():
            try:
                h.close()
            except Exception:  # noqa: BLE001 - closing at shutdown must not raise
                pass
        self._handles = {}

    def __getstate__(self):
        state = dict(self.__dict__)
        state["_handles"] = {}  # handles never travel to another process
        state["_verified"], state["_digests"] = set(), {}
        state["_static_cache"] = (None, {})
        return state

    def __del__(self):
        self.close()
