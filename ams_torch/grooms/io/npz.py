"""ams_torch's own ``.npz``: the groom's points, counts, root binding and metadata.

Arrays: ``format`` ("ams_torch-groom-v1"), ``points`` (P, 3) float32 metres, ``counts`` (S,)
int64 points per strand, and when bound ``root_triangles`` (S,), ``root_barycentrics`` (S, 3),
``root_face_vertices`` (S, 3), ``root_rest_frames`` (S, 3, 3); ``metadata`` a JSON string
(numpy arrays in the metadata are stored as lists). Written uncompressed; read member by
member without pickles, each ``.npy`` header checked against its member's size (and a
deflated member's size against what deflate can expand to) before anything is allocated.
"""
from __future__ import annotations

import json
import os
import struct
import zipfile
import zlib

import numpy as np
from numpy.lib import format as npformat

from ams_torch.grooms.io._common import GroomFileError, concat_strands, fail, split_points

FORMAT = "ams_torch-groom-v1"
_BINDING = {"root_triangles": (np.int64, ()), "root_barycentrics": (np.float32, (3,)),
            "root_face_vertices": (np.int64, (3,)), "root_rest_frames": (np.float32, (3, 3))}


def _json_default(obj):
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (np.floating,)):
        return float(obj)
    return str(obj)


def write_npz(path, strands, metadata=None, binding=None) -> None:
    """Write polylines (metres), optional binding dict of arrays and metadata to ``.npz``.

    The archive is stored uncompressed (float data hardly compresses, and the reader can then
    bound every allocation by the file size)."""
    pts, counts = concat_strands(strands)
    arrays = dict(format=np.array(FORMAT), points=pts, counts=counts,
                  metadata=np.array(json.dumps(metadata or {}, default=_json_default)))
    if binding is not None:
        for key, (dtype, _) in _BINDING.items():
            if binding.get(key) is not None:
                arrays[key] = np.asarray(binding[key], dtype=dtype)
    with open(path, "wb") as f:
        np.savez(f, **arrays)


#: deflate cannot expand data by more than about 1032:1; a member claiming more is corrupt
_MAX_DEFLATE_RATIO = 1032
_ZIP_ERRORS = (zipfile.BadZipFile, zipfile.LargeZipFile, EOFError, OSError, KeyError, NotImplementedError,
               RuntimeError, struct.error, UnicodeDecodeError, zlib.error, OverflowError, ValueError, RecursionError)


def _read_member(path, zf: zipfile.ZipFile, archive_size: int, name: str) -> np.ndarray:
    """One ``.npy`` member, with its header checked against the member's size before reading."""
    info = zf.getinfo(name)
    if info.compress_size + info.header_offset > archive_size:
        raise fail(path, f"corrupt .npz file: member {name!r} claims {info.compress_size} bytes at offset "
                         f"{info.header_offset}, beyond the file's {archive_size} bytes")
    if info.compress_type == zipfile.ZIP_STORED:
        if info.file_size != info.compress_size:
            raise fail(path, f"corrupt .npz file: stored member {name!r} says {info.file_size} bytes but holds "
                             f"{info.compress_size}")
    elif info.compress_type == zipfile.ZIP_DEFLATED:
        if info.file_size > _MAX_DEFLATE_RATIO * info.compress_size + 1024:
            raise fail(path, f"corrupt .npz file: member {name!r} claims {info.file_size} bytes from "
                             f"{info.compress_size} compressed (more than deflate can expand)")
    else:
        raise fail(path, f"corrupt .npz file: member {name!r} uses compression method {info.compress_type} "
                         "(only stored and deflate are read)")
    with zf.open(info) as fh:
        version = npformat.read_magic(fh)
        if version == (1, 0):
            shape, fortran, dtype = npformat.read_array_header_1_0(fh)
        elif version in ((2, 0), (3, 0)):
            shape, fortran, dtype = npformat.read_array_header_2_0(fh)
        else:
            raise fail(path, f"corrupt .npz file: member {name!r} has .npy version {version}")
        if dtype.hasobject:
            raise fail(path, f"corrupt .npz file: member {name!r} holds Python objects (not read)")
        header = fh.tell()
        nbytes = int(np.prod(shape, dtype=object)) * dtype.itemsize
        if header + nbytes != info.file_size:
            raise fail(path, f"corrupt .npz file: member {name!r} declares shape {shape} of {dtype} "
                             f"({nbytes} bytes) but holds {info.file_size - header} bytes of data")
        raw = bytearray(nbytes)  # bounded: nbytes matches the member's size, checked above
        got = fh.readinto(raw)
    if got != nbytes:
        raise fail(path, f"truncated .npz file: member {name!r} ends after {got} of {nbytes} bytes")
    arr = np.frombuffer(raw, dtype=dtype)
    return arr.reshape(shape, order="F" if fortran else "C")


