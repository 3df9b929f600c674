"""ams_torch's own ``.npz``: the groom's points, counts, root binding and metadata.

Arrays: ``format`` ("ams_torch-groom-v1"), ``points`` (P, 3) float32 metres, ``counts`` (S,)
int64 points per strand, and when bound ``root_triangles`` (S,), ``root_barycentrics`` (S, 3),
``root_face_vertices`` (S, 3), ``root_rest_frames`` (S, 3, 3); ``metadata`` a JSON string
(numpy arrays in the metadata are stored as lists). Read with ``allow_pickle=False``.
"""
from __future__ import annotations

import json
import zipfile

import numpy as np

from ams_torch.grooms.io._common import concat_strands, fail, split_points

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
    """Write polylines (metres), optional binding dict of arrays and metadata to ``.npz``."""
    pts, counts = concat_strands(strands)
    arrays = dict(format=np.array(FORMAT), points=pts, counts=counts,
                  metadata=np.array(json.dumps(metadata or {}, default=_json_default)))
    if binding is not None:
        for key, (dtype, _) in _BINDING.items():
            if binding.get(key) is not None:
                arrays[key] = np.asarray(binding[key], dtype=dtype)
    with open(path, "wb") as f:
        np.savez_compressed(f, **arrays)


def read_npz(path):
    """``.npz`` → (list of (n_i, 3) float32 arrays, metadata dict, binding dict or None)."""
    with open(path, "rb") as f:
        magic = f.read(4)
    if magic != b"PK\x03\x04" and magic != b"PK\x05\x06":
        raise fail(path, f"corrupt .npz file: not a zip archive (starts with {magic!r}, an .npz starts with b'PK')")
    try:
        with np.load(path, allow_pickle=False) as z:
            files = set(z.files)
            missing = {"format", "points", "counts"} - files
            if missing:
                raise fail(path, f"not an ams_torch groom .npz: missing arrays {sorted(missing)}")
            fmt = str(z["format"])
            if fmt != FORMAT:
                raise fail(path, f"not an ams_torch groom .npz: format {fmt!r} (expected {FORMAT!r})")
            pts = np.asarray(z["points"], dtype=np.float32)
            counts = np.asarray(z["counts"], dtype=np.int64)
            meta = json.loads(str(z["metadata"])) if "metadata" in files else {}
            binding = {k: np.asarray(z[k]) for k in _BINDING if k in files}
    except (zipfile.BadZipFile, EOFError, OSError, KeyError, json.JSONDecodeError) as err:
        raise fail(path, f"corrupt or truncated .npz file ({type(err).__name__}: {err})") from None
    except ValueError as err:
        if str(err).startswith(str(path)):
            raise
        raise fail(path, f"corrupt or truncated .npz file ({err})") from None
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise fail(path, f"corrupt groom .npz: points have shape {pts.shape}, expected (P, 3)")
    if counts.ndim != 1 or (len(counts) and counts.min() < 0) or int(counts.sum()) != len(pts):
        raise fail(path, f"corrupt groom .npz: counts add up to {int(counts.sum())} but there are {len(pts)} points")
    s = len(counts)
    for key, (_, tail) in _BINDING.items():
        if key in binding and binding[key].shape != (s,) + tuple(tail):
            raise fail(path, f"corrupt groom .npz: {key} has shape {binding[key].shape}, expected {(s,) + tuple(tail)}")
    strands = [a.copy() for a in split_points(pts, counts)]
    return strands, meta, (binding or None)
