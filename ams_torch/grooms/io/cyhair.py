"""Cem Yuksel's ``.hair`` format (www.cemyuksel.com/research/hairmodels), with LuxCore's UVs.

Little-endian. A 128-byte header::

    char     signature[4]   "HAIR"
    uint32   hair_count     number of strands
    uint32   point_count    total number of points
    uint32   arrays         bit flags: 1 segments, 2 points, 4 thickness, 8 transparency,
                            16 colour, 32 UV (LuxCore's extension)
    uint32   d_segments     default segments per strand (when there is no segments array)
    float32  d_thickness, d_transparency, d_color[3]
    char     info[88]

then the arrays that the flags announce, in this order: segments (uint16 per strand, points =
segments + 1), points (3 float32 per point), thickness (float32 per point), transparency
(float32 per point), colour (3 float32 per point), UV (2 float32 per point).

Every count in the header is checked against the file size before anything is allocated.

Reading keeps the optional per-point arrays in ``metadata["hair_arrays"]`` (``thickness`` (P,),
``transparency`` (P,), ``color`` (P, 3), ``uv`` (P, 2)), the defaults in
``metadata["hair_defaults"]`` and the info string in ``metadata["info"]``. The default thickness
becomes the groom's width (``metadata["width"]``, file units) when it is a plausible hair
diameter (0 < d_thickness·scale ≤ 1 mm after the import scale; Yuksel's own default of 1.0 is
not), otherwise the width stays at the library default (70 µm).

Writing: ``d_thickness`` is the groom's width in metres (a diameter; default 70 µm), not
Yuksel's default 1.0; the per-point arrays kept by the reader are written back when their
length matches the groom's points; the segments array is left out when every strand has the
same count (``d_segments`` then holds it).
"""
from __future__ import annotations

import math
import struct

import numpy as np

from ams_torch.grooms.io._common import ByteReader, concat_strands, fail, read_bytes, split_points

_HEADER = struct.Struct("<4sIIIIff3f88s")
assert _HEADER.size == 128
SEGMENTS, POINTS, THICKNESS, TRANSPARENCY, COLORS, UVS = 1, 2, 4, 8, 16, 32
#: per-point arrays after the points: (flag, metadata key, floats per point), in file order
_EXTRA = ((THICKNESS, "thickness", 1), (TRANSPARENCY, "transparency", 1), (COLORS, "color", 3), (UVS, "uv", 2))
WHAT = "Cem Yuksel .hair"


def read_hair(path):
    """``.hair`` → (list of (n_i, 3) float32 arrays, metadata dict)."""
    data = read_bytes(path)
    if len(data) < _HEADER.size:
        raise fail(path, f"truncated {WHAT} file: {len(data)} bytes, the header needs {_HEADER.size}")
    sig, hair_count, point_count, arrays, d_seg, d_thick, d_transp, c0, c1, c2, info = _HEADER.unpack_from(data)
    if sig != b"HAIR":
        raise fail(path, f"not a {WHAT} file: signature {sig!r} instead of b'HAIR'")
    if not arrays & POINTS:
        raise fail(path, f"{WHAT} file has no points array (flags {arrays:#x})")
    if arrays & ~0x3F:
        raise fail(path, f"corrupt {WHAT} file: unknown array flags {arrays:#x}")
    # sizes announced by the header, checked against the file before any allocation
    floats_per_point = 3 + sum(w for bit, _, w in _EXTRA if arrays & bit)
    need = _HEADER.size + 4 * floats_per_point * point_count + (2 * hair_count if arrays & SEGMENTS else 0)
    if need != len(data):
        raise fail(path, f"corrupt or truncated {WHAT} file: the header says {hair_count} strands and {point_count} "
                         f"points with flags {arrays:#x}, which need {need} bytes, but the file has {len(data)} bytes")
    if hair_count > point_count:
        raise fail(path, f"corrupt {WHAT} file: the header says {hair_count} strands but only {point_count} points "
                         f"(every strand has at least one; file size {len(data)} bytes)")
    r = ByteReader(path, data, WHAT)
    r.seek(_HEADER.size, "header")
    if arrays & SEGMENTS:
        seg = r.array("<u2", hair_count, f"the segments array ({hair_count} strands)").astype(np.int64)
        total = int(seg.sum()) + hair_count
    else:
        total = (int(d_seg) + 1) * hair_count
        seg = None
    if total != point_count:
        raise fail(path, f"corrupt {WHAT} file: the segment counts add up to {total} points but the header says "
                         f"{point_count}")
    if seg is None:
        seg = np.full(hair_count, d_seg, dtype=np.int64)  # bounded: hair_count ≤ point_count ≤ size / 12
    counts = seg + 1
    pts = r.array("<f4", 3 * point_count, f"the points array ({point_count} points)").reshape(-1, 3)
    extra = {}
    for bit, key, width in _EXTRA:
        if arrays & bit:
            a = r.array("<f4", width * point_count, f"the {key} array").copy()
            extra[key] = a if width == 1 else a.reshape(-1, width)
    r.expect_end("the arrays announced in the header")
    meta = dict(
        info=info.split(b"\0", 1)[0].decode("latin-1"),
        hair_defaults=dict(segments=int(d_seg), thickness=float(d_thick), transparency=float(d_transp),
                           color=[float(c0), float(c1), float(c2)]),
    )
    if math.isfinite(d_thick) and d_thick > 0:
        meta["width_candidate"] = float(d_thick)  # adopted by read_groom if plausible after scaling
    if extra:
        meta["hair_arrays"] = extra
    strands = [s.astype(np.float32) for s in split_points(pts, counts)]
    return strands, meta


def write_hair(path, strands, metadata=None, width: float = 7e-5) -> None:
    """Write polylines (metres) as ``.hair``; strands may have different point counts (≤ 65,536).

    ``width``: the groom's strand diameter in metres, written as ``d_thickness``.
    """
    metadata = metadata or {}
    pts, counts = concat_strands(strands)
    if len(counts) and counts.min() < 1:
        raise ValueError(f"{path}: cannot write an empty strand to a .hair file")
    seg = counts - 1
    if len(seg) and seg.max() > 0xFFFF:
        raise ValueError(f"{path}: .hair stores segment counts as uint16; a strand has {int(seg.max())} segments")
    uniform = len(seg) > 0 and bool(np.all(seg == seg[0]))
    flags = POINTS | (0 if uniform else SEGMENTS)
    defaults = dict(transparency=0.0, color=[1.0, 1.0, 1.0])
    defaults.update({k: v for k, v in (metadata.get("hair_defaults") or {}).items()
                     if k in ("transparency", "color")})
    extra = metadata.get("hair_arrays") or {}
    p = len(pts)
    blobs = []
    for bit, key, w in _EXTRA:
        arr = extra.get(key)
        if arr is not None and np.asarray(arr).size == p * w:
            flags |= bit
            blobs.append(np.ascontiguousarray(np.asarray(arr, dtype="<f4")).tobytes())
    info = str(metadata.get("info", "ams_torch groom (metres)")).encode("latin-1", "replace")[:87]
    header = _HEADER.pack(b"HAIR", len(counts), p, flags, int(seg[0]) if uniform else 0,
                          float(width), float(defaults["transparency"]),
                          *[float(c) for c in defaults["color"]], info.ljust(88, b"\0"))
    body = [header]
    if not uniform:
        body.append(seg.astype("<u2").tobytes())
    body.append(np.ascontiguousarray(pts, dtype="<f4").tobytes())
    body += blobs
    with open(path, "wb") as f:
        f.write(b"".join(body))
