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
from ams_torch.apps.data.format import (FRAME_DIGESTS, FRAMED, PER_FRAME, PER_SEQUENCE, SEQ_PREFIX, SPLITS,
                                        DatasetError, check_together, list_files, open_dataset, read_header)

__all__ = ["HairSequenceDataset", "read_dataset_sequence", "read_scene_meshes"]


def read_scene_meshes(path: str) -> dict:
    """The scene description stored in a dataset file: ``{"head": {"type", "vertices" (V, 3) m,
    "faces" (F, 3), parameters...}, "colliders": [{"type", parameters..., "vertices", "faces"}]}``
    (metres; the head's in the head frame, a collider's in its own frame: its world pose at
    frame f is ``collider_rotations[f, c]``, ``collider_translations[f, c]`` of a sequence)."""
    def part(g):
        out = {k: (json.loads(v) if k == "params" else v) for k, v in g.attrs.items()}
        out.update({k: g[k][()] for k in ("vertices", "faces") if k in g})
        return out

    with open_dataset(path) as f:
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
               meshes=read_scene_meshes(ds.files[fi]))
    ds.close()
    return out


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
        window: W, frames per item (≥ 1).
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

    Item ``i`` is a dict of tensors: ``positions`` (W, S, N, 3) m (world frame),
    ``guide_positions`` (W, G, N, 3) m, ``rotations`` (W, 3, 3), ``translations`` (W, 3) m,
    ``velocities`` (W, S, N, 3) m/s, ``linear_velocities`` (W, 3) m/s, ``angular_velocities``
    (W, 3) rad/s, the static fields, plus ``sequence`` (the sequence index) and ``start`` (its
    first frame). Items are ordered by file, then sequence, then start. Corrupt data and
    checksum mismatches raise :class:`DatasetError` naming the file, sequence, array and frame.

    Files are opened lazily, once per process: a ``DataLoader`` worker opens its own handles on
    its first item and never uses a handle inherited from another process.
    """

    def __init__(self, root, window: int = 1, stride: int = 1, fields: Optional[Sequence[str]] = None,
                 static_fields: Sequence[str] = (), sequences: Optional[Iterable[int]] = None,
                 split: Union[None, str, Sequence[str]] = None, verify: str = "first_read",
                 dtype: torch.dtype = torch.float32):
        for name, v in (("window", window), ("stride", stride)):
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"{name} must be an integer >= 1; got {v!r}")
        self.verify = _check_choice(verify, ("first_read", "always", "never"), "verify")
        splits = None if split is None else [split] if isinstance(split, str) else list(split)
        for sp in splits or []:
            _check_choice(sp, SPLITS, "split")
        self.files = list_files(root)
        refuse_duplicates(self.files)
        self.window, self.stride, self.dtype = window, stride, dtype
        keep = None if sequences is None else {int(i) for i in sequences}
        self.sequences: List[Tuple[int, str, int, int]] = []  # (file, group name, index, frames)
        available, headers = None, {}
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
                    have = {k for k in PER_FRAME if k in g}
                    available = have if available is None else available & have
                    self.sequences.append((fi, name, index, int(g.attrs["frames"])))
        together = check_together(headers)
        if together:
            raise DatasetError(f"{root}: these files are not one dataset: {together[0]} (run `ams-torch validate`)")
        if not self.sequences:
            what = " for the requested indices" if keep else f" in split {splits}" if splits else ""
            raise ValueError(f"no sequences found in {root!r}{what}")
        available = available or set()
        if fields is None:
            fields = [k for k in ("positions", "guide_positions", "rotations", "translations") if k in available]
        missing = [k for k in fields if k not in available]
        if missing:
            raise ValueError(f"field(s) {missing} are not stored in every sequence (available: {sorted(available)})")
        bad_static = [k for k in static_fields if k not in PER_SEQUENCE]
        if bad_static:
            raise ValueError(f"unknown static field(s) {bad_static}; choose from {list(PER_SEQUENCE)}")
        self.fields, self.static_fields = list(fields), list(static_fields)
        self.items: List[Tuple[int, int]] = [(q, s) for q, (_, _, _, frames) in enumerate(self.sequences)
                                             for s in range(0, frames - window + 1, stride)]
        if not self.items:
            raise ValueError(f"window = {window} is longer than every sequence "
                             f"(at most {max(s[3] for s in self.sequences)} frames)")
        self._handles: Dict[int, object] = {}
        self._verified: set = set()
        self._digests: Dict[tuple, np.ndarray] = {}
        self._pid = os.getpid()

    def __len__(self) -> int:
        return len(self.items)

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
        if key in FRAMED:
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
        fi, name, index, _ = self.sequences[q]
        g = self._file(fi)[name]
        w = slice(start, start + self.window)
        out = {k: self._tensor(self._read(fi, name, k, w)) for k in self.fields}
        for k in self.static_fields:
            if k in g:
                out[k] = self._tensor(self._read(fi, name, k, slice(None)))
        out["sequence"] = index
        out["start"] = start
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
        for k in ("motion", "wind", "groom", "params"):
            if k in g.attrs:
                out[k] = json.loads(g.attrs[k])
        out.update(split=str(g.attrs.get("split", "")), group=int(g.attrs["group"]), dt=float(g.attrs["dt"]))
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
        return state

    def __del__(self):
        self.close()
