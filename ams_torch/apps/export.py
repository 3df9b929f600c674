"""Animated USD out: a simulated sequence as a USD stage (hair curves, head and colliders).

:func:`export_usd` reads a sequence HDF5 written by :func:`ams_torch.apps.cli.write_sequence`
and writes ``.usd``/``.usdc`` (binary crate) or ``.usda`` (text) with:

- stage metadata ``metersPerUnit = 1``, ``upAxis = Y``, ``timeCodesPerSecond =
  framesPerSecond = 1/dt``, ``startTimeCode``/``endTimeCode``; sequence frame k (0-based, the
  state after step k + 1) is time code k + 1, i.e. (k + 1)·dt seconds;
- ``/World/Hair``: one linear, non-periodic ``BasisCurves`` with constant
  ``curveVertexCounts`` (N per strand), time-sampled ``points`` (the HDF5 frames, float32,
  metres, world frame, exactly) and ``extent`` (including the half width), and ``widths``
  (constant 70 µm by default; a float sets it, an (N,) or (S, N) array gives per-point
  widths with vertex interpolation);
- ``/World/Head``: the head as a ``Mesh`` in its own frame with a time-sampled
  ``xformOp:transform`` from the head poses (R, T) (omitted when the scene's head is "none");
- ``/World/Colliders/<type>_<i>``: each collider as a ``Mesh`` (analytic shapes tessellated:
  sphere, capsule, a finite 2 m × 2 m quad for a plane, the hollow sphere's shell with its cut
  and rounded rim) with a time-sampled ``xformOp:transform`` from the collider poses.

:func:`export_usd_arrays` does the same from arrays in memory. The stage is written under a
temporary name and moved into place (no half-written files).
"""
from __future__ import annotations

import inspect
import json
import math
import os
from typing import Optional

import numpy as np

__all__ = ["export_usd", "export_usd_arrays", "collider_mesh", "head_mesh_for_scene", "DEFAULT_WIDTH",
           "PLANE_SIZE"]

#: default strand diameter written to USD, metres
DEFAULT_WIDTH = 7e-5
#: side of the square drawn for an (infinite) plane collider, metres
PLANE_SIZE = 2.0


def _pxr():
    try:
        from pxr import Gf, Usd, UsdGeom, Vt
    except ImportError as err:
        raise ImportError("export_usd needs usd-core (pip install usd-core)") from err
    return Gf, Usd, UsdGeom, Vt


# --------------------------------------------------------------------------------------------
# geometry of heads and colliders
# --------------------------------------------------------------------------------------------
def head_mesh_for_scene(scene: dict):
    """The scene's head as a ``trimesh.Trimesh`` in the head frame (metres), or None.

    ``[head].mesh``: "default" → :func:`ams_torch.grooms.head.default_head` (``subdivisions``,
    default 4), "sphere" → an icosphere of ``radius`` (default 0.1 m), "none" → None, else a
    mesh file read with :func:`ams_torch.geometry.mesh.load_mesh` and the head's import keys
    (``units``, ``scale``, ``up_axis``, ``transform``) when the scene has them.
    """
    import trimesh

    head = scene.get("head", {}) or {}
    kind = head.get("mesh", "default")
    if kind == "none":
        return None
    if kind == "default":
        from ams_torch.grooms.head import default_head

        return default_head(int(head.get("subdivisions", 4)))
    if kind == "sphere":
        return trimesh.creation.icosphere(subdivisions=3, radius=float(head.get("radius", 0.1)))
    from ams_torch.geometry.mesh import load_mesh

    return load_mesh(kind, units=head.get("units"), scale=head.get("scale"), up_axis=head.get("up_axis", "y"),
                     transform=head.get("transform"))


def _collider_defaults(kind: str) -> dict:
    from ams_torch.stages import collide

    cls = {"sphere": collide.SphereCollider, "capsule": collide.CapsuleCollider, "plane": collide.PlaneCollider,
           "hollow_sphere": collide.HollowSphereCollider}.get(kind)
    if cls is None:
        raise ValueError(f"collider type must be sphere, capsule, plane or hollow_sphere; got {kind!r}")
    return {k: p.default for k, p in inspect.signature(cls.__init__).parameters.items()
            if p.default is not inspect.Parameter.empty}


