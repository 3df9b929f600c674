"""Simulation datasets on disk (HDF5): layout, checksums, validation and a torch ``Dataset``.

``ams-torch generate`` (:mod:`ams_torch.apps.datagen`) writes one HDF5 file per shard; the layout is
documented in ``docs/dataset_format.md``. In short, every sequence is a group ``seq_{index:06d}``
holding ``positions`` (F, S, N, 3) (float32 or float16, metres, world frame, one chunk per
frame), the head pose per frame, the rest groom and its root binding, optional velocities and
guide strands, its draws as JSON attributes and a SHA-256 checksum of everything stored.

- :func:`validate`: check files (structure, shapes, checksums, NaN/Inf, frame counts).
- :class:`HairSequenceDataset`: windows of frames for training, with lazy per-process file
  handles so it works with ``DataLoader(num_workers > 0)``.
"""
from __future__ import annotations

import glob
import hashlib
import json
import os
from typing import Dict, Iterable, List, Optional, Sequence, Tuple, Union

import numpy as np
import torch

__all__ = ["FORMAT", "FORMAT_VERSION", "sequence_name", "dataset_digest", "sequence_checksum",
           "validate_file", "validate", "list_files", "HairSequenceDataset", "PER_FRAME", "PER_SEQUENCE"]

FORMAT = "ams_torch.dataset"
FORMAT_VERSION = 1
SEQ_PREFIX = "seq_"
# per-frame datasets (leading dim F) and per-sequence ones
PER_FRAME = ("positions", "velocities", "guide_positions", "rotations", "translations", "linear_velocities",
             "angular_velocities")
PER_SEQUENCE = ("rest_positions", "root_triangles", "root_barycentrics", "guide_indices")
POSE_FIELDS = ("rotations", "translations", "linear_velocities", "angular_velocities")


def sequence_name(index: int) -> str:
    """HDF5 group name of sequence ``index``: ``seq_000012``."""
    return f"{SEQ_PREFIX}{int(index):06d}"


def array_digest(chunks: Iterable[np.ndarray]) -> str:
    """SHA-256 (hex) of the C-order bytes of consecutive slabs of one array."""
    h = hashlib.sha256()
    for c in chunks:
        h.update(np.ascontiguousarray(c).tobytes())
    return h.hexdigest()


def _slabs(dset, frames_per_read: int = 1):
    """Read a dataset in slabs along its first axis (one chunk per frame for per-frame data)."""
    if dset.ndim == 0 or dset.shape[0] == 0:
        yield dset[()]
        return
    step = frames_per_read if dset.chunks and dset.chunks[0] == 1 else dset.shape[0]
    for k in range(0, dset.shape[0], step):
        yield dset[k:k + step]


def dataset_digest(dset) -> str:
    """SHA-256 (hex) of an h5py dataset's stored values (C order, stored dtype), read slab by slab."""
    return array_digest(_slabs(dset))


def sequence_checksum(entries: Dict[str, Tuple[str, tuple, str]]) -> str:
    """The checksum of a sequence: SHA-256 over the sorted lines ``name:dtype:shape:digest`` of
    its datasets (``entries[name] = (numpy dtype str, shape, dataset digest)``)."""
    lines = [f"{k}:{d}:{'x'.join(str(s) for s in shape)}:{g}" for k, (d, shape, g) in sorted(entries.items())]
    return hashlib.sha256("\n".join(lines).encode()).hexdigest()


def list_files(root: Union[str, Sequence[str]]) -> List[str]:
    """The dataset files under ``root``: a directory (its ``*.h5``, sorted; the ``.partial`` work
    folder of an unfinished run is not included), one file, or a list of files."""
    if isinstance(root, (list, tuple)):
        files = [str(p) for p in root]
    elif os.path.isdir(root):
        files = sorted(glob.glob(os.path.join(root, "*.h5")))
    else:
        files = [str(root)]
    for p in files:
        if not os.path.isfile(p):
            raise FileNotFoundError(f"no such dataset file {p!r}")
    return files


def _required(store: dict) -> List[str]:
    req = ["rest_positions"]
    if store.get("positions", True):
        req.append("positions")
    if store.get("velocities", False):
        req.append("velocities")
    if store.get("guides", 0):
        req += ["guide_indices", "guide_positions"]
    if store.get("poses", True):
        req += list(POSE_FIELDS)
    return req


