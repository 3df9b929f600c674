"""USD ``BasisCurves`` (``.usd``, ``.usda``, ``.usdc``) through Pixar's ``usd-core`` (optional).

Writing: one linear ``BasisCurves`` prim ``/Groom/Strands`` with ``curveVertexCounts`` and
``points`` (metres: the stage's ``metersPerUnit`` is 1, up axis Y), ``widths`` (the groom's
width, constant; or per point, vertex interpolation, when ``metadata["usd_widths"]`` has one
value per point). When the groom has a root binding it is stored as uniform primvars
``ams:rootTriangle`` (int), ``ams:rootBarycentric`` (float3) and ``ams:rootFaceVertices`` (int
with element size 3).

Reading: every ``BasisCurves`` prim on the stage, in traversal order, with its local-to-world
transform applied, then the stage's declared units and axes:

- ``metersPerUnit``, when the stage authors it, converts to metres (a stage that does not
  author it is taken as stored: USD's schema fallback is centimetres, but files without the
  metadata usually come from tools that never set it; pass ``units=`` to :func:`read_groom`).
- ``upAxis = Z`` is turned to +y up by the proper rotation (x, y, z) → (x, z, −y).
- The curve ``type`` and ``basis``: linear curves are read as they are; cubic ``bezier``,
  ``bspline`` and ``catmullRom`` curves are evaluated to polylines, :data:`SPAN_SAMPLES` = 8
  segments per cubic span, uniform in the span's parameter (so a B-spline no longer comes back
  as its control points). The deprecated ``hermite``/``power`` bases raise.
- ``wrap``: ``nonperiodic`` as the basis says (a cubic B-spline/Catmull-Rom then starts at its
  second span point, not at the first control point); ``pinned`` adds USD's phantom end points
  (2 P0 − P1 and 2 Pn−1 − Pn−2) so B-splines and Catmull-Rom curves reach their end points;
  ``periodic`` (closed) curves raise ``GroomFileError``: a closed loop has no root.
- ``widths``: kept (metres) in ``metadata["usd_widths"]`` with
  ``metadata["usd_widths_interpolation"]``; their median becomes the groom's width.
- ``points`` with only time samples: the first time sample is read (and every other attribute
  at that time); ``metadata["usd_time"]`` says which.

Install with ``pip install usd-core`` (the ``usd`` extra of ams_torch).
"""
from __future__ import annotations

import re
from typing import Dict, List, Optional

import numpy as np

from ams_torch.grooms.io._common import concat_strands, fail, split_points

#: segments per cubic span when a cubic curve is converted to a polyline
SPAN_SAMPLES = 8

# cubic bases as 4×4 matrices M: point(t) = [t³, t², t, 1] · M · [P0, P1, P2, P3]
_BASES = {
    "bezier": (3, np.array([[-1, 3, -3, 1], [3, -6, 3, 0], [-3, 3, 0, 0], [1, 0, 0, 0]], dtype=np.float64)),
    "bspline": (1, np.array([[-1, 3, -3, 1], [3, -6, 3, 0], [-3, 0, 3, 0], [1, 4, 1, 0]], dtype=np.float64) / 6.0),
    "catmullRom": (1, np.array([[-1, 3, -3, 1], [2, -5, 4, -1], [-1, 0, 1, 0], [0, 2, 0, 0]], dtype=np.float64) / 2.0),
}


def _pxr(path):
    try:
        from pxr import Gf, Sdf, Tf, Usd, UsdGeom, Vt
    except ImportError as err:
        raise ImportError(f"{path}: reading/writing USD needs usd-core (pip install usd-core)") from err
    return Gf, Sdf, Tf, Usd, UsdGeom, Vt


