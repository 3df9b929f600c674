"""What the learned methods read from a dataset: checked items and samples, windows of the length
a method trains on, a held-out part of the train split, and the global batches of a training
step (the same on every DDP rank).

A dataset here is a :class:`~ams_torch.apps.data.HairSequenceDataset` opened with ``guides=G``
(or anything whose items have the keys of :data:`ITEM_KEYS`): ``positions`` (W, S, N, 3) m world
(the dense target), ``guide_positions`` (W, G, N, 3) m world, ``guide_index`` (G,) long,
``rest_positions`` (S, N, 3) m head frame, ``num_pinned`` (S,) long, ``rotations`` (W, 3, 3),
``translations`` (W, 3) m, ``sequence``, ``start``.
"""
from __future__ import annotations

import copy
import hashlib
import json
from typing import Iterator, List, Optional, Sequence

import torch

__all__ = ["ITEM_KEYS", "check_item", "check_sample", "window_view", "holdout", "dataset_fingerprint",
           "batch_windows", "StepBatches", "strand_subset", "to_device"]

#: the keys of a training item (a sample plus the dense target ``positions``)
ITEM_KEYS = ("positions", "guide_positions", "guide_index", "rest_positions", "num_pinned", "rotations",
             "translations", "sequence", "start")


def _shape(x) -> str:
    return str(tuple(x.shape)) if isinstance(x, torch.Tensor) else type(x).__name__


def check_sample(sample: dict, name: str, target: bool = False) -> tuple:
    """Check the tensors a learned method reads from ``sample`` (a protocol sample, or a training
    item when ``target``); returns (T, G, S, N). Raises ValueError naming the key and the shape
    expected."""
    keys = ITEM_KEYS if target else tuple(k for k in ITEM_KEYS if k != "positions")
    missing = [k for k in keys if k not in sample]
    if missing:
        what = "training item" if target else "sample"
        raise ValueError(f"{name}: the {what} lacks {missing} (has {sorted(sample)}); a dataset for the benchmark "
                         f"is opened with HairSequenceDataset(..., guides=G)")
    g = sample["guide_positions"]
    r = sample["rest_positions"]
    if not (isinstance(g, torch.Tensor) and g.dim() == 4 and g.shape[-1] == 3):
        raise ValueError(f"{name}: guide_positions must be (T, G, N, 3) metres; got {_shape(g)}")
    if not (isinstance(r, torch.Tensor) and r.dim() == 3 and r.shape[-1] == 3):
        raise ValueError(f"{name}: rest_positions must be (S, N, 3) metres; got {_shape(r)}")
    t, gc, n, _ = g.shape
    s = r.shape[0]
    if r.shape[1] != n:
        raise ValueError(f"{name}: guide_positions have N = {n} particles per strand, rest_positions {r.shape[1]}")
    want = {"rotations": (t, 3, 3), "translations": (t, 3), "guide_index": (gc,), "num_pinned": (s,)}
    if target:
        want["positions"] = (t, s, n, 3)
    for k, shape in want.items():
        v = sample[k]
        if not isinstance(v, torch.Tensor) or tuple(v.shape) != shape:
            raise ValueError(f"{name}: {k} must have shape {shape} to match guide_positions {tuple(g.shape)} and "
                             f"rest_positions {tuple(r.shape)}; got {_shape(v)}")
    gi = sample["guide_index"]
    if gi.is_floating_point() or (gc and (int(gi.min()) < 0 or int(gi.max()) >= s)):
        raise ValueError(f"{name}: guide_index must be integer strand indices in [0, {s}); got {gi.tolist()[:8]}...")
    return t, gc, s, n


def check_item(item: dict, name: str) -> tuple:
    """:func:`check_sample` of a training item (with its dense target ``positions``)."""
    return check_sample(item, name, target=True)


def to_device(item: dict, device, dtype=torch.float32) -> dict:
    """The item's tensors on ``device`` (floating ones as ``dtype``)."""
    return {k: (v.to(device, dtype) if v.is_floating_point() else v.to(device)) if isinstance(v, torch.Tensor) else v
            for k, v in item.items()}


def _is_sequence_dataset(ds) -> bool:
    return all(hasattr(ds, a) for a in ("sequences", "items", "window", "stride"))