def read_npz(path):
    """``.npz`` → (list of (n_i, 3) float32 arrays, metadata dict, binding dict or None)."""
    with open(path, "rb") as f:
        magic = f.read(4)
    size = os.path.getsize(path)
    if magic != b"PK\x03\x04" and magic != b"PK\x05\x06":
        raise fail(path, f"corrupt .npz file: not a zip archive (starts with {magic!r}, an .npz starts with b'PK')")
    try:
        with zipfile.ZipFile(path) as zf:
            files = {n[:-4]: n for n in zf.namelist() if n.endswith(".npy")}
            missing = {"format", "points", "counts"} - set(files)
            if missing:
                raise fail(path, f"not an ams_torch groom .npz: missing arrays {sorted(missing)}")
            fmt = str(_read_member(path, zf, size, files["format"]))
            if fmt != FORMAT:
                raise fail(path, f"not an ams_torch groom .npz: format {fmt[:80]!r} (expected {FORMAT!r})")
            pts = np.asarray(_read_member(path, zf, size, files["points"]), dtype=np.float32)
            counts = np.asarray(_read_member(path, zf, size, files["counts"]), dtype=np.int64)
            meta = json.loads(str(_read_member(path, zf, size, files["metadata"]))) if "metadata" in files else {}
            binding = {k: np.asarray(_read_member(path, zf, size, files[k])) for k in _BINDING if k in files}
    except GroomFileError:
        raise
    except _ZIP_ERRORS as err:
        raise fail(path, f"corrupt or truncated .npz file ({type(err).__name__}: {err})") from None
    if not isinstance(meta, dict):
        raise fail(path, f"corrupt groom .npz: metadata is a JSON {type(meta).__name__}, expected an object")
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise fail(path, f"corrupt groom .npz: points have shape {pts.shape}, expected (P, 3)")
    if counts.ndim != 1:
        raise fail(path, f"corrupt groom .npz: counts have shape {counts.shape}, expected (S,)")
    if len(counts) and counts.min() < 0:
        i = int(np.flatnonzero(counts < 0)[0])
        raise fail(path, f"corrupt groom .npz: strand {i} has a negative point count ({int(counts[i])})")
    if int(counts.sum()) != len(pts):
        raise fail(path, f"corrupt groom .npz: counts add up to {int(counts.sum())} but there are {len(pts)} points")
    s = len(counts)
    for key, (_, tail) in _BINDING.items():
        if key in binding and binding[key].shape != (s,) + tuple(tail):
            raise fail(path, f"corrupt groom .npz: {key} has shape {binding[key].shape}, expected {(s,) + tuple(tail)}")
    if binding:
        tri = binding.get("root_face_vertices")
        if tri is not None and len(tri) and tri.min() < 0:
            raise fail(path, "corrupt groom .npz: negative vertex index in root_face_vertices")
    strands = split_points(pts, counts)
    return strands, meta, (binding or None)