def _check_sequence(g, name: str, frames: int, store: dict) -> List[str]:
    """Problems of one sequence group (an empty list when it is sound)."""
    problems = []
    missing = [k for k in _required(store) if k not in g]
    if missing:
        return [f"{name}: missing dataset(s) {missing}"]
    if "checksum" not in g.attrs:
        problems.append(f"{name}: no checksum attribute")
    rest = g["rest_positions"]
    if rest.ndim != 3 or rest.shape[-1] != 3:
        return problems + [f"{name}/rest_positions: shape {rest.shape}, expected (S, N, 3)"]
    s, n = rest.shape[:2]
    guides = int(g["guide_indices"].shape[0]) if "guide_indices" in g else 0
    expect = {"positions": (frames, s, n, 3), "velocities": (frames, s, n, 3),
              "guide_positions": (frames, guides, n, 3), "rotations": (frames, 3, 3), "translations": (frames, 3),
              "linear_velocities": (frames, 3), "angular_velocities": (frames, 3),
              "root_triangles": (s,), "root_barycentrics": (s, 3), "guide_indices": (guides,)}
    entries = {}
    for key in sorted(g.keys()):
        d = g[key]
        if key in expect and d.shape != expect[key]:
            what = f"{d.shape[0]} frames, expected {frames}" if key in PER_FRAME and d.shape[:1] != (frames,) \
                else f"shape {d.shape}, expected {expect[key]}"
            problems.append(f"{name}/{key}: {what}")
            continue
        try:
            h = hashlib.sha256()
            bad = 0
            for slab in _slabs(d):
                if np.issubdtype(slab.dtype, np.floating):
                    bad += int(np.size(slab) - np.count_nonzero(np.isfinite(slab)))
                h.update(np.ascontiguousarray(slab).tobytes())
        except (OSError, ValueError, RuntimeError) as err:
            problems.append(f"{name}/{key}: unreadable (corrupt data): {err}")
            continue
        digest = h.hexdigest()
        entries[key] = (d.dtype.str, d.shape, digest)
        if bad:
            problems.append(f"{name}/{key}: {bad} NaN/Inf value(s)")
        stored = d.attrs.get("sha256")
        if stored is not None and stored != digest:
            problems.append(f"{name}/{key}: checksum mismatch (data changed after writing)")
    if "guide_indices" in g and "guide_indices" in entries:
        gi = g["guide_indices"][()]
        if gi.size and (gi.min() < 0 or gi.max() >= s):
            problems.append(f"{name}/guide_indices: out of range [0, {s})")
    if not problems and "checksum" in g.attrs and sequence_checksum(entries) != g.attrs["checksum"]:
        problems.append(f"{name}: sequence checksum mismatch")
    return problems


def validate_file(path: str) -> List[str]:
    """Check one dataset file: it opens, has the format's attributes, holds exactly the sequences
    it lists, every sequence has the datasets its ``store`` settings promise with consistent
    shapes and frame counts, no NaN/Inf, and every checksum matches. Returns the problems found
    (each naming the file and the sequence/dataset), an empty list when the file is sound."""
    import h5py

    try:
        f = h5py.File(path, "r")
    except (OSError, ValueError) as err:
        return [f"{path}: cannot be opened as HDF5 (truncated or corrupt file): {err}"]
    problems = []
    with f:
        try:
            attrs = dict(f.attrs)
            if attrs.get("format") != FORMAT:
                return [f"{path}: not an ams_torch dataset (attribute format = {attrs.get('format')!r})"]
            if int(attrs.get("format_version", -1)) > FORMAT_VERSION:
                return [f"{path}: format_version {attrs['format_version']} is newer than this library's "
                        f"{FORMAT_VERSION}"]
            frames = int(attrs["frames"])
            store = json.loads(attrs["store"])
            listed = [sequence_name(i) for i in np.asarray(attrs["sequences"]).tolist()]
            present = sorted(k for k in f.keys() if k.startswith(SEQ_PREFIX))
        except (KeyError, ValueError, OSError) as err:
            return [f"{path}: unreadable file attributes: {err}"]
        missing = sorted(set(listed) - set(present))
        extra = sorted(set(present) - set(listed))
        if missing:
            problems.append(f"{path}: missing sequence(s) {missing[:5]}{' ...' if len(missing) > 5 else ''}")
        if extra:
            problems.append(f"{path}: unlisted sequence(s) {extra[:5]}")
        for name in present:
            try:
                g = f[name]
            except (KeyError, OSError) as err:
                problems.append(f"{path}: {name}: unreadable group: {err}")
                continue
            problems += [f"{path}: {p}" for p in _check_sequence(g, name, frames, store)]
    return problems


