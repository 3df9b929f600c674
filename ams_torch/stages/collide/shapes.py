"""Collider shapes (SPEC §8): solids given by a signed distance in their local frame.

Every collider describes a solid by its signed distance σ (metres, negative inside) and outward
unit normal n = ∇σ/|∇σ| in its own local frame, a rigid ``pose`` (with velocities) and a Coulomb
friction coefficient ``friction`` (μ). A collider with ``follow_head=True`` is attached to the head:
its ``pose`` is relative to the head frame and it moves with the head; otherwise ``pose`` is in
the world. :func:`~ams_torch.stages.collide.resolve_world_poses` turns both kinds into world
poses for a frame, and :func:`~ams_torch.stages.collide.collide` applies the response.

Colliders are ``torch.nn.Module`` s: their geometry, friction and default pose are buffers, so a
simulator that registers them moves them with ``.to()`` / ``.double()``.

Analytic colliders (:class:`SphereCollider`, :class:`HollowSphereCollider`,
:class:`CapsuleCollider`, :class:`PlaneCollider`) evaluate σ exactly; :class:`MeshCollider`
samples an :class:`~ams_torch.geometry.sdf.SDFGrid` built from a triangle mesh (open meshes too: the
sign comes from the generalised winding number), built by :meth:`MeshCollider.build` (the simulator
calls it once; cached on disk), so a scene without colliders never builds a grid.
"""
from __future__ import annotations

import math
from abc import ABC, abstractmethod
from typing import Optional, Tuple

import torch

from ams_torch.geometry.pose import Pose
from ams_torch.geometry.sdf import SDFGrid

__all__ = ["Collider", "SphereCollider", "HollowSphereCollider", "CapsuleCollider", "PlaneCollider", "MeshCollider",
           "DEFAULT_FRICTION"]

DEFAULT_FRICTION = 0.5


def _vec(a, name: str) -> torch.Tensor:
    t = torch.as_tensor(a, dtype=torch.float64).reshape(-1)
    if t.numel() != 3:
        raise ValueError(f"{name} must be a 3-vector, got shape {tuple(torch.as_tensor(a).shape)}")
    return t