def write_usd(path, strands, metadata=None, binding=None, width: float = 7e-5) -> None:
    """Write polylines (metres) as a linear BasisCurves prim; ``binding`` = optional dict of arrays;
    ``width``: strand diameter, metres (constant widths)."""
    Gf, Sdf, _, Usd, UsdGeom, Vt = _pxr(path)
    metadata = metadata or {}
    pts, counts = concat_strands(strands)
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    root = UsdGeom.Xform.Define(stage, "/Groom")
    stage.SetDefaultPrim(root.GetPrim())
    curves = UsdGeom.BasisCurves.Define(stage, "/Groom/Strands")
    curves.CreateTypeAttr(UsdGeom.Tokens.linear)
    curves.CreateWrapAttr(UsdGeom.Tokens.nonperiodic)
    curves.CreateCurveVertexCountsAttr(Vt.IntArray([int(c) for c in counts]))
    curves.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(pts, dtype=np.float32)))
    if len(pts):
        curves.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, pts.min(0))), Gf.Vec3f(*map(float, pts.max(0)))]))
    per_point = metadata.get("usd_widths")
    if per_point is not None and np.asarray(per_point).size == len(pts) and len(pts) > 1:
        curves.CreateWidthsAttr(Vt.FloatArray.FromNumpy(np.ascontiguousarray(per_point, dtype=np.float32).ravel()))
        curves.SetWidthsInterpolation(UsdGeom.Tokens.vertex)
    else:
        curves.CreateWidthsAttr(Vt.FloatArray([float(width)]))
        curves.SetWidthsInterpolation(UsdGeom.Tokens.constant)
    if binding is not None:
        api = UsdGeom.PrimvarsAPI(curves.GetPrim())
        api.CreatePrimvar("ams:rootTriangle", Sdf.ValueTypeNames.IntArray, UsdGeom.Tokens.uniform).Set(
            Vt.IntArray([int(t) for t in binding["root_triangles"]]))
        api.CreatePrimvar("ams:rootBarycentric", Sdf.ValueTypeNames.Float3Array, UsdGeom.Tokens.uniform).Set(
            Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(binding["root_barycentrics"], dtype=np.float32)))
        pv = api.CreatePrimvar("ams:rootFaceVertices", Sdf.ValueTypeNames.IntArray, UsdGeom.Tokens.uniform)
        pv.SetElementSize(3)
        pv.Set(Vt.IntArray([int(i) for i in np.asarray(binding["root_face_vertices"]).reshape(-1)]))
    stage.GetRootLayer().Save()


# --------------------------------------------------------------------------------------------
# cubic curves → polylines
# --------------------------------------------------------------------------------------------
def cubic_to_polyline(control: np.ndarray, basis: str, wrap: str, samples: int = SPAN_SAMPLES) -> np.ndarray:
    """Evaluate one cubic USD curve to a polyline.

    control: (n, 3) control points; basis "bezier" | "bspline" | "catmullRom"; wrap
    "nonperiodic" | "pinned". Returns (spans · samples + 1, 3) float64 points, uniform in each
    span's parameter. Raises ``ValueError`` when n does not fit the basis (bezier: 4 + 3k;
    bspline/catmullRom: ≥ 4, or ≥ 2 when pinned).
    """
    step, m = _BASES[basis]
    c = np.asarray(control, dtype=np.float64)
    n = len(c)
    if wrap == "pinned" and basis in ("bspline", "catmullRom"):
        if n < 2:
            raise ValueError(f"a pinned {basis} curve needs at least 2 points; got {n}")
        c = np.concatenate([2 * c[:1] - c[1:2], c, 2 * c[-1:] - c[-2:-1]], 0)
        n = len(c)
    if n < 4 or (n - 4) % step:
        need = "4 + 3k" if step == 3 else "at least 4"
        raise ValueError(f"a {wrap} {basis} curve needs {need} control points; got {len(control)}")
    spans = (n - 4) // step + 1
    idx = np.arange(spans)[:, None] * step + np.arange(4)[None, :]  # (spans, 4)
    t = np.arange(samples, dtype=np.float64) / samples
    powers = np.stack([t ** 3, t ** 2, t, np.ones_like(t)], 1)  # (samples, 4)
    weights = powers @ m  # (samples, 4)
    pts = np.einsum("kj,sjd->skd", weights, c[idx]).reshape(-1, 3)  # (spans · samples, 3)
    end = np.array([1.0, 1.0, 1.0, 1.0]) @ m @ c[idx[-1]]
    return np.concatenate([pts, end[None]], 0)


