"""PLY polylines: a ``vertex`` element (x, y, z) and an ``edge`` element (vertex1, vertex2).

Writing (binary little-endian by default, ASCII with ``ascii=True``): the strands' points in
order, one edge per segment from the root toward the tip, and a ``strand`` element with one
``nsegs`` per strand (the layout hairutil reads; MeshLab shows the edges).

Reading accepts ASCII and binary (either endianness) files with any extra properties or
elements. Strands are rebuilt from the edges, taken as directed vertex1 → vertex2: a strand
starts at a vertex with no incoming edge and follows the edges to its end; a vertex with two
outgoing or two incoming edges, or a closed loop, is an error (not a set of polylines).
Vertices without edges are skipped. Without an ``edge`` element, a ``strand`` element with
``nsegs`` gives the strands as consecutive runs of vertices. List properties (e.g. faces) are
skipped. Every element count is checked against what the file holds before allocating.
"""
from __future__ import annotations

import re
from typing import Dict, List, Tuple

import numpy as np

from ams_torch.grooms.io._common import concat_strands, fail, read_bytes, split_points

_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
WHAT = "PLY"


def _parse_header(path, data: bytes):
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise fail(path, "not a PLY file (no 'ply' magic or no 'end_header')" if not data.startswith(b"ply")
                   else "truncated PLY file: the header has no 'end_header'")
    nl = data.find(b"\n", end)
    if nl < 0:
        raise fail(path, "truncated PLY file: nothing after 'end_header'")
    lines = data[:end].decode("ascii", "replace").splitlines()
    fmt = None
    elements: List[Tuple[str, int, list]] = []
    for ln in lines[1:]:
        tok = ln.split()
        if not tok or tok[0] in ("comment", "obj_info"):
            continue
        if tok[0] == "format":
            fmt = tok[1] if len(tok) > 1 else None
        elif tok[0] == "element":
            if len(tok) != 3 or not re.fullmatch(r"\d+", tok[2]):
                raise fail(path, f"corrupt PLY header line {ln!r}")
            elements.append((tok[1], int(tok[2]), []))
        elif tok[0] == "property":
            if not elements:
                raise fail(path, f"corrupt PLY header: property before any element ({ln!r})")
            if len(tok) == 5 and tok[1] == "list":
                if tok[2] not in _TYPES or tok[3] not in _TYPES:
                    raise fail(path, f"corrupt PLY header: unknown type in {ln!r}")
                elements[-1][2].append((tok[4], _TYPES[tok[2]], _TYPES[tok[3]]))
            elif len(tok) == 3 and tok[1] in _TYPES:
                elements[-1][2].append((tok[2], _TYPES[tok[1]], None))
            else:
                raise fail(path, f"corrupt PLY header: cannot parse {ln!r}")
        else:
            raise fail(path, f"corrupt PLY header: unknown keyword in {ln!r}")
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise fail(path, f"PLY format {fmt!r} is not supported (ascii, binary_little_endian, binary_big_endian)")
    return fmt, elements, nl + 1