def _like(t: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    return t.to(device=p.device, dtype=p.dtype)


def _dot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return (a * b).sum(-1)


def _unit_or(d: torch.Tensor, fallback: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """(d/|d|, |d|) with ``fallback`` (3,) where |d| = 0."""
    length = d.norm(dim=-1)
    unit = d / length.clamp_min(1e-30)[..., None]
    return torch.where((length > 0)[..., None], unit, _like(fallback, d).expand_as(d)), length


_UP = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)


class Collider(torch.nn.Module, ABC):
    """Base class: a rigid solid given by a signed distance in its local frame.

    Attributes:
        friction: () buffer, Coulomb coefficient μ ≥ 0 (dimensionless).
        pose: :class:`~ams_torch.geometry.pose.Pose` of the collider's local frame, relative to the
            head when ``follow_head`` else in the world (default identity, static), kept as buffers
            (``pose_rotation``, ``pose_translation``, ``pose_linear_velocity``,
            ``pose_angular_velocity``). Per-frame poses are given to the step instead (``Control``).
        follow_head: whether the collider moves rigidly with the head.
        projection_iterations: push-out passes per contact response (1 suffices for exact σ).

    Subclasses implement :meth:`distance_and_normal` (and may override :meth:`distance`).
    """

    projection_iterations: int = 1

    def __init__(self, friction: float = DEFAULT_FRICTION, pose: Optional[Pose] = None, follow_head: bool = False):
        super().__init__()
        if not (isinstance(friction, (int, float)) and math.isfinite(friction) and friction >= 0):
            raise ValueError(f"friction must be a finite number ≥ 0; got {friction!r}")
        self.register_buffer("friction", torch.tensor(float(friction), dtype=torch.float64))
        self.follow_head = bool(follow_head)
        self.has_pose = pose is not None
        self.pose = pose if pose is not None else Pose.identity(dtype=torch.float64)

    @property
    def pose(self) -> Pose:
        """The collider's own pose (see the class docstring)."""
        return Pose(self.pose_rotation, self.pose_translation, self.pose_linear_velocity, self.pose_angular_velocity,
                    check=False)

    @pose.setter
    def pose(self, pose: Optional[Pose]) -> None:
        if pose is None:
            pose = Pose.identity(dtype=torch.float64)
        if not isinstance(pose, Pose) or pose.rotation.shape != (3, 3):
            raise ValueError("a collider's own pose must be a single Pose (rotation (3, 3)); give per-frame or "
                             "batched poses to the step (collider_poses)")
        z = torch.zeros(3, dtype=pose.rotation.dtype, device=pose.rotation.device)
        for name, t in (("rotation", pose.rotation), ("translation", pose.translation),
                        ("linear_velocity", pose.linear_velocity if pose.has_velocity else z),
                        ("angular_velocity", pose.angular_velocity if pose.has_velocity else z)):
            self.register_buffer(f"pose_{name}", torch.as_tensor(t).detach().clone())

    def _vec_buffer(self, name: str, value) -> None:
        self.register_buffer(name, _vec(value, name))

    @abstractmethod
    def distance_and_normal(self, points: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        """Local points (..., 3) metres → σ (...) metres (negative inside), unit outward n (..., 3)."""

    def distance(self, points: torch.Tensor) -> torch.Tensor:
        """Local points (..., 3) metres → signed distance σ (...) metres, negative inside."""
        return self.distance_and_normal(points)[0]

    def distance_and_normal_rows(self, rows: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        """:meth:`distance_and_normal` of local points given as rows (3, P) metres: σ (P,) metres
        and the normals as rows (3, P) (the collision stage's layout). Default: through
        :meth:`distance_and_normal`."""
        sigma, normal = self.distance_and_normal(rows.t().contiguous())
        return sigma, normal.t()


class SphereCollider(Collider):
    """Solid ball. center: (3,) metres (local frame), radius: metres."""

    def __init__(self, center=(0.0, 0.0, 0.0), radius: float = 0.1, friction: float = DEFAULT_FRICTION,
                 pose: Optional[Pose] = None, follow_head: bool = False):
        super().__init__(friction, pose, follow_head)
        if radius <= 0:
            raise ValueError("radius must be positive")
        self._vec_buffer("center", center)
        self.radius = float(radius)

    def distance_and_normal(self, points):
        n, length = _unit_or(points - _like(self.center, points), _UP)
        return length - self.radius, n

    def distance(self, points):
        return (points - _like(self.center, points)).norm(dim=-1) - self.radius

    def __repr__(self):
        return f"SphereCollider(center={self.center.tolist()}, radius={self.radius}, friction={float(self.friction)})"


class CapsuleCollider(Collider):
    """Solid capsule: points within ``radius`` (metres) of the segment a–b ((3,) metres each)."""

    def __init__(self, a=(0.0, 0.0, 0.0), b=(0.0, 0.1, 0.0), radius: float = 0.05,
                 friction: float = DEFAULT_FRICTION, pose: Optional[Pose] = None, follow_head: bool = False):
        super().__init__(friction, pose, follow_head)
        if radius <= 0:
            raise ValueError("radius must be positive")
        self._vec_buffer("a", a)
        self._vec_buffer("b", b)
        self.radius = float(radius)

    def distance_and_normal(self, points):
        a, b = _like(self.a, points), _like(self.b, points)
        ab = b - a
        h = (_dot(points - a, ab) / _dot(ab, ab).clamp_min(1e-30)).clamp(0, 1)
        n, length = _unit_or(points - a - h[..., None] * ab, _UP)
        return length - self.radius, n

    def distance(self, points):
        a, b = _like(self.a, points), _like(self.b, points)
        ab = b - a
        h = (_dot(points - a, ab) / _dot(ab, ab).clamp_min(1e-30)).clamp(0, 1)
        return (points - a - h[..., None] * ab).norm(dim=-1) - self.radius

    def __repr__(self):
        return (f"CapsuleCollider(a={self.a.tolist()}, b={self.b.tolist()}, radius={self.radius}, "
                f"friction={float(self.friction)})")


class PlaneCollider(Collider):
    """Half-space behind a plane: solid where (p − point)·normal < 0. point, normal: (3,) (metres; any length)."""

    def __init__(self, point=(0.0, 0.0, 0.0), normal=(0.0, 1.0, 0.0), friction: float = DEFAULT_FRICTION,
                 pose: Optional[Pose] = None, follow_head: bool = False):
        super().__init__(friction, pose, follow_head)
        nrm = _vec(normal, "normal")
        if nrm.norm() == 0:
            raise ValueError("plane normal must be non-zero")
        self._vec_buffer("point", point)
        self.register_buffer("normal", nrm / nrm.norm())

    def distance_and_normal(self, points):
        n = _like(self.normal, points)
        return _dot(points - _like(self.point, points), n), n.expand_as(points)

    def distance(self, points):
        return _dot(points - _like(self.point, points), _like(self.normal, points))

    def __repr__(self):
        return f"PlaneCollider(point={self.point.tolist()}, normal={self.normal.tolist()}, friction={float(self.friction)})"


class HollowSphereCollider(Collider):
    """A thick spherical shell with an opening (a cap cut off), exact signed distance.

    Args:
        center: (3,) metres. radius: radius of the shell's mid-surface, metres.
        thickness: wall thickness, metres (the wall spans radius ± thickness/2; its rim is rounded).
        cut_height: the shell is cut by the plane (p − center)·axis = cut_height (metres, in
            (−radius, radius)); the cap beyond it is open. ``None``: a closed shell.
        axis: (3,) direction of the opening.

    Hair inside the shell sees its inner wall; hair outside sees the outer wall. Particles can
    only be pushed out the nearer side, so keep ``thickness`` larger than what a particle moves
    into the wall in one frame.
    """

    def __init__(self, center=(0.0, 0.0, 0.0), radius: float = 0.2, thickness: float = 0.02,
                 cut_height: Optional[float] = 0.1, axis=(0.0, 1.0, 0.0), friction: float = DEFAULT_FRICTION,
                 pose: Optional[Pose] = None, follow_head: bool = False):
        super().__init__(friction, pose, follow_head)
        if radius <= 0 or thickness <= 0 or thickness >= 2 * radius:
            raise ValueError("need radius > 0 and 0 < thickness < 2 radius")
        if cut_height is not None and not -radius < cut_height < radius:
            raise ValueError("cut_height must lie in (−radius, radius)")
        self._vec_buffer("center", center)
        self.radius, self.thickness = float(radius), float(thickness)
        self.cut_height = None if cut_height is None else float(cut_height)
        ax = _vec(axis, "axis")
        if ax.norm() == 0:
            raise ValueError("axis must be non-zero")
        ax = ax / ax.norm()
        self.register_buffer("axis", ax)
        # orthonormal frame (e1, axis, e2): q = (p·e1, p·axis, p·e2) puts the opening along +y
        helper = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
        if abs(float(ax[0])) > 0.9:
            helper = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
        e1 = torch.linalg.cross(helper, ax)
        e1 = e1 / e1.norm()
        e2 = torch.linalg.cross(e1, ax)
        self.register_buffer("_frame", torch.stack((e1, ax, e2), 0))  # rows: local axes of the shell

    def distance_and_normal(self, points):
        frame = _like(self._frame, points)
        d = points - _like(self.center, points)
        q = d @ frame.T  # (..., 3) in the shell frame, opening toward +y
        half = 0.5 * self.thickness
        radial_n, dist_c = _unit_or(q, _UP)
        shell_sign = torch.where(dist_c >= self.radius, 1.0, -1.0).to(q.dtype)
        sigma = (dist_c - self.radius).abs() - half
        n_q = shell_sign[..., None] * radial_n
        if self.cut_height is not None:
            h = self.cut_height
            w = math.sqrt(self.radius ** 2 - h ** 2)
            rho = q[..., [0, 2]].norm(dim=-1)
            rim = h * rho < w * q[..., 1]  # inside the cone through the rim circle: nearest is the rim
            horiz, _ = _unit_or(torch.stack((q[..., 0], torch.zeros_like(rho), q[..., 2]), -1),
                                torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64))
            to_rim = torch.stack((rho - w, q[..., 1] - h), -1)
            rim_dist = to_rim.norm(dim=-1)
            rim_dir = to_rim / rim_dist.clamp_min(1e-30)[..., None]
            rim_n = rim_dir[..., :1] * horiz + rim_dir[..., 1:] * _like(_UP, q)
            rim_n = torch.where((rim_dist > 0)[..., None], rim_n, _like(_UP, q).expand_as(rim_n))
            sigma = torch.where(rim, rim_dist - half, sigma)
            n_q = torch.where(rim[..., None], rim_n, n_q)
        return sigma, n_q @ frame

    def __repr__(self):
        return (f"HollowSphereCollider(center={self.center.tolist()}, radius={self.radius}, "
                f"thickness={self.thickness}, cut_height={self.cut_height}, axis={self.axis.tolist()}, "
                f"friction={float(self.friction)})")


class MeshCollider(Collider):
    """A triangle mesh (or a ready :class:`~ams_torch.geometry.sdf.SDFGrid`) as a collider.

    Args:
        mesh: ``trimesh.Trimesh`` in metres (its own frame = the collider's local frame), or an
            ``SDFGrid``. It need not be closed: the SDF's sign comes from the generalised winding
            number, so a head open at the neck collides correctly (SPEC §14).
        resolution: SDF samples along the longest side of the padded box (voxel ≈ box/resolution).
        padding: margin around the mesh box, metres (default: see ``SDFGrid.from_mesh``).
        follow_head: default True: the mesh is the head (``pose`` relative to the head frame).
        projection_iterations: push-out passes per response (default 4: grid normals are
            approximate; measured on the default head at 64³, four passes leave < 0.01 voxel of
            penetration even for particles starting 2 cm deep).

    The grid is built (or read from the disk cache) by :meth:`build` or on first use of :attr:`sdf`;
    ``.to()`` / ``.double()`` convert it with the module.
    """

    projection_iterations = 4

    def __init__(self, mesh, resolution: int = 128, padding: Optional[float] = None,
                 friction: float = DEFAULT_FRICTION, pose: Optional[Pose] = None, follow_head: bool = True,
                 projection_iterations: int = 4):
        super().__init__(friction, pose, follow_head)
        self.mesh = None if isinstance(mesh, SDFGrid) else mesh
        self._grid: Optional[SDFGrid] = mesh if isinstance(mesh, SDFGrid) else None
        if self._grid is None and not (hasattr(mesh, "vertices") and hasattr(mesh, "faces")):
            raise TypeError("MeshCollider needs a trimesh.Trimesh (vertices, faces) or an SDFGrid")
        if self.mesh is not None and len(self.mesh.faces) == 0:
            raise ValueError("MeshCollider: the mesh has no faces")
        if self.mesh is not None and not bool(torch.isfinite(torch.as_tensor(self.mesh.vertices)).all()):
            raise ValueError("MeshCollider: the mesh has NaN/Inf vertices")
        self.resolution, self.padding = int(resolution), padding
        self.projection_iterations = int(projection_iterations)

    def build(self) -> "MeshCollider":
        """Build (or load from the disk cache) the SDF grid now; returns self."""
        if self._grid is None:
            probe = self.friction
            self._grid = SDFGrid.from_mesh(self.mesh, resolution=self.resolution, padding=self.padding).to(
                probe.device, probe.dtype)
        return self

    @property
    def sdf(self) -> SDFGrid:
        """The collider's SDF grid (on the module's device and dtype), built on first access."""
        return self.build()._grid

    def _apply(self, fn, *args, **kwargs):
        out = super()._apply(fn, *args, **kwargs)
        if self._grid is not None:  # the grid follows the module's device/dtype
            probe = fn(torch.zeros((), dtype=self._grid.dtype, device=self._grid.device))
            self._grid = self._grid.to(probe.device, probe.dtype)
        return out

    def distance(self, points):
        return self.sdf.distance(points)

    def distance_and_normal(self, points):
        return self.sdf.distance_and_normal(points)

    def distance_and_normal_rows(self, rows):
        return self.sdf.distance_and_normal_rows(rows)

    def __repr__(self):
        grid = repr(self._grid) if self._grid is not None else f"unbuilt, resolution={self.resolution}"
        return f"MeshCollider({grid}, follow_head={self.follow_head}, friction={float(self.friction)})"