def _frame(axis: np.ndarray):
    """Two unit vectors (e1, e2) completing ``axis`` to a right-handed frame (e1, axis, e2)."""
    helper = np.array([0.0, 0.0, 1.0]) if abs(axis[0]) > 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = np.cross(helper, axis)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(e1, axis)


def _revolve(profile: np.ndarray, center, axis, segments: int = 48):
    """Closed surface of revolution: ``profile`` (J, 2) rows (ρ, y), first and last on the
    axis (ρ = 0), revolved about ``axis`` through ``center``. Returns (vertices, faces)."""
    import trimesh

    e1, e2 = _frame(axis)
    rings = profile[1:-1]
    a = 2 * np.pi * np.arange(segments) / segments
    ring_pts = (rings[:, :1, None] * (np.cos(a)[None, :, None] * e1 + np.sin(a)[None, :, None] * e2)
                + rings[:, 1:2, None] * axis)  # (J-2, segments, 3)
    verts = np.concatenate([[profile[0, 1] * axis], ring_pts.reshape(-1, 3), [profile[-1, 1] * axis]], 0)
    verts = verts + np.asarray(center, dtype=np.float64)
    nr = len(rings)
    faces = []
    k = np.arange(segments)
    k1 = (k + 1) % segments
    faces.append(np.stack([np.zeros(segments, np.int64), 1 + k1, 1 + k], 1))
    for j in range(nr - 1):
        r0, r1 = 1 + j * segments, 1 + (j + 1) * segments
        faces.append(np.stack([r0 + k, r0 + k1, r1 + k1], 1))
        faces.append(np.stack([r0 + k, r1 + k1, r1 + k], 1))
    last = len(verts) - 1
    r0 = 1 + (nr - 1) * segments
    faces.append(np.stack([np.full(segments, last), r0 + k, r0 + k1], 1))
    mesh = trimesh.Trimesh(verts, np.concatenate(faces, 0), process=False)
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def collider_mesh(spec: dict):
    """A ``trimesh.Trimesh`` of a scene collider in its local frame (metres).

    spec: a scene collider dict (``type`` and its geometry keys; missing keys take the
    collider class's defaults). Sphere: icosphere; capsule: trimesh's capsule from a to b; plane:
    a :data:`PLANE_SIZE` square centred on ``point`` facing ``normal``; hollow sphere: the
    shell between radius ± thickness/2, cut at ``cut_height`` along ``axis`` with its rounded
    rim (closed shell: two spheres, the inner one facing inward).
    """
    import trimesh

    kind = spec.get("type")
    g = _collider_defaults(kind)
    g.update({k: v for k, v in spec.items() if k not in ("type", "motion", "friction", "follow_head")})
    if kind == "sphere":
        m = trimesh.creation.icosphere(subdivisions=3, radius=float(g["radius"]))
        m.apply_translation(np.asarray(g["center"], dtype=np.float64))
        return m
    if kind == "capsule":
        a, b = np.asarray(g["a"], dtype=np.float64), np.asarray(g["b"], dtype=np.float64)
        d = b - a
        length = float(np.linalg.norm(d))
        if length == 0:
            m = trimesh.creation.icosphere(subdivisions=3, radius=float(g["radius"]))
        else:
            m = trimesh.creation.capsule(height=length, radius=float(g["radius"]), count=[32, 32])
            m.apply_transform(trimesh.geometry.align_vectors([0.0, 0.0, 1.0], d / length))
        m.apply_translation(0.5 * (a + b))
        return m
    if kind == "plane":
        n = np.asarray(g["normal"], dtype=np.float64)
        n = n / np.linalg.norm(n)
        u, v = _frame(n)
        p = np.asarray(g["point"], dtype=np.float64)
        h = 0.5 * PLANE_SIZE
        corners = np.stack([p - h * u - h * v, p + h * u - h * v, p + h * u + h * v, p - h * u + h * v])
        faces = np.array([[0, 1, 2], [0, 2, 3]])
        if np.dot(np.cross(corners[1] - corners[0], corners[2] - corners[0]), n) < 0:
            faces = faces[:, ::-1]
        return trimesh.Trimesh(corners, faces, process=False)
    # hollow sphere
    r, t = float(g["radius"]), float(g["thickness"])
    axis = np.asarray(g["axis"], dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    center = np.asarray(g["center"], dtype=np.float64)
    ro, ri = r + 0.5 * t, r - 0.5 * t
    if g["cut_height"] is None:
        outer = trimesh.creation.icosphere(subdivisions=3, radius=ro)
        inner = trimesh.creation.icosphere(subdivisions=3, radius=ri)
        inner.invert()
        m = trimesh.util.concatenate([outer, inner])
        m.apply_translation(center)
        return m
    h = float(g["cut_height"])
    phic = math.acos(-h / r)
    phi_out = np.linspace(0.0, phic, 33)[:-1]
    u = np.array([math.sin(phic), -math.cos(phic)])
    tau = np.array([math.cos(phic), math.sin(phic)])
    beta = np.linspace(0.0, np.pi, 13)
    rim = r * u + 0.5 * t * (np.cos(beta)[:, None] * u + np.sin(beta)[:, None] * tau)
    phi_in = np.linspace(phic, 0.0, 33)[1:]
    profile = np.concatenate([np.stack([ro * np.sin(phi_out), -ro * np.cos(phi_out)], 1), rim,
                              np.stack([ri * np.sin(phi_in), -ri * np.cos(phi_in)], 1)], 0)
    profile[0, 0] = profile[-1, 0] = 0.0
    return _revolve(profile, center, axis)


# --------------------------------------------------------------------------------------------
# writing
# --------------------------------------------------------------------------------------------
def _matrix(Gf, rotation, translation):
    """Gf.Matrix4d of x ↦ R x + T (USD matrices act on row vectors: rows hold Rᵀ, then T)."""
    m = np.eye(4)
    m[:3, :3] = np.asarray(rotation, dtype=np.float64).T
    m[3, :3] = np.asarray(translation, dtype=np.float64)
    return Gf.Matrix4d(m.tolist())


def _mesh_prim(stage, UsdGeom, Vt, path: str, mesh):
    prim = UsdGeom.Mesh.Define(stage, path)
    v = np.ascontiguousarray(mesh.vertices, dtype=np.float32)
    prim.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(v))
    prim.CreateFaceVertexCountsAttr(Vt.IntArray([3] * len(mesh.faces)))
    prim.CreateFaceVertexIndicesAttr(Vt.IntArray(np.asarray(mesh.faces, dtype=np.int64).ravel().tolist()))
    prim.CreateExtentAttr(Vt.Vec3fArray.FromNumpy(np.stack([v.min(0), v.max(0)]).astype(np.float32)))
    prim.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    prim.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
    return prim


