"""Import transforms: bring assets authored in other units and axes into the library's frame.

The library works in metres with +y up (SPEC §14). An imported groom or mesh says how it was
authored with three keys, applied in this order:

1. **scale** — ``units`` ("m", "cm", "mm") or an explicit ``scale`` factor (file units → metres;
   give one or the other, not both). Default: 1 (the file is in metres).
2. **up axis** — ``up_axis`` "y" (the default: nothing changes) or "z": a Z-up asset is turned
   into the +y-up frame by the proper rotation (x, y, z) → (x, z, −y) (a −90° turn about +x,
   det +1, no mirroring): +z becomes +y and −y (the usual "front" of a Z-up character) +z, the
   direction the library's faces look.
3. **transform** — an optional rigid motion in the library frame (metres, after steps 1–2):
   a 4×4 matrix acting on column vectors ``[x; 1]``, a pair ``(R, t)`` with ``R`` a 3×3
   rotation and ``t`` (3,) metres, or the scene files' table ``{"rotation": R,
   "translation": t}`` (either may be left out). ``R`` must be a rotation (orthonormal, det +1) to within a
   tolerance set by its dtype (``sqrt(eps)``: 1.5e-8 for float64, 3.5e-4 for float32), so type
   rotations with at least 8 significant digits or pass float32 arrays.

The result is one 4×4 float64 matrix ``M = T · U · S`` acting on column vectors.

:func:`check_plausible_size` warns (:class:`ImplausibleSizeWarning`) when an imported asset is
too big to be hair or a head in metres — the usual sign of a file in centimetres read as metres.
"""
from __future__ import annotations

import math
import warnings
from collections.abc import Mapping
from typing import Optional, Sequence, Tuple, Union

import numpy as np

__all__ = ["UNITS", "import_transform", "apply_transform", "linear_scale", "is_identity", "ImplausibleSizeWarning",
           "check_plausible_size", "MAX_STRAND_LENGTH", "MAX_MESH_WIDTH", "Z_UP_TO_Y_UP"]

#: metres per unit for the ``units`` names
UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001}

#: (x, y, z) of a Z-up asset → (x, z, −y) in the +y-up frame (rotation, det +1)
Z_UP_TO_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])

#: longest plausible strand, metres (the longest human hair on record is about 5.6 m; a
#: groom for simulation longer than 3 m is almost certainly in the wrong units)
MAX_STRAND_LENGTH = 3.0
#: widest plausible head / collision mesh, metres
MAX_MESH_WIDTH = 1.0

TransformLike = Union[np.ndarray, Sequence, Tuple[Sequence, Sequence]]


class ImplausibleSizeWarning(UserWarning):
    """An imported groom or mesh is implausibly large for metres (probably centimetres read as
    metres); the message gives the measured size and the file."""


def _rotation_tolerance(dtype) -> float:
    dt = np.dtype(dtype) if np.issubdtype(np.dtype(dtype), np.floating) else np.dtype(np.float64)
    return float(math.sqrt(np.finfo(dt).eps))


def _as_float_array(value, what: str) -> np.ndarray:
    try:
        import torch
        if isinstance(value, torch.Tensor):
            value = value.detach().cpu().numpy()
    except ImportError:  # pragma: no cover - torch is a dependency
        pass
    try:
        arr = np.asarray(value)
    except (TypeError, ValueError) as err:
        raise ValueError(f"transform: {what} is not a numeric array ({err})") from None
    if arr.dtype == object or not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise ValueError(f"transform: {what} must be numeric; got dtype {arr.dtype}")
    return arr


def _check_rotation(r: np.ndarray, tol: float) -> None:
    if r.shape != (3, 3):
        raise ValueError(f"transform: the rotation must be 3x3; got shape {r.shape}")
    if not np.all(np.isfinite(r)):
        raise ValueError("transform: the rotation has NaN/Inf entries")
    ortho = float(np.abs(r.T @ r - np.eye(3)).max())
    if ortho > tol:
        raise ValueError(f"transform: the 3x3 part is not orthonormal (max |RᵀR − I| = {ortho:.3g} > "
                         f"tolerance {tol:.3g}); scale with units=/scale=, not in the transform")
    det = float(np.linalg.det(r))
    if det < 0:
        raise ValueError(f"transform: the 3x3 part is a reflection (det = {det:.6g}); a rigid transform needs "
                         "det +1 (use up_axis='z' for Z-up assets)")


def _rigid(transform, tol: Optional[float]) -> np.ndarray:
    """A 4x4 float64 rigid matrix from a 4x4, (R, t) or {"rotation": R, "translation": t}, validated."""
    if isinstance(transform, Mapping):
        unknown = sorted(set(map(str, transform)) - {"rotation", "translation"})
        if unknown:
            raise ValueError(f"transform: unknown key(s) {unknown}; a transform table has rotation and translation")
        transform = (transform.get("rotation", np.eye(3)), transform.get("translation", np.zeros(3)))
    if isinstance(transform, (tuple, list)) and len(transform) == 2 and np.ndim(transform[1]) == 1 \
            and np.size(transform[1]) == 3:
        r = _as_float_array(transform[0], "R")
        t = _as_float_array(transform[1], "t")
        tol = _rotation_tolerance(r.dtype) if tol is None else tol
        r, t = r.astype(np.float64), t.astype(np.float64).reshape(3)
        _check_rotation(r, tol)
        if not np.all(np.isfinite(t)):
            raise ValueError("transform: the translation has NaN/Inf entries")
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = r, t
        return m
    m = _as_float_array(transform, "the matrix")
    if m.shape != (4, 4):
        raise ValueError(f"transform must be a 4x4 matrix or a pair (R (3, 3), t (3,)); got shape {m.shape}")
    tol = _rotation_tolerance(m.dtype) if tol is None else tol
    m = m.astype(np.float64)
    if not np.all(np.isfinite(m)):
        raise ValueError("transform: the matrix has NaN/Inf entries")
    if np.abs(m[3] - [0.0, 0.0, 0.0, 1.0]).max() > tol:
        raise ValueError(f"transform: the last row of a rigid 4x4 matrix must be [0, 0, 0, 1]; got {m[3].tolist()}")
    _check_rotation(m[:3, :3], tol)
    m[3] = [0.0, 0.0, 0.0, 1.0]
    return m


