"""USC-HairSalon ``.data`` and CT2Hair ``.bin`` strand files.

``.data`` (USC-HairSalon, Hu et al. 2015), little-endian: int32 strand count S, then for each
strand an int32 point count n and n × 3 float32 (x, y, z). Units as stored (the USC
hairstyles are in metres, y up).

``.bin`` (CT2Hair, Shen et al. 2023): the same layout with 7 float32 per point: x, y, z, then
three floats (a direction: normal or tangent, depending on the producer) and one label.
Reading keeps the four extra values per point in ``metadata["bin_attributes"]`` ((P, 4)
float32, concatenated over the kept strands; the direction is rotated by ``up_axis`` and
``transform`` on import). Strands with fewer than two points are dropped on reading
(``metadata["dropped_strands"]``). Every count is checked against the bytes left before
anything is allocated. Writing uses those when their row count matches the
groom's points, otherwise writes the unit tangent (central differences) and label 0.
"""
from __future__ import annotations

import struct
from typing import Dict, List, Tuple

import numpy as np

from ams_torch.grooms.io._common import ByteReader, concat_strands, fail, read_bytes, split_points, strand_tangents


def _read(path, floats_per_point: int, what: str) -> Tuple[List[np.ndarray], Dict]:
    """Two passes: the strand counts and offsets first (one int64 each, bounded by the file
    size), then one gather of all points; strands with fewer than two points are dropped here
    (``metadata["dropped_strands"]``) so that they never cost a Python object."""
    data = read_bytes(path)
    r = ByteReader(path, data, what)
    if r.left < 4:
        raise fail(path, f"truncated {what} file: {r.left} bytes, the int32 strand count needs 4")
    s = int(r.scalar("<i4", "the strand count"))
    if s < 0:
        raise fail(path, f"corrupt {what} file: negative strand count {s}")
    if 4 * s > r.left:
        raise fail(path, f"corrupt or truncated {what} file: header says {s} strands, but {r.left} bytes cannot "
                         f"hold even their point counts (file size {len(data)})")
    rec = floats_per_point * 4
    counts = np.empty(s, dtype=np.int64)
    starts = np.empty(s, dtype=np.int64)  # offset of each strand's first point, in float32 units
    pos = 4
    size = len(data)
    unpack = struct.Struct("<i").unpack_from
    for i in range(s):
        if pos + 4 > size:
            raise fail(path, f"truncated {what} file: the point count of strand {i} at offset {pos} is missing "
                             f"(file size {size})")
        n = unpack(data, pos)[0]
        if n < 0:
            raise fail(path, f"corrupt {what} file: negative point count {n} for strand {i} (offset {pos})")
        pos += 4
        if n * rec > size - pos:
            raise fail(path, f"truncated {what} file: strand {i} has {n} points ({n * rec} bytes) at offset "
                             f"{pos}, but only {size - pos} bytes are left")
        counts[i], starts[i] = n, pos // 4
        pos += n * rec
    if pos != size:
        raise fail(path, f"corrupt {what} file: {size - pos} unexpected trailing bytes after the last of {s} strands "
                         f"(offset {pos}); the counts in the file do not match its size")
    keep = counts >= 2
    meta: Dict = {}
    if not keep.all():
        meta["dropped_strands"] = int((~keep).sum())
    counts, starts = counts[keep], starts[keep]
    flat = np.frombuffer(data, dtype="<f4", count=size // 4)
    total = int(counts.sum())
    first = np.repeat(starts - np.concatenate([[0], np.cumsum(counts)[:-1]]) * floats_per_point, counts) \
        if total else np.zeros(0, np.int64)
    rows = first + np.arange(total, dtype=np.int64) * floats_per_point  # float index of each point
    block = flat[rows[:, None] + np.arange(floats_per_point)] if total else np.zeros((0, floats_per_point), "<f4")
    pts = np.ascontiguousarray(block[:, :3], dtype=np.float32)
    strands = split_points(pts, counts)
    if floats_per_point > 3:
        meta["bin_attributes"] = np.ascontiguousarray(block[:, 3:], dtype=np.float32)
    return strands, meta


def _write(path, strands, extra=None) -> None:
    pts, counts = concat_strands(strands)
    width = 3 if extra is None else 3 + extra.shape[1]
    rows = pts if extra is None else np.concatenate([pts, extra.astype(np.float32)], 1)
    rows = np.ascontiguousarray(rows, dtype="<f4")
    parts = [np.int32(len(counts)).astype("<i4").tobytes()]
    start = 0
    for n in counts:
        n = int(n)
        parts.append(np.int32(n).astype("<i4").tobytes())
        parts.append(rows[start:start + n].tobytes())
        start += n
    assert rows.shape[1] == width
    with open(path, "wb") as f:
        f.write(b"".join(parts))


def read_data(path):
    """USC-HairSalon ``.data`` → (list of (n_i, 3) float32 arrays, metadata dict)."""
    return _read(path, 3, "USC-HairSalon .data")


def write_data(path, strands, metadata=None) -> None:
    """Write a list of (n_i, 3) polylines (metres) as USC-HairSalon ``.data``."""
    _write(path, strands)


def read_bin(path):
    """CT2Hair ``.bin`` → (list of (n_i, 3) float32 arrays, metadata with ``bin_attributes`` (P, 4))."""
    return _read(path, 7, "CT2Hair .bin")


def write_bin(path, strands, metadata=None) -> None:
    """Write polylines as CT2Hair ``.bin`` (xyz, then 3 direction floats and a label per point)."""
    pts, counts = concat_strands(strands)
    extra = None if metadata is None else metadata.get("bin_attributes")
    if extra is None or np.asarray(extra).shape != (len(pts), 4):
        extra = np.concatenate([strand_tangents(pts, counts), np.zeros((len(pts), 1), np.float32)], 1)
    _write(path, strands, np.asarray(extra, dtype=np.float32))