def window_view(ds, window: int, stride: int = 1, keep: Optional[Sequence[int]] = None):
    """``ds`` with items of ``window`` frames every ``stride`` frames (None: one item per whole
    sequence) (a shallow copy of a
    HairSequenceDataset: its own file handles, its items recomputed), keeping the sequences whose
    index is in ``keep`` (default all; a view of a view keeps only sequences the first kept, so
    a held-out part never comes back). Another kind of dataset is returned as it is (its items
    must then hold at least ``window`` frames) or as a Subset of the kept sequences."""
    if not _is_sequence_dataset(ds):
        if keep is None:
            return ds
        keep = set(int(i) for i in keep)
        return torch.utils.data.Subset(ds, [i for i, q in enumerate(item_sequences(ds)) if q in keep])
    view = copy.copy(ds)  # HairSequenceDataset.__getstate__: no file handle is shared
    kept = set(int(i) for i in keep) if keep is not None else None
    before = getattr(ds, "kept_sequences", None)  # a view of a view keeps the first one's restriction
    if before is not None:
        kept = set(before) if kept is None else kept & set(before)
    view.kept_sequences = None if kept is None else frozenset(kept)
    if window is None:  # whole sequences, one item each
        view.window, view.stride = None, int(stride)
        view.items = [(q, 0) for q, seq in enumerate(ds.sequences) if kept is None or int(seq[2]) in kept]
        return view
    view.window, view.stride = int(window), int(stride)
    view.items = [(q, s) for q, seq in enumerate(ds.sequences) if kept is None or int(seq[2]) in kept
                  for s in range(0, int(seq[-1]) - window + 1, stride)]
    if not view.items:
        raise ValueError(f"no window of {window} frames: the sequences have at most "
                         f"{max(int(s[-1]) for s in ds.sequences)} frames")
    return view


def item_sequences(ds) -> List[int]:
    """The sequence index of every item of ``ds`` (read from the items when the dataset does not
    say)."""
    if _is_sequence_dataset(ds):
        return [int(ds.sequences[q][2]) for q, _ in ds.items]
    if hasattr(ds, "item_sequences"):
        return [int(q) for q in ds.item_sequences()]
    return [int(ds[i]["sequence"]) for i in range(len(ds))]


def holdout(train, share: float = 0.2):
    """(train part, held-out part) of ``train`` by whole sequences: every ⌈1/share⌉-th sequence is
    held out (at least one; none when the split has a single sequence, which is then cut in time:
    its last ``share`` of windows is held out)."""
    seqs = sorted(set(item_sequences(train)))
    if len(seqs) >= 2:
        every = max(2, round(1.0 / share))
        held = seqs[every - 1::every] or seqs[-1:]
        kept = [s for s in seqs if s not in held]
        return keep_sequences(train, kept), keep_sequences(train, held)
    n = len(train)
    cut = max(1, min(n - 1, int(round(n * (1 - share))))) if n > 1 else n
    if n < 2:
        raise ValueError("the train split has a single window: nothing to hold out for validation; give valid=")
    return torch.utils.data.Subset(train, range(cut)), torch.utils.data.Subset(train, range(cut, n))


def keep_sequences(ds, seqs):
    if _is_sequence_dataset(ds):
        return window_view(ds, ds.window, ds.stride, keep=seqs)
    keep = set(seqs)
    return torch.utils.data.Subset(ds, [i for i, q in enumerate(item_sequences(ds)) if q in keep])


def dataset_fingerprint(ds) -> dict:
    """What identifies the data a model was trained on: the recipe digests of the files and the
    sequence indices (HairSequenceDataset), else the number of items."""
    base = ds.dataset if isinstance(ds, torch.utils.data.Subset) else ds
    if _is_sequence_dataset(base) and hasattr(base, "files"):
        from ams_torch.apps.data.format import read_header

        digests = sorted({(read_header(p) or {}).get("digest", "?") for p in base.files})
        return {"recipes": digests, "sequences": sorted(set(item_sequences(ds)))}
    return {"items": len(ds), "sequences": sorted(set(item_sequences(ds)))}


def digest(obj) -> str:
    """SHA-256 of a JSON-able object (sorted keys)."""
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()


def batch_windows(step: int, batch: int, total: int, seed: int) -> torch.Tensor:
    """Item indices of global batch ``step``: a stream of per-epoch permutations of range(total),
    cut into batches of ``batch`` (the same on every rank and after a resume)."""
    start = step * batch
    out, pos = [], start
    while pos < start + batch:
        epoch, off = divmod(pos, total)
        perm = torch.randperm(total, generator=torch.Generator().manual_seed(seed * 100003 + epoch))
        take = min(total - off, start + batch - pos)
        out.append(perm[off:off + take])
        pos += take
    return torch.cat(out)


class StepBatches(torch.utils.data.Sampler):
    """Batch sampler of a DataLoader: for steps ``start`` … ``stop − 1``, this rank's contiguous
    share of global batch ``step`` (:func:`batch_windows`)."""

    def __init__(self, total: int, batch: int, seed: int, start: int, stop: int, rank: int = 0, world: int = 1):
        self.total, self.batch, self.seed = total, batch, seed
        self.start, self.stop, self.rank, self.local = start, stop, rank, batch // world

    def __iter__(self) -> Iterator[List[int]]:
        for step in range(self.start, self.stop):
            ids = batch_windows(step, self.batch, self.total, self.seed)
            yield ids[self.rank * self.local:(self.rank + 1) * self.local].tolist()

    def __len__(self) -> int:
        return max(0, self.stop - self.start)


def strand_subset(s: int, count: int, seed: int) -> torch.Tensor:
    """``count`` distinct strands of ``s`` (all of them, in order, when count ≥ s), drawn from
    ``seed``: (count,) long, sorted."""
    if count <= 0 or count >= s:
        return torch.arange(s)
    g = torch.Generator().manual_seed(int(seed) % (2 ** 63))
    return torch.randperm(s, generator=g)[:count].sort().values