def _check_shape(name, arr, shape):
    if arr is None:
        return
    got = tuple(np.shape(arr))
    if len(got) != len(shape) or any(s is not None and g != s for g, s in zip(got, shape)):
        want = "(" + ", ".join("?" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"export_usd: {name} must have shape {want}; got {got}")


def export_usd_arrays(usd_path: str, positions, dt: float, *, rotations=None, translations=None,
                      scene: Optional[dict] = None, head_mesh=None, collider_rotations=None,
                      collider_translations=None, every: int = 1, width=None, progress: bool = False) -> str:
    """Write an animated USD stage from arrays (see the module docstring for its layout).

    Args:
        usd_path: output ``.usd``/``.usdc``/``.usda``.
        positions: (F, S, N, 3) float metres, world frame (array or an h5py dataset; read one
            frame at a time).
        dt: seconds per frame (> 0).
        rotations, translations: head poses (F, 3, 3), (F, 3) metres (default identity).
        scene: the validated scene dict (its ``head`` and ``colliders``), optional.
        head_mesh: a ``trimesh.Trimesh`` in the head frame to use instead of the scene's head
            (``False``: no head).
        collider_rotations, collider_translations: (F, C, 3, 3), (F, C, 3) metres world poses
            of the scene's C colliders (required when the scene has colliders).
        every: write every k-th frame (k ≥ 1).
        width: strand diameter, metres: None (70 µm), a float, or (N,) / (S, N) per point.
        progress: show a tqdm bar.

    Returns:
        ``usd_path``.
    """
    Gf, Usd, UsdGeom, Vt = _pxr()
    scene = scene or {}
    shape = tuple(np.shape(positions))
    if len(shape) != 4 or shape[-1] != 3:
        raise ValueError(f"export_usd: positions must be (F, S, N, 3); got {shape}")
    frames, s, n = shape[:3]
    dt = float(dt)
    if not (math.isfinite(dt) and dt > 0):
        raise ValueError(f"export_usd: dt must be a positive number of seconds; got {dt!r}")
    if isinstance(every, bool) or not isinstance(every, (int, np.integer)) or every < 1:
        raise ValueError(f"export_usd: every must be a positive integer; got {every!r}")
    ext = os.path.splitext(usd_path)[1].lower()
    if ext not in (".usd", ".usda", ".usdc"):
        raise ValueError(f"{usd_path}: the USD file must end in .usd, .usda or .usdc")
    _check_shape("rotations", rotations, (frames, 3, 3))
    _check_shape("translations", translations, (frames, 3))
    specs = list(scene.get("colliders", []) or [])
    if specs:
        if collider_rotations is None or collider_translations is None:
            raise ValueError("export_usd: the scene has colliders but no collider_rotations/collider_translations")
        _check_shape("collider_rotations", collider_rotations, (frames, len(specs), 3, 3))
        _check_shape("collider_translations", collider_translations, (frames, len(specs), 3))
    if width is None:
        width = DEFAULT_WIDTH
    w = np.asarray(width, dtype=np.float64)
    if w.ndim == 0:
        per_point = None
        if not (math.isfinite(float(w)) and w > 0):
            raise ValueError(f"export_usd: width must be a positive number of metres; got {width!r}")
    else:
        try:
            per_point = np.broadcast_to(w, (s, n)).astype(np.float32).ravel()
        except ValueError:
            raise ValueError(f"export_usd: width must be a float or broadcast to (S, N) = ({s}, {n}); got shape "
                             f"{w.shape}") from None
        if not (np.all(np.isfinite(per_point)) and np.all(per_point > 0)):
            raise ValueError("export_usd: widths must be positive and finite")
    picks = list(range(0, frames, int(every)))
    if head_mesh is None:
        head_mesh = head_mesh_for_scene(scene)
    meshes = [collider_mesh(c) for c in specs]

    from ams_torch.apps.atomic import atomic_path

    def verify(tmp: str) -> None:  # the stage opens and holds every frame's points
        try:
            back = Usd.Stage.Open(tmp)
            samples = UsdGeom.BasisCurves(back.GetPrimAtPath("/World/Hair")).GetPointsAttr().GetNumTimeSamples()
        except RuntimeError as err:
            raise _usd_error(usd_path, err) from None
        if samples != len(picks):
            raise _usd_error(usd_path, f"the stage read back holds {samples} frames of points, {len(picks)} were written")

    with atomic_path(usd_path, verify=verify) as tmp:
        try:
            stage = Usd.Stage.CreateNew(tmp)
            UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
            UsdGeom.SetStageMetersPerUnit(stage, 1.0)
            stage.SetTimeCodesPerSecond(1.0 / dt)
            stage.SetFramesPerSecond(1.0 / dt)
            if picks:
                stage.SetStartTimeCode(picks[0] + 1)
                stage.SetEndTimeCode(picks[-1] + 1)
            world = UsdGeom.Xform.Define(stage, "/World")
            stage.SetDefaultPrim(world.GetPrim())
            stage.GetRootLayer().customLayerData = {"ams_torch:dt": dt, "ams_torch:every": int(every),
                                                    "ams_torch:frames": int(frames)}
            hair = UsdGeom.BasisCurves.Define(stage, "/World/Hair")
            hair.CreateTypeAttr(UsdGeom.Tokens.linear)
            hair.CreateWrapAttr(UsdGeom.Tokens.nonperiodic)
            hair.CreateCurveVertexCountsAttr(Vt.IntArray([int(n)] * s))
            if per_point is None:
                widths = Vt.FloatArray([float(w)])
                hair.CreateWidthsAttr(widths)
                hair.SetWidthsInterpolation(UsdGeom.Tokens.constant)
            else:
                widths = Vt.FloatArray.FromNumpy(per_point)
                hair.CreateWidthsAttr(widths)
                hair.SetWidthsInterpolation(UsdGeom.Tokens.vertex)
            points_attr = hair.CreatePointsAttr()
            extent_attr = hair.CreateExtentAttr()
            half = 0.5 * float(np.max(per_point) if per_point is not None else w)
            xf_head = None
            if head_mesh is not None and head_mesh is not False:
                head = _mesh_prim(stage, UsdGeom, Vt, "/World/Head", head_mesh)
                xf_head = head.AddTransformOp()
            xf_cols = []
            if meshes:
                UsdGeom.Scope.Define(stage, "/World/Colliders")
                for i, (spec, m) in enumerate(zip(specs, meshes)):
                    prim = _mesh_prim(stage, UsdGeom, Vt, f"/World/Colliders/{spec['type']}_{i}", m)
                    xf_cols.append(prim.AddTransformOp())
            it = picks
            if progress:
                from tqdm.auto import tqdm

                it = tqdm(picks, desc=f"exporting {os.path.basename(usd_path)}", unit="frame")
            for k in it:
                tc = Usd.TimeCode(k + 1)
                x = np.ascontiguousarray(np.asarray(positions[k], dtype=np.float32).reshape(-1, 3))
                points_attr.Set(Vt.Vec3fArray.FromNumpy(x), tc)
                lo, hi = (x.min(0) - half, x.max(0) + half) if len(x) else (np.zeros(3), np.zeros(3))
                extent_attr.Set(Vt.Vec3fArray.FromNumpy(np.stack([lo, hi]).astype(np.float32)), tc)
                if xf_head is not None:
                    r = np.eye(3) if rotations is None else rotations[k]
                    t = np.zeros(3) if translations is None else translations[k]
                    xf_head.Set(_matrix(Gf, r, t), tc)
                for c, op in enumerate(xf_cols):
                    op.Set(_matrix(Gf, collider_rotations[k][c], collider_translations[k][c]), tc)
            stage.GetRootLayer().Save()
        except RuntimeError as err:  # pxr.Tf.ErrorException: a full disk, a folder it cannot write...
            raise _usd_error(usd_path, err) from None
        finally:
            stage = None
    return usd_path


