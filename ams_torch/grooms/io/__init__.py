"""Reading and writing grooms in the field's hair file formats.

:func:`read_groom` and :func:`write_groom` choose the format from the file's extension:

==============  ==========================================  =====  =====
extension       format                                      read   write
==============  ==========================================  =====  =====
``.data``       USC-HairSalon                               yes    yes
``.hair``       Cem Yuksel's hair format                    yes    yes
``.bin``        CT2Hair (7 float32 per point)               yes    yes
``.tfx``        AMD TressFX 3/4 binary                      yes    no
``.ply``        PLY polylines (vertices + edges)            yes    yes
``.usd[a|c]``   USD BasisCurves (needs ``usd-core``)        yes    yes
``.npz``        ams_torch groom with its root binding       yes    yes
==============  ==========================================  =====  =====

Every reader raises ``ValueError`` (:class:`GroomFileError`) whose message starts with the
file's path and says what is wrong (truncated, corrupt count, bad signature, non-finite
coordinates ...). Units are those stored in the file (metres for the files we write).
Strands with fewer than two points (USC files contain many) are dropped on reading; their
number is in ``metadata["dropped_strands"]``.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from ams_torch.grooms.groom import Groom, resample_strands
from ams_torch.grooms.io._common import GroomFileError, check_points
from ams_torch.grooms.io.cyhair import read_hair, write_hair
from ams_torch.grooms.io.npz import read_npz, write_npz
from ams_torch.grooms.io.ply import read_ply, write_ply
from ams_torch.grooms.io.tressfx import read_tfx
from ams_torch.grooms.io.usc import read_bin, read_data, write_bin, write_data
from ams_torch.grooms.io.usd import read_usd, write_usd

__all__ = ["read_groom", "write_groom", "GroomFileError", "FORMATS"]

#: extension → (description, readable, writable)
FORMATS = {
    ".data": ("USC-HairSalon", True, True),
    ".hair": ("Cem Yuksel .hair", True, True),
    ".bin": ("CT2Hair .bin", True, True),
    ".tfx": ("AMD TressFX .tfx", True, False),
    ".ply": ("PLY polylines", True, True),
    ".usd": ("USD BasisCurves", True, True),
    ".usda": ("USD BasisCurves (ASCII)", True, True),
    ".usdc": ("USD BasisCurves (crate)", True, True),
    ".npz": ("ams_torch groom", True, True),
}
_BINDING_KEYS = ("root_triangles", "root_barycentrics", "root_face_vertices", "root_rest_frames")


def _ext(path) -> str:
    ext = Path(os.fspath(path)).suffix.lower()
    if ext not in FORMATS:
        known = ", ".join(FORMATS)
        raise ValueError(f"{os.fspath(path)}: unknown groom file extension {ext!r} (known: {known})")
    return ext


def read_groom(path, resample: Optional[int] = None) -> Groom:
    """Read a groom; the format follows the extension (see the module table).

    Args:
        path: file path.
        resample: None keeps the strands as stored: when they all have the same number of
            points, ``rest_positions`` is (S, n, 3) float32 and ``strands`` None; otherwise
            ``rest_positions`` is None and ``strands`` a list of S float32 (n_i, 3) arrays.
            An int N resamples every strand to N points uniformly in arc length, keeping its
            length (``rest_positions`` (S, N, 3), ``strands`` None).

    Returns:
        :class:`~ams_torch.grooms.groom.Groom` (metres if the file is; root binding only from
        ``.npz`` and USD files written by ams_torch), ``metadata["source"]`` the path and
        ``metadata["format"]`` the extension.

    Raises:
        ValueError: the file is truncated/corrupt/not in the format (message names the file).
        FileNotFoundError: no such file.
    """
    ext = _ext(path)
    binding = None
    if ext == ".data":
        strands, meta = read_data(path)
    elif ext == ".hair":
        strands, meta = read_hair(path)
    elif ext == ".bin":
        strands, meta = read_bin(path)
    elif ext == ".tfx":
        strands, meta = read_tfx(path)
    elif ext == ".ply":
        strands, meta = read_ply(path)
    elif ext == ".npz":
        strands, meta, binding = read_npz(path)
    else:
        strands, meta, binding = read_usd(path)
    check_points(path, strands)
    keep = [i for i, s in enumerate(strands) if len(s) >= 2]
    if len(keep) != len(strands):
        meta["dropped_strands"] = len(strands) - len(keep)
        strands = [strands[i] for i in keep]
        if binding is not None:
            binding = {k: np.asarray(v)[keep] for k, v in binding.items()}
    meta["source"] = os.fspath(path)
    meta["format"] = ext
    bind = {k: (None if binding is None else binding.get(k)) for k in _BINDING_KEYS}
    counts = {len(s) for s in strands}
    if resample is not None:
        n = int(resample)
        meta["point_counts"] = sorted(counts)
        meta["resampled_to"] = n
        pos = resample_strands(strands, n) if strands else np.zeros((0, n, 3))
        return Groom(rest_positions=torch.as_tensor(pos, dtype=torch.float32), metadata=meta, **bind)
    if len(counts) == 1:
        return Groom(rest_positions=torch.as_tensor(np.stack(strands), dtype=torch.float32), metadata=meta, **bind)
    return Groom(strands=strands, metadata=meta, **bind)


def write_groom(path, groom: Groom, **options) -> None:
    """Write ``groom`` to ``path``; the format follows the extension (see the module table).

    Positions are written as float32 in the groom's frame and units (metres). ``.npz`` and
    USD also keep the root binding; ``.hair``/``.bin`` write back their format's extra
    per-point arrays kept in ``groom.metadata`` by their readers. ``options``: ``ascii=True``
    for PLY. ``.tfx`` is read only (``ValueError``).
    """
    ext = _ext(path)
    if not FORMATS[ext][2]:
        raise ValueError(f"{os.fspath(path)}: writing {FORMATS[ext][0]} files is not supported (read only)")
    if not isinstance(groom, Groom):
        raise TypeError(f"write_groom expects a Groom, got {type(groom).__name__}")
    strands = [np.asarray(s, dtype=np.float32) for s in groom.polylines()]
    binding = None
    if groom.has_binding:
        binding = {k: (None if getattr(groom, k) is None else getattr(groom, k).detach().cpu().numpy())
                   for k in _BINDING_KEYS}
    meta = groom.metadata
    if ext == ".data":
        write_data(path, strands, meta)
    elif ext == ".hair":
        write_hair(path, strands, meta)
    elif ext == ".bin":
        write_bin(path, strands, meta)
    elif ext == ".ply":
        write_ply(path, strands, meta, ascii=bool(options.get("ascii", False)))
    elif ext == ".npz":
        write_npz(path, strands, meta, binding)
    else:
        write_usd(path, strands, meta, binding)