def validate(root: Union[str, Sequence[str]], progress: bool = False) -> Tuple[Dict[str, List[str]], List[str]]:
    """Validate every dataset file under ``root`` (see :func:`list_files`).

    Returns ``(problems, notes)``: ``problems[path]`` lists what is wrong with each file (empty when
    sound); ``notes`` are facts that are not errors (shards of a sharding not present here, an
    unfinished run's ``.partial`` folder) plus cross-file problems prefixed ``error:`` (a sequence
    in two files, files of different recipes)."""
    import h5py

    files = list_files(root)
    it = files
    if progress:
        from tqdm.auto import tqdm

        it = tqdm(files, desc="validating", unit="file")
    problems = {p: validate_file(p) for p in it}
    notes = []
    owner: Dict[int, str] = {}
    shards: Dict[Tuple[str, int], set] = {}
    hashes = set()
    for p in files:
        if problems[p]:
            continue
        with h5py.File(p, "r") as f:
            hashes.add(str(f.attrs.get("recipe_hash", "")))
            n = int(f.attrs.get("num_shards", 1))
            shards.setdefault((str(f.attrs.get("recipe_name", "")), n), set()).add(int(f.attrs.get("shard", 0)))
            for i in np.asarray(f.attrs["sequences"]).tolist():
                if i in owner:
                    notes.append(f"error: sequence {i} is in both {owner[i]} and {p}")
                owner[i] = p
    if len(hashes) > 1:
        notes.append(f"error: the files come from {len(hashes)} different recipes")
    for (name, n), have in sorted(shards.items()):
        lacking = sorted(set(range(n)) - have)
        if lacking:
            notes.append(f"{name}: {len(have)} of {n} shards present (missing {lacking[:8]})")
    if not isinstance(root, (list, tuple)) and os.path.isdir(os.path.join(str(root), ".partial")):
        left = os.listdir(os.path.join(str(root), ".partial"))
        if left:
            notes.append(f"unfinished shard(s) in progress (rerun generate to resume): {sorted(left)}")
    return problems, notes