def _usd_error(usd_path: str, err) -> OSError:
    """A WriteError naming the file and USD's own reason (its first error message)."""
    import errno

    from ams_torch.apps.atomic import WriteError

    text = str(err)
    said = [line.split(" : ", 1)[-1].strip().strip("'") for line in text.splitlines() if "Error" in line]
    reason = said[0] if said else " ".join(text.split())
    code = errno.ENOSPC if "No space left" in text else errno.EIO
    return WriteError(code, f"{usd_path}: USD could not write the stage: {reason}")


def export_usd(sequence_path: str, usd_path: str, *, every: int = 1, width=None, progress: bool = False) -> str:
    """Write the sequence HDF5 ``sequence_path`` (from :func:`ams_torch.apps.cli.write_sequence`)
    as an animated USD stage ``usd_path``; returns ``usd_path``.

    every: write every k-th frame; width: strand diameter in metres (None: 70 µm; or (N,) /
    (S, N) per point); progress: a tqdm bar. Frames are read from the file one at a time.

    Raises:
        FileNotFoundError: no such sequence. ValueError naming the file: not a sequence (no
        ``positions``), inconsistent datasets, bad arguments.
    """
    import h5py

    if not os.path.isfile(sequence_path):
        raise FileNotFoundError(f"no such sequence file {sequence_path!r}")
    try:
        f = h5py.File(sequence_path, "r")
    except OSError as err:
        raise ValueError(f"{sequence_path}: not an HDF5 file ({err})") from None
    with f:
        if "positions" not in f:
            raise ValueError(f"{sequence_path}: no 'positions' dataset (not an ams-torch sequence)")
        try:
            scene = json.loads(f.attrs["scene"]) if "scene" in f.attrs else {}
        except (TypeError, ValueError) as err:
            raise ValueError(f"{sequence_path}: the 'scene' attribute is not JSON ({err})") from None
        dt = float(f.attrs.get("dt", 1.0 / 60.0))
        get = (lambda k: f[k][()] if k in f else None)  # noqa: E731 - small pose arrays
        try:
            return export_usd_arrays(usd_path, f["positions"], dt, rotations=get("rotations"),
                                     translations=get("translations"), scene=scene,
                                     collider_rotations=get("collider_rotations"),
                                     collider_translations=get("collider_translations"), every=every, width=width,
                                     progress=progress)
        except ValueError as err:
            if str(err).startswith(sequence_path):
                raise
            raise ValueError(f"{sequence_path}: {err}") from None
