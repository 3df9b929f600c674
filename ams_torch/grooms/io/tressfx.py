"""AMD TressFX ``.tfx`` (binary, TressFX 3.x/4.x), read only.

Layout assumed (from AMD's ``TressFXFileFormat.h``; little-endian), a 160-byte header::

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
(x, y, z, w) with w the vertex's movability/inverse mass (0 = pinned, typically the first
two vertices). We read the positions (units as stored: TressFX assets are usually in the
authoring tool's units, often centimetres), keep w in ``metadata["tfx_w"]`` (S, V) and the
strand thickness and UVs when present. TressFX's runtime pads the strand count to a
multiple of 64 when it loads a file; that padding is not in the file and not added here.
"""
from __future__ import annotations

import math
import struct

import numpy as np

from ams_torch.grooms.io._common import ByteReader, fail, read_bytes

_HEADER = struct.Struct("<f7I32I")
assert _HEADER.size == 160
WHAT = "TressFX .tfx"


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
    r = ByteReader(path, data, WHAT)
    r.seek(off_pos, "offsetVertexPosition")
    xyzw = r.array("<f4", 4 * s * v, f"the vertex positions ({s} strands × {v} vertices × float4)")
    xyzw = xyzw.reshape(s, v, 4)
    meta = dict(tfx_version=float(version), tfx_w=xyzw[..., 3].copy())
    if off_thick:
        r.seek(off_thick, "offsetStrandThickness")
        meta["tfx_strand_thickness"] = r.array("<f4", s, "the strand thickness array").copy()
    if off_suv:
        r.seek(off_suv, "offsetStrandUV")
        meta["tfx_strand_uv"] = r.array("<f4", 2 * s, "the strand UV array").reshape(s, 2).copy()
    strands = list(xyzw[..., :3].astype(np.float32))
    return strands, meta