def _read_body(path, data: bytes, fmt: str, elements, start: int) -> Dict[str, Dict[str, np.ndarray]]:
    """Scalar properties of every element as arrays. List properties (faces ...) are skipped:
    no groom needs them, and skipping them keeps memory bounded by the file size."""
    out: Dict[str, Dict[str, np.ndarray]] = {}
    if fmt == "ascii":
        try:
            flat = np.fromstring(data[start:], dtype=np.float64, sep=" ")
        except ValueError:
            raise fail(path, "corrupt PLY file: the ASCII body holds a value that is not a number") from None
        pos = 0
        for name, count, props in elements:
            width = len(props)
            left = len(flat) - pos
            if all(p[2] is None for p in props):
                need = width * count
                if need > left:
                    raise fail(path, f"truncated PLY file: element '{name}' needs {need} values, only {left} are left")
                block = flat[pos:pos + need].reshape(count, width)
                pos += need
                with np.errstate(invalid="ignore", over="ignore"):
                    out[name] = {p[0]: block[:, j].astype(p[1]) for j, p in enumerate(props)}
                continue
            if count * width > left:  # every property takes at least one value per row
                raise fail(path, f"truncated PLY file: element '{name}' ({count} rows) needs at least "
                                 f"{count * width} values, only {left} are left")
            cols = {p[0]: np.empty(count, dtype=np.float64) for p in props if p[2] is None}
            for row in range(count):
                for pname, _, itype in props:
                    if pos >= len(flat):
                        raise fail(path, f"truncated PLY file: element '{name}' ends at row {row} of {count}")
                    if itype is None:
                        cols[pname][row] = flat[pos]
                        pos += 1
                    else:
                        k = flat[pos]
                        if not (np.isfinite(k) and k >= 0 and k == int(k)) or pos + 1 + int(k) > len(flat):
                            raise fail(path, f"corrupt or truncated PLY file: list in element '{name}', row {row}")
                        pos += 1 + int(k)
            with np.errstate(invalid="ignore", over="ignore"):
                out[name] = {k: v.astype(next(p[1] for p in props if p[0] == k)) for k, v in cols.items()}
        return out
    endian = "<" if fmt == "binary_little_endian" else ">"
    pos = start
    for name, count, props in elements:
        if all(p[2] is None for p in props):
            dt = np.dtype([(p[0], endian + p[1]) for p in props])
            need = dt.itemsize * count
            if pos + need > len(data):
                raise fail(path, f"truncated PLY file: element '{name}' ({count} rows, {need} bytes) at offset "
                                 f"{pos}, only {len(data) - pos} bytes are left")
            arr = np.frombuffer(data, dtype=dt, count=count, offset=pos)
            pos += need
            out[name] = {p[0]: arr[p[0]].astype(p[1]) for p in props}
            continue
        least = sum(np.dtype(p[1]).itemsize for p in props)  # a list row holds at least its count
        if count * least > len(data) - pos:
            raise fail(path, f"truncated PLY file: element '{name}' ({count} rows of at least {least} bytes) at "
                             f"offset {pos}, only {len(data) - pos} bytes are left")
        cols = {p[0]: np.empty(count, dtype=p[1]) for p in props if p[2] is None}
        for row in range(count):
            for pname, dtype, itype in props:
                size = np.dtype(dtype).itemsize
                if pos + size > len(data):
                    raise fail(path, f"truncated PLY file: element '{name}' ends at row {row} of {count}")
                value = np.frombuffer(data, endian + dtype, 1, pos)[0]
                pos += size
                if itype is None:
                    cols[pname][row] = value
                else:
                    k = int(value)
                    isize = np.dtype(itype).itemsize
                    if k < 0 or pos + k * isize > len(data):
                        raise fail(path, f"corrupt or truncated PLY file: list in element '{name}', row {row}")
                    pos += k * isize
        out[name] = cols
    return out


def _chains(path, n_vertices: int, v1: np.ndarray, v2: np.ndarray) -> List[np.ndarray]:
    """Vertex index chains of directed polylines given by edges v1 → v2."""
    if len(v1) and (min(v1.min(), v2.min()) < 0 or max(v1.max(), v2.max()) >= n_vertices):
        raise fail(path, f"corrupt PLY file: an edge refers to a vertex outside [0, {n_vertices})")
    outdeg = np.bincount(v1, minlength=n_vertices)
    indeg = np.bincount(v2, minlength=n_vertices)
    if len(v1) and (outdeg.max() > 1 or indeg.max() > 1):
        bad = int(np.flatnonzero((outdeg > 1) | (indeg > 1))[0])
        raise fail(path, f"PLY edges do not form polylines: vertex {bad} has {outdeg[bad]} outgoing and "
                         f"{indeg[bad]} incoming edges")
    if np.array_equal(v2, v1 + 1):  # fast path: every edge joins consecutive vertices (our writer)
        used = (outdeg + indeg) > 0
        starts = np.flatnonzero(used & (indeg == 0))
        ends = np.flatnonzero(used & (outdeg == 0))
        return [np.arange(a, b + 1, dtype=np.int64) for a, b in zip(starts, ends)]
    nxt = np.full(n_vertices, -1, dtype=np.int64)
    nxt[v1] = v2
    starts = np.flatnonzero((indeg == 0) & (outdeg == 1))
    # walk all chains at once
    chains = [[int(s)] for s in starts]
    cur = starts.copy()
    alive = np.arange(len(starts))
    visited = len(starts)
    while len(alive):
        cur = nxt[cur]
        keep = cur >= 0
        alive, cur = alive[keep], cur[keep]
        for a, c in zip(alive.tolist(), cur.tolist()):
            chains[a].append(c)
        visited += len(cur)
    if visited != int(((outdeg + indeg) > 0).sum()):
        raise fail(path, "PLY edges do not form polylines: some edges form a closed loop")
    return [np.asarray(c, dtype=np.int64) for c in chains]


