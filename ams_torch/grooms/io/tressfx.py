"""AMD TressFX ``.tfx`` (binary, TressFX 3.x/4.x): reading and writing.

Layout (from AMD's ``TressFXFileFormat.h``; little-endian), a 160-byte header::

    float32 version
    uint32  numHairStrands
    uint32  numVerticesPerStrand          every strand has this many vertices
    uint32  offsetVertexPosition          byte offset of float4[numHairStrands × numVerticesPerStrand]
    uint32  offsetStrandUV                float2[numHairStrands], 0 = none
    uint32  offsetVertexUV                float2[numHairStrands × numVerticesPerStrand], 0 = none
    uint32  offsetStrandThickness         float32[numHairStrands], 0 = none
    uint32  offsetVertexColor             float4[numHairStrands × numVerticesPerStrand], 0 = none
    uint32  reserved[32]

Vertices are strand-major (all vertices of strand 0, then strand 1, ...), root first; each is
(x, y, z, w) with w the vertex's inverse mass (0 = pinned, the first two vertices in AMD's
assets). Every array's size is checked against the file before it is read.

Reading: positions (units as stored: AMD's sample assets are in metres), ``metadata["tfx_w"]``
(S, V), and when present ``tfx_strand_uv`` (S, 2), ``tfx_vertex_uv`` (S, V, 2),
``tfx_strand_thickness`` (S,), ``tfx_vertex_color`` (S, V, 4). TressFX's runtime pads the
strand count to a multiple of 64 when it loads a file; that padding is not in the file and not
added here.

Writing (:func:`write_tfx`) follows TressFX's constraints: a fixed number of vertices per strand
that is a power of two up to 64 (strands are resampled in arc length to it when they have
another count), w = 0 on the first ``num_pinned`` vertices and 1 elsewhere, version 4.0,
positions right after the header, then the strand UVs when the groom has them (as AMD's
exporter lays them out); the other optional arrays are not written.
"""
from __future__ import annotations

import math
import struct

import numpy as np

from ams_torch.grooms.io._common import ByteReader, fail, read_bytes

_HEADER = struct.Struct("<f7I32I")
assert _HEADER.size == 160
WHAT = "TressFX .tfx"
#: TressFX's limit on vertices per strand
MAX_VERTICES = 64


def read_tfx(path):
    """``.tfx`` → (list of S (V, 3) float32 arrays, metadata dict)."""
    data = read_bytes(path)
    if len(data) < _HEADER.size:
        raise fail(path, f"truncated {WHAT} file: {len(data)} bytes, the header needs {_HEADER.size}")
    fields = _HEADER.unpack_from(data)
    version, s, v, off_pos, off_suv, off_vuv, off_thick, off_col = fields[:8]
    if not (math.isfinite(version) and 1.0 <= version < 100.0):
        raise fail(path, f"not a {WHAT} file: version field reads {version!r}")
    if v < 2:
        raise fail(path, f"corrupt {WHAT} file: {v} vertices per strand (need ≥ 2)")
    if off_pos < _HEADER.size:
        raise fail(path, f"corrupt {WHAT} file: vertex positions at offset {off_pos}, inside the 160-byte header")
    if 16 * s * v > len(data):
        raise fail(path, f"corrupt or truncated {WHAT} file: {s} strands × {v} vertices need {16 * s * v} bytes "
                         f"of positions, the file has {len(data)}")
    arrays = _layout(path, len(data), s, v, off_pos, ((off_suv, (s, 2), "offsetStrandUV"),
                                                      (off_vuv, (s, v, 2), "offsetVertexUV"),
                                                      (off_thick, (s,), "offsetStrandThickness"),
                                                      (off_col, (s, v, 4), "offsetVertexColor")))
    r = ByteReader(path, data, WHAT)
    r.seek(off_pos, "offsetVertexPosition")
    xyzw = r.array("<f4", 4 * s * v, f"the vertex positions ({s} strands × {v} vertices × float4)")
    xyzw = xyzw.reshape(s, v, 4)
    meta = dict(tfx_version=float(version), tfx_w=xyzw[..., 3].copy())
    keys = {"offsetStrandUV": "tfx_strand_uv", "offsetVertexUV": "tfx_vertex_uv",
            "offsetStrandThickness": "tfx_strand_thickness", "offsetVertexColor": "tfx_vertex_color"}
    for off, shape, name in arrays:
        r.seek(off, name)
        meta[keys[name]] = r.array("<f4", int(np.prod(shape)), f"the array at {name}").reshape(shape).copy()
    strands = list(xyzw[..., :3].astype(np.float32))
    return strands, meta


