"""USD ``BasisCurves`` (``.usd``, ``.usda``, ``.usdc``) through Pixar's ``usd-core`` (optional).

Writing: one linear ``BasisCurves`` prim ``/Groom/Strands`` with ``curveVertexCounts`` and
``points`` (metres: the stage's ``metersPerUnit`` is 1, up axis Y), constant ``widths``
(``metadata["usd_width"]``, default 70 µm, a hair's diameter). When the groom has a root
binding it is stored as uniform primvars ``ams:rootTriangle`` (int) and
``ams:rootBarycentric`` (float3) and ``ams:rootFaceVertices`` (int3 as 3 ints per curve).

Reading: every ``BasisCurves`` prim on the stage, in traversal order, with its
local-to-world transform applied and the stage's ``metersPerUnit`` converted to metres
(the up axis is recorded in ``metadata["usd_up_axis"]``, not changed).

Install with ``pip install usd-core`` (the ``usd`` extra of ams_torch).
"""
from __future__ import annotations

import re

import numpy as np

from ams_torch.grooms.io._common import concat_strands, fail, split_points


def _pxr(path):
    try:
        from pxr import Gf, Sdf, Tf, Usd, UsdGeom, Vt
    except ImportError as err:
        raise ImportError(f"{path}: reading/writing USD needs usd-core (pip install usd-core)") from err
    return Gf, Sdf, Tf, Usd, UsdGeom, Vt


def write_usd(path, strands, metadata=None, binding=None) -> None:
    """Write polylines (metres) as a linear BasisCurves prim; ``binding`` = optional dict of arrays."""
    Gf, Sdf, Tf, Usd, UsdGeom, Vt = _pxr(path)
    metadata = metadata or {}
    pts, counts = concat_strands(strands)
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    root = UsdGeom.Xform.Define(stage, "/Groom")
    stage.SetDefaultPrim(root.GetPrim())
    curves = UsdGeom.BasisCurves.Define(stage, "/Groom/Strands")
    curves.CreateTypeAttr(UsdGeom.Tokens.linear)
    curves.CreateCurveVertexCountsAttr(Vt.IntArray([int(c) for c in counts]))
    curves.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(pts, dtype=np.float32)))
    curves.CreateWidthsAttr(Vt.FloatArray([float(metadata.get("usd_width", 7e-5))]))
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


def read_usd(path):
    """USD stage → (list of (n_i, 3) float32 arrays, metadata dict, binding dict or None)."""
    Gf, Sdf, Tf, Usd, UsdGeom, Vt = _pxr(path)
    try:
        stage = Usd.Stage.Open(str(path))
    except Tf.ErrorException as err:
        msg = " ".join(str(err).split())
        found = re.search(r"in file \S+ : (.*?)(?: Error in '|$)", msg)
        msg = found.group(1) if found else msg
        raise fail(path, f"corrupt or unreadable USD file ({msg[:300]})") from None
    if stage is None:
        raise fail(path, "corrupt or unreadable USD file (the stage did not open)")
    scale = float(UsdGeom.GetStageMetersPerUnit(stage))
    strands, binding_parts = [], []
    time = Usd.TimeCode.Default()
    n_prims = 0
    for prim in stage.Traverse():
        if not prim.IsA(UsdGeom.BasisCurves):
            continue
        n_prims += 1
        curves = UsdGeom.BasisCurves(prim)
        counts = np.asarray(curves.GetCurveVertexCountsAttr().Get(time) or [], dtype=np.int64)
        pts = np.asarray(curves.GetPointsAttr().Get(time) or [], dtype=np.float64).reshape(-1, 3)
        if int(counts.sum()) != len(pts):
            raise fail(path, f"corrupt USD file: {prim.GetPath()} has curveVertexCounts adding up to "
                             f"{int(counts.sum())} but {len(pts)} points")
        xf = np.asarray(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(time), dtype=np.float64)
        pts = (pts @ xf[:3, :3] + xf[3, :3]) * scale  # USD matrices act on row vectors
        strands += [s.astype(np.float32) for s in split_points(pts, counts)]
        api = UsdGeom.PrimvarsAPI(prim)
        tri = api.GetPrimvar("ams:rootTriangle")
        bary = api.GetPrimvar("ams:rootBarycentric")
        fv = api.GetPrimvar("ams:rootFaceVertices")
        if tri and bary and fv and tri.Get() is not None:
            binding_parts.append(dict(root_triangles=np.asarray(tri.Get(), dtype=np.int64),
                                      root_barycentrics=np.asarray(bary.Get(), dtype=np.float32),
                                      root_face_vertices=np.asarray(fv.Get(), dtype=np.int64).reshape(-1, 3)))
        else:
            binding_parts.append(None)
    if n_prims == 0:
        raise fail(path, "USD file has no BasisCurves prim")
    binding = None
    if all(b is not None for b in binding_parts):
        binding = {k: np.concatenate([b[k] for b in binding_parts], 0) for k in binding_parts[0]}
    up = str(UsdGeom.GetStageUpAxis(stage))
    return strands, dict(usd_up_axis=up, usd_meters_per_unit=scale), binding
