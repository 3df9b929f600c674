"""The checkers of the table-driven scene and recipe validation.

A checker is a callable ``(value, key, ctx) -> normalised value`` that calls ``ctx.fail(msg)``
(raising :class:`SceneError`, or the recipe's error class, naming the file and the key) when the
value is wrong; a table is a dict ``key -> (checker, default or ABSENT)`` checked by
:func:`check_table`. The scene sections (:mod:`ams_torch.apps.scene.schema`) and the recipe
(:mod:`ams_torch.apps.recipe.checks`) are written as such tables.
"""
from __future__ import annotations

import copy
import math
import os
from typing import Callable, Dict, Optional

import numpy as np

from ams_torch.apps.scene.limits import check_range

__all__ = ["SceneError", "check_table", "check_rotation", "is_number", "number", "integer", "boolean", "one_of",
           "string", "vec3", "list_of", "file_path", "rotation", "transform", "ABSENT", "POSITIVE", "NONNEG",
           "ANY_NUMBER", "ROTATION_TOLERANCE", "UNITS"]

ROTATION_TOLERANCE = 1e-5  #: max |RᵀR − I| of a rotation matrix in a scene file
#: the largest magnitude of a non-integer number in a scene or recipe (float32 reaches 3.4e38: products
#: of larger values overflow); keys with a physical bound have a tighter one (limits.RANGES)
MAX_MAGNITUDE = 1e15
UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001}  #: file unit -> metres
ABSENT = _ABSENT = object()  # no default: the key stays absent unless given
_CAUGHT = (TypeError, ValueError, ArithmeticError, IndexError, KeyError, AttributeError, FileNotFoundError)


class SceneError(ValueError):
    """A scene file is invalid; the message names the file and the key."""


class _Ctx:
    """Where the scene came from: ``where`` (file name for messages), ``base`` (its folder), and
    the error class to raise."""

    def __init__(self, where: str, base: str, error=SceneError):
        self.where, self.base, self.error = where, base, error

    def fail(self, msg: str):
        raise self.error(f"{self.where}: {msg}")


def _show(v) -> str:
    r = repr(v)
    return r if len(r) <= 80 else r[:77] + "..."