def _layout(path, size: int, s: int, v: int, off_pos: int, optional) -> list:
    """Check where the header puts the arrays: each optional one (offset, shape, header name)
    after the header and overlapping no other, and every byte of the file after the header
    belonging to an array (to within a strand's worth of padding). A lowered numHairStrands
    leaves whole strands unread (AMD's Ratboy with 1114 of its 2228 strands): refused, as is an
    offset into the header, which would read header bytes as UVs or colours. Returns the
    optional arrays present, as (offset, shape, name)."""
    spans = [(off_pos, off_pos + 16 * s * v, "offsetVertexPosition")]
    present = []
    for off, shape, name in optional:
        if not off:
            continue
        if off < _HEADER.size:
            raise fail(path, f"corrupt {WHAT} file: {name} = {off} points into the {_HEADER.size}-byte header")
        end = off + 4 * int(np.prod(shape))
        if end > size:
            raise fail(path, f"corrupt or truncated {WHAT} file: the array at {name} ({shape} × float32) needs bytes "
                             f"{off}..{end}, the file has {size}")
        spans.append((off, end, name))
        present.append((off, shape, name))
    spans.sort()
    for (a0, a1, an), (b0, b1, bn) in zip(spans, spans[1:]):
        if b0 < a1:
            raise fail(path, f"corrupt {WHAT} file: the arrays at {an} (bytes {a0}..{a1}) and {bn} (from {b0}) "
                             f"overlap")
    covered = sum(b - a for a, b, _ in spans)
    unread = size - _HEADER.size - covered
    if unread >= 16 * v:  # more than a strand's worth: the header's counts do not describe this file
        raise fail(path, f"corrupt {WHAT} file: numHairStrands = {s} × {v} vertices leaves {unread} bytes of the "
                         f"file unread (room for about {s + unread // (16 * v + 8 * bool(present))} strands); the "
                         f"header's strand count does not match the file")
    return present


def default_vertex_count(n: int) -> int:
    """TressFX vertex count for strands of ``n`` points: the next power of two ≥ n, capped at 64."""
    return min(MAX_VERTICES, 1 << max(1, int(n) - 1).bit_length())


def _check_vertex_count(path, count) -> int:
    if isinstance(count, bool) or not isinstance(count, (int, np.integer)):
        raise ValueError(f"{path}: vertices_per_strand must be an integer power of two in [2, 64]; got {count!r}")
    count = int(count)
    if count < 2 or count > MAX_VERTICES or count & (count - 1):
        raise ValueError(f"{path}: TressFX needs a power-of-two number of vertices per strand, at most "
                         f"{MAX_VERTICES} (2, 4, 8, 16, 32, 64); got {count}")
    return count


def write_tfx(path, strands, metadata=None, vertices_per_strand=None, num_pinned: int = 2) -> int:
    """Write polylines (metres) as a TressFX 4 ``.tfx`` file; returns the vertices per strand.

    Args:
        strands: list of S (n_i, 3) float32 arrays, metres, root first.
        metadata: the groom's metadata; ``tfx_strand_uv`` (S, 2) is written when present.
        vertices_per_strand: power of two in [2, 64]. Default: the next power of two of the
            longest strand's point count, capped at 64. Strands with another point count are
            resampled uniformly in arc length (lengths kept, see
            :func:`ams_torch.grooms.groom.resample_strands`); strands that already have it are
            written exactly.
        num_pinned: vertices with w = 0 at each root (default 2, as AMD's assets); 0 ≤
            num_pinned ≤ vertices_per_strand.
    """
    from ams_torch.grooms.groom import resample_strands

    metadata = metadata or {}
    strands = [np.asarray(x, dtype=np.float32).reshape(-1, 3) for x in strands]
    longest = max((len(x) for x in strands), default=2)
    v = default_vertex_count(longest) if vertices_per_strand is None else _check_vertex_count(path, vertices_per_strand)
    if isinstance(num_pinned, bool) or not isinstance(num_pinned, (int, np.integer)) or not 0 <= num_pinned <= v:
        raise ValueError(f"{path}: num_pinned must be an integer in [0, {v}] (vertices per strand); got {num_pinned!r}")
    s = len(strands)
    pos = np.empty((s, v, 3), dtype=np.float32)
    redo = [i for i, x in enumerate(strands) if len(x) != v]
    for i, x in enumerate(strands):
        if len(x) == v:
            pos[i] = x
    if redo:
        if any(len(strands[i]) < 1 for i in redo):
            raise ValueError(f"{path}: cannot write an empty strand to a .tfx file")
        pos[redo] = resample_strands([strands[i] for i in redo], v).astype(np.float32)
    w = np.ones((s, v, 1), dtype=np.float32)
    w[:, :int(num_pinned)] = 0.0
    body = np.concatenate([pos, w], -1).astype("<f4").tobytes()
    uv = metadata.get("tfx_strand_uv")
    off_suv = 0
    tail = b""
    if uv is not None and np.asarray(uv).shape == (s, 2):
        off_suv = _HEADER.size + len(body)
        tail = np.ascontiguousarray(np.asarray(uv, dtype="<f4")).tobytes()
    header = _HEADER.pack(4.0, s, v, _HEADER.size, off_suv, 0, 0, 0, *([0] * 32))
    with open(path, "wb") as f:
        f.write(header + body + tail)
    return v
