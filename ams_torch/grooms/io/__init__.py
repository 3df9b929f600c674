"""Reading and writing grooms in the field's hair file formats.

:func:`read_groom` and :func:`write_groom` choose the format from the file's extension:

==============  ==========================================  =====  =====
extension       format                                      read   write
==============  ==========================================  =====  =====
``.data``       USC-HairSalon                               yes    yes
``.hair``       Cem Yuksel's hair format (+ LuxCore UVs)    yes    yes
``.bin``        CT2Hair (7 float32 per point)               yes    yes
``.tfx``        AMD TressFX 3/4 binary                      yes    yes
``.ply``        PLY polylines (vertices + edges)            yes    yes
``.usd[a|c]``   USD BasisCurves (needs ``usd-core``)        yes    yes
``.npz``        ams_torch groom with its root binding       yes    yes
==============  ==========================================  =====  =====

Every reader raises ``ValueError`` (:class:`GroomFileError`) whose message starts with the
file's path and says what is wrong (truncated, corrupt count, bad signature, non-finite
coordinates, bytes that are not text ...). Every count in a binary header is checked against
the file's size before anything is allocated, so a corrupt count cannot exhaust memory.

Units and axes: files store whatever their author used (USC grooms are in centimetres, AMD's
TressFX assets in metres, Z-up tools write Z-up). :func:`read_groom` takes the import keys of
:func:`ams_torch.geometry.units.import_transform` (``units``/``scale``, ``up_axis``,
``transform``, applied in that order) and warns (:class:`ImplausibleSizeWarning`) when a strand
is longer than 3 m. USD stages declare their own ``metersPerUnit`` and ``upAxis``, which the
reader applies. Strands with fewer than two points (USC files contain many) are dropped on
reading; their number is in ``metadata["dropped_strands"]``.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from ams_torch.geometry.units import (MAX_STRAND_LENGTH, ImplausibleSizeWarning, apply_transform,
                                      check_plausible_size, import_transform, linear_scale)
from ams_torch.grooms.groom import DEFAULT_WIDTH, Groom, resample_strands, strand_lengths
from ams_torch.grooms.io._common import GroomFileError, check_points
from ams_torch.grooms.io.cyhair import read_hair, write_hair
from ams_torch.grooms.io.npz import read_npz, write_npz
from ams_torch.grooms.io.ply import read_ply, write_ply
from ams_torch.grooms.io.tressfx import read_tfx, write_tfx
from ams_torch.grooms.io.usc import read_bin, read_data, write_bin, write_data
from ams_torch.grooms.io.usd import read_usd, write_usd

__all__ = ["read_groom", "write_groom", "GroomFileError", "FORMATS", "ImplausibleSizeWarning"]

#: extension → (description, readable, writable)
FORMATS = {
    ".data": ("USC-HairSalon", True, True),
    ".hair": ("Cem Yuksel .hair", True, True),
    ".bin": ("CT2Hair .bin", True, True),
    ".tfx": ("AMD TressFX .tfx", True, True),
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


#: widest plausible hair diameter: a ``.hair`` default thickness above it is not taken as a width
_MAX_WIDTH = 1e-3


def _import(path, ext, strands, meta, binding, matrix) -> tuple:
    """Apply the import matrix to strands and to the length/direction data in metadata."""
    s = linear_scale(matrix)
    strands = [apply_transform(x, matrix, dtype=np.float32) for x in strands]
    if "bin_attributes" in meta and len(meta["bin_attributes"]):
        attrs = np.array(meta["bin_attributes"], dtype=np.float32)
        attrs[:, :3] = apply_transform(attrs[:, :3], matrix, direction=True)
        meta["bin_attributes"] = attrs
    arrays = meta.get("hair_arrays")
    if arrays and "thickness" in arrays:
        arrays["thickness"] = (np.asarray(arrays["thickness"], dtype=np.float64) * s).astype(np.float32)
    if "usd_widths" in meta:
        meta["usd_widths"] = (np.asarray(meta["usd_widths"], dtype=np.float64) * s).astype(np.float32)
    if binding is not None and binding.get("root_rest_frames") is not None:
        r = torch.as_tensor(matrix[:3, :3] / s)
        binding["root_rest_frames"] = (r @ torch.as_tensor(np.asarray(binding["root_rest_frames"], np.float64))).numpy()
    return strands, meta, binding


def read_groom(path, resample: Optional[int] = None, *, units: Optional[str] = None, scale: Optional[float] = None,
               up_axis: str = "y", transform=None) -> Groom:
    """Read a groom; the format follows the extension (see the module table).

    Args:
        path: file path.
        resample: None keeps the strands as stored: when they all have the same number of
            points, ``rest_positions`` is (S, n, 3) float32 and ``strands`` None; otherwise
            ``rest_positions`` is None and ``strands`` a list of S float32 (n_i, 3) arrays.
            An int N resamples every strand to N points uniformly in arc length, keeping its
            length (``rest_positions`` (S, N, 3), ``strands`` None).
        units, scale, up_axis, transform: how the file was authored, see
            :func:`ams_torch.geometry.units.import_transform`: ``units`` "m"/"cm"/"mm" or
            ``scale`` (metres per file unit), then ``up_axis`` "y"/"z", then an optional rigid
            ``transform`` (4×4 or (R, t) in metres). Default: metres, +y up, no transform. USD
            stages that declare ``metersPerUnit``/``upAxis`` are converted by the reader; giving
            ``units``/``scale`` or ``up_axis="z"`` for such a file is an error (it would convert
            twice).

    Returns:
        :class:`~ams_torch.grooms.groom.Groom` in metres, +y up; root binding only from
        ``.npz`` and USD files written by ams_torch (or bind it with :meth:`Groom.bind_to`);
        ``width`` from the file when it stores a plausible one (USD widths, ``.hair`` default
        thickness ≤ 1 mm, ``.npz``), else 70 µm. ``metadata``: ``source`` (the path),
        ``format`` (the extension), ``import_transform`` ((4, 4) list) and the format's extras.

    Warns:
        :class:`ImplausibleSizeWarning` when the longest strand is longer than 3 m.

    Raises:
        ValueError: the file is truncated/corrupt/not in the format (:class:`GroomFileError`,
            message starts with the file), or bad import keys.
        FileNotFoundError: no such file.
    """
    ext = _ext(path)
    matrix = import_transform(units=units, scale=scale, up_axis=up_axis, transform=transform)
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
        if meta.get("usd_meters_per_unit_authored") and (units is not None or scale is not None):
            raise ValueError(f"{os.fspath(path)}: the stage declares metersPerUnit = {meta['usd_meters_per_unit']:g}, "
                             "already converted to metres; do not pass units/scale (use transform to move it)")
        if meta.get("usd_up_axis_authored") and str(up_axis).lower() == "z":
            raise ValueError(f"{os.fspath(path)}: the stage declares upAxis = {meta['usd_up_axis']}, already "
                             "converted to +y up; do not pass up_axis='z'")
    check_points(path, strands)
    keep = [i for i, s in enumerate(strands) if len(s) >= 2]
    if len(keep) != len(strands):
        meta["dropped_strands"] = meta.get("dropped_strands", 0) + len(strands) - len(keep)
        strands = [strands[i] for i in keep]
        if binding is not None:
            binding = {k: np.asarray(v)[keep] for k, v in binding.items()}
    identity = bool(np.array_equal(matrix, np.eye(4)))
    if not identity:
        strands, meta, binding = _import(path, ext, strands, meta, binding, matrix)
    meta["source"] = os.fspath(path)
    meta["format"] = ext
    meta["import_transform"] = matrix.tolist()
    s = linear_scale(matrix)
    width = DEFAULT_WIDTH
    if "width" in meta:
        width = float(meta.pop("width")) * s
    candidate = meta.pop("width_candidate", None)
    if candidate is not None and 0 < candidate * s <= _MAX_WIDTH:
        width = float(candidate) * s
    if strands:
        longest = float(strand_lengths(strands).max())
        check_plausible_size("longest strand", longest, MAX_STRAND_LENGTH, source=os.fspath(path))
    bind = {k: (None if binding is None else binding.get(k)) for k in _BINDING_KEYS}
    counts = {len(s) for s in strands}
    if resample is not None:
        n = int(resample)
        meta["point_counts"] = sorted(counts)
        meta["resampled_to"] = n
        pos = resample_strands(strands, n) if strands else np.zeros((0, n, 3))
        return Groom(rest_positions=torch.as_tensor(pos, dtype=torch.float32), metadata=meta, width=width, **bind)
    if len(counts) == 1:
        return Groom(rest_positions=torch.as_tensor(np.stack(strands), dtype=torch.float32), metadata=meta,
                     width=width, **bind)
    return Groom(strands=strands, metadata=meta, width=width, **bind)


def write_groom(path, groom: Groom, **options) -> Optional[int]:
    """Write ``groom`` to ``path``; the format follows the extension (see the module table).

    Positions are written as float32 in the groom's frame and units (metres). ``.npz`` and
    USD also keep the root binding; ``.hair``/``.bin`` write back their format's extra
    per-point arrays kept in ``groom.metadata`` by their readers; ``.hair`` and USD write the
    groom's ``width`` (metres) as thickness/widths, ``.npz`` keeps it. ``options``:
    ``ascii=True`` for PLY; ``vertices_per_strand`` (power of two ≤ 64) and ``num_pinned``
    (default 2) for ``.tfx`` (see :func:`ams_torch.grooms.io.tressfx.write_tfx`; returns the
    vertices per strand written). Unknown options raise ``TypeError``.
    """
    ext = _ext(path)
    if not FORMATS[ext][2]:
        raise ValueError(f"{os.fspath(path)}: writing {FORMATS[ext][0]} files is not supported (read only)")
    if not isinstance(groom, Groom):
        raise TypeError(f"write_groom expects a Groom, got {type(groom).__name__}")
    allowed = {".ply": {"ascii"}, ".tfx": {"vertices_per_strand", "num_pinned"}}.get(ext, set())
    unknown = sorted(set(options) - allowed)
    if unknown:
        raise TypeError(f"write_groom: unknown option(s) {unknown} for {ext} files (allowed: {sorted(allowed)})")
    strands = [np.asarray(s, dtype=np.float32) for s in groom.polylines()]
    binding = None
    if groom.has_binding:
        binding = {k: (None if getattr(groom, k) is None else getattr(groom, k).detach().cpu().numpy())
                   for k in _BINDING_KEYS}
    meta = groom.metadata
    if ext == ".data":
        write_data(path, strands, meta)
    elif ext == ".hair":
        write_hair(path, strands, meta, width=groom.width)
    elif ext == ".bin":
        write_bin(path, strands, meta)
    elif ext == ".tfx":
        return write_tfx(path, strands, meta, vertices_per_strand=options.get("vertices_per_strand"),
                         num_pinned=options.get("num_pinned", 2))
    elif ext == ".ply":
        write_ply(path, strands, meta, ascii=bool(options.get("ascii", False)))
    elif ext == ".npz":
        write_npz(path, strands, dict(meta, width=groom.width), binding)
    else:
        write_usd(path, strands, meta, binding, width=groom.width)
    return None