def read_ply(path):
    """PLY polylines → (list of (n_i, 3) float32 arrays, metadata dict)."""
    data = read_bytes(path)
    fmt, elements, start = _parse_header(path, data)
    body = _read_body(path, data, fmt, elements, start)
    vert = body.get("vertex")
    if vert is None or not all(k in vert for k in "xyz"):
        raise fail(path, "PLY file has no 'vertex' element with x, y, z properties")
    pts = np.stack([np.asarray(vert[k], dtype=np.float32) for k in "xyz"], 1)
    meta = dict(ply_format=fmt)
    edge = body.get("edge")
    if edge is not None and "vertex1" in edge and "vertex2" in edge:
        v1 = np.asarray(edge["vertex1"], dtype=np.int64)
        v2 = np.asarray(edge["vertex2"], dtype=np.int64)
        chains = _chains(path, len(pts), v1, v2)
        return [pts[c] for c in chains], meta
    strand = body.get("strand")
    if strand is not None and "nsegs" in strand:
        counts = np.asarray(strand["nsegs"], dtype=np.int64) + 1
        if len(counts) and counts.min() < 1:
            raise fail(path, f"corrupt PLY file: negative nsegs {int(counts.min()) - 1} in the 'strand' element")
        if int(counts.sum()) != len(pts):
            raise fail(path, f"corrupt PLY file: strand nsegs add up to {int(counts.sum())} points, the file has "
                             f"{len(pts)} vertices")
        return [s.copy() for s in split_points(pts, counts)], meta
    raise fail(path, "PLY file has neither an 'edge' element (vertex1, vertex2) nor a 'strand' element (nsegs)")


def write_ply(path, strands, metadata=None, ascii: bool = False) -> None:
    """Write polylines (metres) as PLY: vertices, edges root → tip, per-strand ``nsegs``."""
    pts, counts = concat_strands(strands)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]) if len(counts) else np.zeros(0, np.int64)
    nseg = np.maximum(counts - 1, 0)
    v1 = (np.repeat(starts, nseg) + np.arange(int(nseg.sum())) - np.repeat(np.cumsum(nseg) - nseg, nseg)).astype(np.int64)
    v2 = v1 + 1
    ntype = "ushort" if (len(nseg) == 0 or nseg.max() <= 0xFFFF) else "uint"
    fmt = "ascii" if ascii else "binary_little_endian"
    header = (f"ply\nformat {fmt} 1.0\ncomment ams_torch groom: {len(counts)} strands\n"
              f"element vertex {len(pts)}\nproperty float x\nproperty float y\nproperty float z\n"
              f"element edge {len(v1)}\nproperty int vertex1\nproperty int vertex2\n"
              f"element strand {len(counts)}\nproperty {ntype} nsegs\nend_header\n").encode("ascii")
    with open(path, "wb") as f:
        f.write(header)
        if ascii:
            np.savetxt(f, pts, fmt="%.9g")
            np.savetxt(f, np.stack([v1, v2], 1), fmt="%d")
            np.savetxt(f, nseg[:, None], fmt="%d")
        else:
            f.write(np.ascontiguousarray(pts, dtype="<f4").tobytes())
            f.write(np.ascontiguousarray(np.stack([v1, v2], 1), dtype="<i4").tobytes())
            f.write(nseg.astype("<u2" if ntype == "ushort" else "<u4").tobytes())