# -- checkers: (value, key, ctx) -> normalised value ------------------------------------------
def is_number(v) -> bool:
    """A finite int or float (not a bool)."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return False
    try:
        return math.isfinite(float(v))
    except OverflowError:
        return False


def number(lo: Optional[float] = None, hi: Optional[float] = None, *, open_lo: bool = False, integer: bool = False):
    """A finite number (or an int when ``integer``) in [lo, hi] (or (lo, hi] when ``open_lo``)."""
    what = "an integer" if integer else "a finite number"
    show = (lambda b: str(b)) if integer else (lambda b: f"{b:g}")  # noqa: E731
    if lo is not None:
        what += f" {'>' if open_lo else '>='} {show(lo)}"
    if hi is not None:
        what += f" {'and ' if lo is not None else ''}<= {show(hi)}"

    def check(v, key, ctx):
        ok = is_number(v) and (isinstance(v, int) or not integer)
        ok = ok and (lo is None or (v > lo if open_lo else v >= lo)) and (hi is None or v <= hi)
        if not ok:
            ctx.fail(f"{key} must be {what}; got {_show(v)}")
        if not integer and abs(v) > MAX_MAGNITUDE:
            ctx.fail(f"{key} = {v!r} is outside what this library runs: a number's magnitude must be at most "
                     f"{MAX_MAGNITUDE:g}")
        return v

    return check


POSITIVE, NONNEG, ANY_NUMBER = number(0, open_lo=True), number(0), number()


def integer(lo: int = 1, hi: Optional[int] = None):
    return number(lo, hi, integer=True)


def boolean(v, key, ctx):
    if not isinstance(v, bool):
        ctx.fail(f"{key} must be true or false; got {_show(v)}")
    return v


def one_of(*choices):
    def check(v, key, ctx):
        if not isinstance(v, str) or v not in choices:
            ctx.fail(f"{key} must be one of {list(choices)}; got {_show(v)}")
        return v

    return check


def string(v, key, ctx):
    if not isinstance(v, str):
        ctx.fail(f"{key} must be a string; got {_show(v)}")
    return v


def vec3(nonzero: bool = False):
    def check(v, key, ctx):
        if not (isinstance(v, (list, tuple)) and len(v) == 3 and all(is_number(c) for c in v)):
            ctx.fail(f"{key} must be a list of three numbers; got {_show(v)}")
        if nonzero and not any(float(c) for c in v):
            ctx.fail(f"{key} must be non-zero; got {_show(v)}")
        if any(abs(c) > MAX_MAGNITUDE for c in v):
            ctx.fail(f"{key} = {_show(v)} is outside what this library runs: a number's magnitude must be at most "
                     f"{MAX_MAGNITUDE:g}")
        return [float(c) for c in v]

    return check


def list_of(item: Callable, min_len: int = 1):
    def check(v, key, ctx):
        if not isinstance(v, list) or len(v) < min_len:
            ctx.fail(f"{key} must be a list of at least {min_len} item(s); got {_show(v)}")
        return [item(x, f"{key}[{i}]", ctx) for i, x in enumerate(v)]

    return check


def file_path(exts=None, kind: str = "file"):
    """An existing file (relative to the scene's folder), optionally with one of ``exts``."""

    def check(v, key, ctx):
        if not isinstance(v, str) or not v:
            ctx.fail(f"{key} must be a file path string; got {_show(v)}")
        allowed = exts() if callable(exts) else exts
        ext = os.path.splitext(v)[1].lower()
        if allowed is not None and ext not in allowed:
            ctx.fail(f"{key}: {v!r} is not a {kind} (extension {ext or 'none'}; known: {' '.join(sorted(allowed))})")
        p = v if os.path.isabs(v) else os.path.join(ctx.base, v)
        if not os.path.isfile(p):
            ctx.fail(f"{key}: no such file {v!r} (looked for {p})")
        return p

    return check


def _matrix(v, rows: int, cols: int, key: str, ctx) -> np.ndarray:
    if not (isinstance(v, list) and len(v) == rows and all(
            isinstance(r, list) and len(r) == cols and all(is_number(c) for c in r) for r in v)):
        ctx.fail(f"{key} must be a {rows}x{cols} nested list of numbers (rows); got {_show(v)}")
    return np.asarray(v, dtype=np.float64)


def check_rotation(r: np.ndarray, key: str, fail: Callable[[str], None], tol: float = ROTATION_TOLERANCE) -> None:
    """Fail unless ``r`` (3, 3) is a rotation: |RᵀR − I| <= tol (max entry) and det R = +1."""
    err = float(np.abs(r.T @ r - np.eye(3)).max())
    if not err <= tol:
        fail(f"{key} is not a rotation matrix: its rows are not orthonormal (max |R^T R - I| = {err:.2g}, "
             f"tolerance {tol:g}; write the entries with at least 6 significant digits)")
    det = float(np.linalg.det(r))
    if det < 0:
        fail(f"{key} is not a rotation matrix: det = {det:.6g} (a reflection; a rotation has det = +1)")


def _nearest_rotation(r: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(r)
    return u @ vt


def rotation(v, key, ctx):
    """A 3x3 rotation (rows), checked to ``ROTATION_TOLERANCE`` and returned as the nearest exact
    rotation (so later float64 checks of orthonormality pass)."""
    r = _matrix(v, 3, 3, key, ctx)
    check_rotation(r, key, ctx.fail)
    return _nearest_rotation(r).tolist()


def transform(v, key, ctx):
    """A rigid transform: a 4x4 nested list [[R, t], [0, 0, 0, 1]] or a table ``{rotation = 3x3,
    translation = [3]}`` (either may be left out). Returns ``{"rotation", "translation"}``."""
    if isinstance(v, dict):
        t = _table(v, {"rotation": (rotation, np.eye(3).tolist()), "translation": (vec3(), [0.0, 0.0, 0.0])},
                   key.strip("[]").replace("].", "."), ctx)
        return t
    m = _matrix(v, 4, 4, key, ctx)
    if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9, rtol=0):
        ctx.fail(f"{key}: the last row of a 4x4 transform must be [0, 0, 0, 1]; got {m[3].tolist()}")
    check_rotation(m[:3, :3], f"{key} (its upper-left 3x3)", ctx.fail)
    return {"rotation": _nearest_rotation(m[:3, :3]).tolist(), "translation": m[:3, 3].tolist()}


def _table(d, spec: Dict[str, tuple], section: str, ctx) -> dict:
    """Check table ``d`` against ``spec`` (key -> (checker, default)); returns the checked copy
    with defaults filled in (``_ABSENT``: none)."""
    if not isinstance(d, dict):
        ctx.fail(f"[{section}] must be a table; got {_show(d)}")
    unknown = sorted(str(k) for k in d if k not in spec)
    if unknown:
        ctx.fail(f"unknown key(s) {unknown} in [{section}]; allowed: {sorted(spec)}")
    prefix = "" if section == "top level" else f"[{section}]."
    out = {}
    for k, (check, default) in spec.items():
        if k in d:
            out[k] = check(d[k], prefix + k, ctx)
            check_range(out[k], prefix + k, ctx.fail)  # sizes and magnitudes this library runs
        elif default is not _ABSENT:
            out[k] = copy.deepcopy(default)
    return out


def check_table(d, spec: Dict[str, tuple], section: str, where: str, base: str = ".", error=SceneError) -> dict:
    """Check table ``d`` against ``spec`` (key -> (checker, default or ``ABSENT``)); raises
    ``error`` naming ``where`` and the key. Returns the checked copy with defaults filled in."""
    return _table(d, spec, section, _Ctx(where, base, error))


def _construct(fn, args: dict, section: str, ctx, prefix: str = ""):
    """Call a constructor with checked arguments; its ValueError/TypeError becomes a SceneError."""
    try:
        return fn(**args)
    except _CAUGHT as err:
        msg = str(err).replace(prefix, f"[{section}].") if prefix else str(err)
        ctx.fail(msg if msg.startswith(f"[{section}]") else f"[{section}]: {msg}")