def import_transform(units: Optional[str] = None, scale: Optional[float] = None, up_axis: str = "y",
                     transform: Optional[TransformLike] = None, *, tolerance: Optional[float] = None) -> np.ndarray:
    """The 4×4 import matrix ``M = T · U · S`` (scale, then up axis, then rigid transform).

    Args:
        units: "m", "cm" or "mm": the file's length unit (exclusive with ``scale``).
        scale: metres per file unit, a positive finite float (exclusive with ``units``).
            Neither: 1 (the file is in metres).
        up_axis: "y" (default) or "z" (rotated to +y up: (x, y, z) → (x, z, −y)).
        transform: optional rigid motion applied last, in metres in the +y-up frame: a 4×4
            matrix (column vectors, last row [0, 0, 0, 1]), ``(R (3, 3), t (3,) metres)`` or
            ``{"rotation": R, "translation": t}``.
        tolerance: override the orthonormality tolerance (default ``sqrt(eps)`` of the
            transform's dtype).

    Returns:
        (4, 4) float64 matrix; points map as ``p' = M[:3, :3] @ p + M[:3, 3]``.

    Raises:
        ValueError: unknown units or up axis, both units and scale, a non-positive scale, a
        transform that is not rigid (not orthonormal, a reflection, bad last row, NaN).
    """
    if units is not None and scale is not None:
        raise ValueError(f"give units or scale, not both (units={units!r}, scale={scale!r})")
    if units is not None:
        key = str(units).strip().lower()
        if key not in UNITS:
            raise ValueError(f"units must be one of {sorted(UNITS)}; got {units!r}")
        s = UNITS[key]
    elif scale is not None:
        if isinstance(scale, bool):
            raise ValueError(f"scale must be a positive number; got {scale!r}")
        try:
            s = float(scale)
        except (TypeError, ValueError):
            raise ValueError(f"scale must be a positive number; got {scale!r}") from None
        if not (math.isfinite(s) and s > 0):
            raise ValueError(f"scale must be a positive finite number; got {scale!r}")
    else:
        s = 1.0
    axis = str(up_axis).strip().lower() if up_axis is not None else "y"
    if axis not in ("y", "z"):
        raise ValueError(f"up_axis must be 'y' or 'z'; got {up_axis!r}")
    m = np.diag([s, s, s, 1.0])
    if axis == "z":
        u = np.eye(4)
        u[:3, :3] = Z_UP_TO_Y_UP
        m = u @ m
    if transform is not None:
        m = _rigid(transform, tolerance) @ m
    return m


def is_identity(matrix: np.ndarray) -> bool:
    """Whether a 4×4 import matrix changes nothing (exactly)."""
    return bool(np.array_equal(np.asarray(matrix), np.eye(4)))


def linear_scale(matrix: np.ndarray) -> float:
    """The uniform scale factor of an import matrix (|det of its 3×3 part|^(1/3))."""
    return float(abs(np.linalg.det(np.asarray(matrix, dtype=np.float64)[:3, :3])) ** (1.0 / 3.0))


def apply_transform(points, matrix: np.ndarray, *, direction: bool = False, dtype=None) -> np.ndarray:
    """Apply a 4×4 import matrix to points (..., 3) (or to directions, without translation and
    scale, when ``direction``). Computed in float64; returned in ``dtype`` (default: the input's
    floating dtype, float32 for non-float input)."""
    p = np.asarray(points)
    out_dtype = dtype if dtype is not None else (p.dtype if np.issubdtype(p.dtype, np.floating) else np.float32)
    if p.shape[-1:] != (3,):
        raise ValueError(f"apply_transform: points must be (..., 3); got {p.shape}")
    m = np.asarray(matrix, dtype=np.float64)
    if direction:
        r = m[:3, :3] / linear_scale(m)
        return (p.astype(np.float64) @ r.T).astype(out_dtype)
    return (p.astype(np.float64) @ m[:3, :3].T + m[:3, 3]).astype(out_dtype)


def check_plausible_size(what: str, size_m: float, limit_m: float, source: str = "", stacklevel: int = 3) -> bool:
    """Warn with :class:`ImplausibleSizeWarning` when ``size_m`` (metres) exceeds ``limit_m``.

    ``what`` names the measure ("longest strand", "mesh width"), ``source`` the file. Returns
    True when a warning was issued.
    """
    if size_m > limit_m:
        where = f"{source}: " if source else ""
        warnings.warn(f"{where}{what} is {size_m:.4g} m, more than {limit_m:g} m; implausible for metres — "
                      "is the file in centimetres or millimetres? (pass units='cm'/'mm' or scale=)",
                      ImplausibleSizeWarning, stacklevel=stacklevel)
        return True
    return False
