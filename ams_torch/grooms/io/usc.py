"""USC-HairSalon ``.data`` and CT2Hair ``.bin`` strand files.

``.data`` (USC-HairSalon, Hu et al. 2015), little-endian: int32 strand count S, then for each
strand an int32 point count n and n × 3 float32 (x, y, z). Units as stored (the USC
hairstyles are in metres, y up).

``.bin`` (CT2Hair, Shen et al. 2023): the same layout with 7 float32 per point: x, y, z, then
three floats (a direction: normal or tangent, depending on the producer) and one label.
Reading keeps the four extra values per point in ``metadata["bin_attributes"]`` ((P, 4)
float32, concatenated over strands). Writing uses those when their row count matches the
groom's points, otherwise writes the unit tangent (central differences) and label 0.
"""
from __future__ import annotations

from typing import Dict, List, Tuple

import numpy as np

from ams_torch.grooms.io._common import ByteReader, concat_strands, fail, read_bytes, strand_tangents


def _read(path, floats_per_point: int, what: str) -> Tuple[List[np.ndarray], Dict]:
    r = ByteReader(path, read_bytes(path), what)
    if r.left < 4:
        raise fail(path, f"truncated {what} file: {r.left} bytes, the int32 strand count needs 4")
    s = int(r.scalar("<i4", "the strand count"))
    if s < 0:
        raise fail(path, f"corrupt {what} file: negative strand count {s}")
    if 4 * s > r.left:
        raise fail(path, f"corrupt or truncated {what} file: header says {s} strands, but {r.left} bytes cannot "
                         f"hold even their point counts")
    strands, extras = [], []
    rec = floats_per_point * 4
    for i in range(s):
        n = int(r.scalar("<i4", f"the point count of strand {i}"))
        if n < 0:
            raise fail(path, f"corrupt {what} file: negative point count {n} for strand {i} (offset {r.pos - 4})")
        if n * rec > r.left:
            raise fail(path, f"truncated {what} file: strand {i} has {n} points ({n * rec} bytes) at offset "
                             f"{r.pos}, but only {r.left} bytes are left")
        a = r.array("<f4", n * floats_per_point, f"the points of strand {i}").reshape(n, floats_per_point)
        strands.append(a[:, :3].astype(np.float32))
        if floats_per_point > 3:
            extras.append(a[:, 3:])
    r.expect_end(f"the last of {s} strands")
    meta: Dict = {}
    if floats_per_point > 3:
        meta["bin_attributes"] = (np.concatenate(extras, 0).astype(np.float32) if extras
                                  else np.zeros((0, floats_per_point - 3), np.float32))
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