def _curve_polylines(path, prim_path, pts: np.ndarray, counts: np.ndarray, ctype: str, basis: str,
                     wrap: str) -> List[np.ndarray]:
    if wrap == "periodic":
        raise fail(path, f"{prim_path}: periodic (closed) curves are not read: a closed loop has no root "
                         "(re-export the strands with wrap = nonperiodic)")
    if wrap not in ("nonperiodic", "pinned"):
        raise fail(path, f"corrupt USD file: {prim_path} has an unknown wrap {wrap!r}")
    if ctype == "linear":
        return split_points(pts, counts)
    if ctype != "cubic":
        raise fail(path, f"corrupt USD file: {prim_path} has an unknown curve type {ctype!r}")
    if basis not in _BASES:
        raise fail(path, f"{prim_path}: cubic curves with basis {basis!r} are not supported (bezier, bspline, "
                         "catmullRom are)")
    out = []
    for i, c in enumerate(split_points(pts, counts)):
        try:
            out.append(cubic_to_polyline(c, basis, wrap))
        except ValueError as err:
            raise fail(path, f"corrupt USD file: {prim_path}, curve {i}: {err}") from None
    return out


# --------------------------------------------------------------------------------------------
# reading
# --------------------------------------------------------------------------------------------
def _open_stage(path):
    _, _, Tf, Usd, _, _ = _pxr(path)
    try:
        stage = Usd.Stage.Open(str(path))
    except Tf.ErrorException as err:
        msg = " ".join(str(err).split())
        found = re.search(r"in file \S+ : (.*?)(?: Error in '|$)", msg)
        msg = found.group(1) if found else msg
        raise fail(path, f"corrupt or unreadable USD file ({msg[:300]})") from None
    except UnicodeDecodeError as err:
        raise fail(path, f"corrupt or unreadable USD file: byte {err.start} is not valid UTF-8 text") from None
    if stage is None:
        raise fail(path, "corrupt or unreadable USD file (the stage did not open)")
    return stage


def _values(path, where: str, value, dtype, width: int = 1) -> np.ndarray:
    """An attribute's value as a flat-or-(n, width) numpy array; a corrupt value (wrong type,
    an unregistered type name) is a GroomFileError naming the attribute."""
    if value is None:
        return np.zeros((0, width) if width > 1 else 0, dtype=dtype)
    try:
        arr = np.asarray(value, dtype=dtype)
    except (TypeError, ValueError, OverflowError):
        raise fail(path, f"corrupt USD file: {where} holds a {type(value).__name__}, not an array of numbers") from None
    if width > 1:
        if arr.size % width:
            raise fail(path, f"corrupt USD file: {where} has {arr.size} values, not a multiple of {width}")
        arr = arr.reshape(-1, width)
    elif arr.ndim != 1:
        raise fail(path, f"corrupt USD file: {where} has shape {arr.shape}, expected a flat array")
    return arr


def _read_time(points_attr, Usd):
    """Default time when ``points`` has a default value, else its first time sample."""
    if points_attr.Get(Usd.TimeCode.Default()) is not None:
        return Usd.TimeCode.Default(), None
    times = points_attr.GetTimeSamples()
    if times:
        return Usd.TimeCode(times[0]), float(times[0])
    return Usd.TimeCode.Default(), None


def read_usd(path):
    """USD stage → (list of (n_i, 3) float32 arrays, metadata dict, binding dict or None)."""
    _, _, Tf, Usd, UsdGeom, _ = _pxr(path)
    try:
        return _read_usd(path, Usd, UsdGeom)
    except UnicodeDecodeError as err:
        raise fail(path, f"corrupt or unreadable USD file: byte {err.start} is not valid UTF-8 text") from None
    except Tf.ErrorException as err:
        raise fail(path, f"corrupt or unreadable USD file ({' '.join(str(err).split())[:300]})") from None