class HairSequenceDataset(torch.utils.data.Dataset):
    """Windows of consecutive frames from datasets written by ``ams-torch generate``.

    Args:
        root: a directory (every ``*.h5`` in it), one file, or a list of files.
        window: W, frames per item (≥ 1).
        stride: frames between the starts of consecutive windows (≥ 1).
        fields: per-frame arrays to return. Default: ``positions`` (when stored),
            ``guide_positions`` (when stored), ``rotations``, ``translations``. Also available:
            ``velocities``, ``linear_velocities``, ``angular_velocities``.
        static_fields: per-sequence arrays returned with every item, e.g. ``("rest_positions",
            "guide_indices")``. Default none (read them once with :meth:`sequence_arrays`).
        sequences: keep only these sequence indices (e.g. a train/test split); default all.
        dtype: dtype of the floating outputs (float16 storage is upcast). Default float32.

    Item ``i`` is a dict of tensors: ``positions`` (W, S, N, 3) m (world frame),
    ``guide_positions`` (W, G, N, 3) m, ``rotations`` (W, 3, 3), ``translations`` (W, 3) m,
    ``velocities`` (W, S, N, 3) m/s, ``linear_velocities`` (W, 3) m/s, ``angular_velocities``
    (W, 3) rad/s, the static fields, plus ``sequence`` (the sequence index) and ``start`` (its
    first frame). Items are ordered by file, then sequence, then start.

    Files are opened lazily, once per process: a ``DataLoader`` worker opens its own handles on
    its first item and never uses a handle inherited from another process.
    """

    def __init__(self, root, window: int = 1, stride: int = 1, fields: Optional[Sequence[str]] = None,
                 static_fields: Sequence[str] = (), sequences: Optional[Iterable[int]] = None,
                 dtype: torch.dtype = torch.float32):
        import h5py

        if isinstance(window, bool) or not isinstance(window, int) or window < 1:
            raise ValueError(f"window must be an integer >= 1; got {window!r}")
        if isinstance(stride, bool) or not isinstance(stride, int) or stride < 1:
            raise ValueError(f"stride must be an integer >= 1; got {stride!r}")
        self.files = list_files(root)
        self.window, self.stride, self.dtype = window, stride, dtype
        keep = None if sequences is None else {int(i) for i in sequences}
        self.sequences: List[Tuple[int, str, int, int]] = []  # (file, group name, index, frames)
        available = None
        for fi, path in enumerate(self.files):
            try:
                f = h5py.File(path, "r")
            except OSError as err:
                raise ValueError(f"{path}: cannot be opened as HDF5 (truncated or corrupt file): {err}") from None
            with f:
                if f.attrs.get("format") != FORMAT:
                    raise ValueError(f"{path}: not an ams_torch dataset (run `ams-torch validate` on it)")
                for name in sorted(k for k in f.keys() if k.startswith(SEQ_PREFIX)):
                    g = f[name]
                    index = int(g.attrs["index"])
                    if keep is not None and index not in keep:
                        continue
                    frames = int(g.attrs["frames"])
                    have = {k for k in PER_FRAME if k in g}
                    available = have if available is None else available & have
                    self.sequences.append((fi, name, index, frames))
        if not self.sequences:
            raise ValueError(f"no sequences found in {root!r}" + (" for the requested indices" if keep else ""))
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
        self.items: List[Tuple[int, int]] = []  # (sequence slot, start)
        for q, (_, _, _, frames) in enumerate(self.sequences):
            self.items += [(q, s) for s in range(0, frames - window + 1, stride)]
        if not self.items:
            raise ValueError(f"window = {window} is longer than every sequence "
                             f"(at most {max(s[3] for s in self.sequences)} frames)")
        self._handles: Dict[int, object] = {}
        self._pid = os.getpid()

    def __len__(self) -> int:
        return len(self.items)

    def _file(self, fi: int):
        import h5py

        if self._pid != os.getpid():  # a forked worker: never touch the parent's handles
            self._handles, self._pid = {}, os.getpid()
        h = self._handles.get(fi)
        if h is None:
            h = self._handles[fi] = h5py.File(self.files[fi], "r")
        return h

    def _tensor(self, a: np.ndarray) -> torch.Tensor:
        t = torch.from_numpy(np.ascontiguousarray(a))
        return t.to(self.dtype) if t.is_floating_point() else t

    def __getitem__(self, i: int) -> Dict[str, torch.Tensor]:
        if not -len(self.items) <= i < len(self.items):
            raise IndexError(f"item {i} out of range ({len(self.items)} windows)")
        q, start = self.items[i]
        fi, name, index, _ = self.sequences[q]
        g = self._file(fi)[name]
        w = slice(start, start + self.window)
        out = {k: self._tensor(g[k][w]) for k in self.fields}
        for k in self.static_fields:
            if k in g:
                out[k] = self._tensor(g[k][()])
        out["sequence"] = index
        out["start"] = start
        return out

    def sequence_arrays(self, index: int) -> Dict[str, np.ndarray]:
        """The per-sequence arrays (rest_positions (S, N, 3) m, root binding, guide_indices) and
        the parsed JSON attributes (motion, wind, groom, params) of sequence ``index``."""
        for fi, name, idx, _ in self.sequences:
            if idx == index:
                g = self._file(fi)[name]
                out = {k: g[k][()] for k in PER_SEQUENCE if k in g}
                for k in ("motion", "wind", "groom", "params"):
                    if k in g.attrs:
                        out[k] = json.loads(g.attrs[k])
                return out
        raise KeyError(f"sequence {index} is not in this dataset")

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
        return state

    def __del__(self):
        self.close()