def _read_usd(path, Usd, UsdGeom):
    stage = _open_stage(path)
    mpu_authored = bool(stage.HasAuthoredMetadata(UsdGeom.Tokens.metersPerUnit))
    up_authored = bool(stage.HasAuthoredMetadata(UsdGeom.Tokens.upAxis))
    scale = float(UsdGeom.GetStageMetersPerUnit(stage)) if mpu_authored else 1.0
    if not (np.isfinite(scale) and scale > 0):
        raise fail(path, f"corrupt USD file: metersPerUnit = {scale!r}")
    up = str(UsdGeom.GetStageUpAxis(stage))
    if up not in ("Y", "Z"):
        raise fail(path, f"corrupt USD file: upAxis = {up!r} (USD allows Y or Z)")
    strands: List[np.ndarray] = []
    binding_parts, widths, interps, curves_info = [], [], set(), []
    usd_time: Optional[float] = None
    for prim in stage.Traverse():
        if not prim.IsA(UsdGeom.BasisCurves):
            continue
        curves = UsdGeom.BasisCurves(prim)
        name = str(prim.GetPath())
        time, sample = _read_time(curves.GetPointsAttr(), Usd)
        if sample is not None:
            usd_time = sample if usd_time is None else usd_time
        counts = _values(path, f"{name}.curveVertexCounts", curves.GetCurveVertexCountsAttr().Get(time), np.int64)
        pts = _values(path, f"{name}.points", curves.GetPointsAttr().Get(time), np.float64, 3)
        if len(counts) and counts.min() < 0:
            raise fail(path, f"corrupt USD file: {name} has a negative curveVertexCount {int(counts.min())}")
        if int(counts.sum()) != len(pts):
            raise fail(path, f"corrupt USD file: {name} has curveVertexCounts adding up to "
                             f"{int(counts.sum())} but {len(pts)} points")
        ctype = str(curves.GetTypeAttr().Get(time))
        basis = str(curves.GetBasisAttr().Get(time))
        wrap = str(curves.GetWrapAttr().Get(time))
        xf = np.asarray(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(time), dtype=np.float64)
        if xf.shape != (4, 4) or not np.all(np.isfinite(xf)):
            raise fail(path, f"corrupt USD file: {name} has a non-finite transform")
        pts = pts @ xf[:3, :3] + xf[3, :3]  # USD matrices act on row vectors
        polylines = _curve_polylines(path, name, pts, counts, ctype, basis, wrap)
        strands += polylines
        curves_info.append(dict(prim=name, type=ctype, basis=basis if ctype == "cubic" else None, wrap=wrap,
                                curves=int(len(counts))))
        w = _values(path, f"{name}.widths", curves.GetWidthsAttr().Get(time), np.float64)
        if len(w):
            widths.append(w)
            interps.add(str(curves.GetWidthsInterpolation()))
        api = UsdGeom.PrimvarsAPI(prim)
        tri = api.GetPrimvar("ams:rootTriangle")
        bary = api.GetPrimvar("ams:rootBarycentric")
        fv = api.GetPrimvar("ams:rootFaceVertices")
        if tri and bary and fv and tri.Get() is not None:
            part = dict(root_triangles=_values(path, f"{name}.ams:rootTriangle", tri.Get(), np.int64),
                        root_barycentrics=_values(path, f"{name}.ams:rootBarycentric", bary.Get(), np.float32, 3),
                        root_face_vertices=_values(path, f"{name}.ams:rootFaceVertices", fv.Get(), np.int64, 3))
            if any(len(v) != len(counts) for v in part.values()):
                raise fail(path, f"corrupt USD file: {name} has root binding primvars of the wrong length "
                                 f"(expected one per curve, {len(counts)})")
            binding_parts.append(part)
        else:
            binding_parts.append(None)
    if not curves_info:
        raise fail(path, "USD file has no BasisCurves prim")
    rot = np.eye(3)
    if up == "Z":
        rot = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
    out = [((s @ rot.T) * scale).astype(np.float32) for s in strands]
    binding = None
    if all(b is not None for b in binding_parts):
        binding = {k: np.concatenate([b[k] for b in binding_parts], 0) for k in binding_parts[0]}
    meta: Dict = dict(usd_up_axis=up, usd_meters_per_unit=scale, usd_meters_per_unit_authored=mpu_authored,
                      usd_up_axis_authored=up_authored, usd_curves=curves_info)
    if usd_time is not None:
        meta["usd_time"] = usd_time
    if widths:
        all_w = np.concatenate(widths) * scale
        if len(interps) == 1:
            meta["usd_widths"] = all_w.astype(np.float32)
            meta["usd_widths_interpolation"] = interps.pop()
        good = all_w[np.isfinite(all_w) & (all_w > 0)]
        if len(good):
            meta["width"] = float(np.median(good))
    return out, meta, binding
