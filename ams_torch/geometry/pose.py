"""Rigid poses of the head (and of colliders): rotation, translation and their velocities."""
from __future__ import annotations

import math
from dataclasses import InitVar, dataclass
from typing import Optional, Sequence

import torch
import torch.utils._pytree as pytree

__all__ = ["Pose", "axis_angle_to_matrix", "matrix_to_axis_angle", "check_rotation", "rotation_tolerance"]


def axis_angle_to_matrix(rotvec: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula. rotvec: (..., 3) radians (axis × angle) → (..., 3, 3)."""
    theta2 = (rotvec * rotvec).sum(-1, keepdim=True)
    theta = torch.sqrt(theta2.clamp_min(1e-300) if rotvec.dtype == torch.float64 else theta2.clamp_min(1e-30))
    small = theta2 < 1e-12
    # sin(θ)/θ and (1 − cos θ)/θ² with Taylor fallbacks near 0 (finite gradients too)
    a = torch.where(small, 1 - theta2 / 6, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(theta)) / theta2.clamp_min(1e-30))
    x, y, z = rotvec.unbind(-1)
    zero = torch.zeros_like(x)
    k = torch.stack((zero, -z, y, z, zero, -x, -y, x, zero), -1).reshape(rotvec.shape[:-1] + (3, 3))
    eye = torch.eye(3, dtype=rotvec.dtype, device=rotvec.device).expand_as(k)
    return eye + a[..., None] * k + b[..., None] * (k @ k)


def matrix_to_axis_angle(rot: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`axis_angle_to_matrix` for angles in [0, π). rot: (..., 3, 3) → (..., 3)."""
    w = torch.stack(
        (rot[..., 2, 1] - rot[..., 1, 2], rot[..., 0, 2] - rot[..., 2, 0], rot[..., 1, 0] - rot[..., 0, 1]), -1
    )
    cos = ((rot.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1, 1)
    sin = 0.5 * w.norm(dim=-1)
    theta = torch.atan2(sin, cos)
    scale = torch.where(sin > 1e-7, theta / (2 * sin.clamp_min(1e-30)), 0.5 + theta * theta / 12)
    return w * scale[..., None]


def _as_dtype(t: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    return t if t.dtype == dtype else t.to(dtype)


def rotation_tolerance(dtype: torch.dtype) -> float:
    """Largest accepted ``max |R Rᵀ − I|`` and ``|det R − 1|`` for a rotation of this dtype:
    10 √ε (3.5e-3 in float32, 1.5e-7 in float64)."""
    return 10.0 * math.sqrt(torch.finfo(dtype).eps)


def check_rotation(rotation: torch.Tensor, name: str = "rotation") -> None:
    """Raise ``ValueError`` naming ``name`` unless ``rotation`` (..., 3, 3) holds finite proper
    rotations: orthonormal and det +1 within :func:`rotation_tolerance` (a host sync)."""
    r = torch.as_tensor(rotation)
    if r.dim() < 2 or tuple(r.shape[-2:]) != (3, 3):
        raise ValueError(f"{name} must have shape (..., 3, 3); got {tuple(r.shape)}")
    if not r.is_floating_point():
        raise ValueError(f"{name} must be a floating-point tensor; got {r.dtype}")
    if r.numel() == 0:
        return
    if not bool(torch.isfinite(r).all()):
        raise ValueError(f"{name} contains NaN/Inf")
    tol = rotation_tolerance(r.dtype)
    eye = torch.eye(3, dtype=r.dtype, device=r.device)
    ortho = (r @ r.transpose(-1, -2) - eye).abs().amax(dim=(-1, -2)).reshape(-1)
    det = torch.linalg.det(r).reshape(-1)
    bad = (ortho > tol) | ((det - 1).abs() > tol)
    if bool(bad.any()):
        k = int(torch.nonzero(bad)[0])
        where = f" at index {tuple(int(i) for i in torch.unravel_index(torch.tensor(k), r.shape[:-2]))}" \
            if r.dim() > 2 else ""
        raise ValueError(f"{name} is not a rotation{where}: max |R Rᵀ − I| = {float(ortho[k]):.3g}, det = "
                         f"{float(det[k]):.6g}; a rotation must be orthonormal with det +1 (tolerance {tol:.2g} "
                         f"for {r.dtype})")


@dataclass(frozen=True)
class Pose:
    """A rigid pose with its velocity (world frame), for the head or a collider.

    A point ``p`` of the body's local frame sits at ``R p + T`` in the world and moves with
    the rigid-body velocity ``linear_velocity + angular_velocity × (x − T)``.

    Fields (every tensor may carry the same leading batch dims ``...``):
        rotation: (..., 3, 3) rotation matrix R (orthonormal, det +1).
        translation: (..., 3) metres, T.
        linear_velocity: (..., 3) m/s, velocity of the frame's origin; ``None`` = unknown
            (the simulator then takes it from the change of pose over the frame).
        angular_velocity: (..., 3) rad/s, world frame; ``None`` = unknown (likewise).

    Construction validates shapes (the batch dims of all fields agree, both velocities or
    neither) and values (finite; R a proper rotation within :func:`rotation_tolerance`), and
    raises ``ValueError`` naming the field. ``check=False`` skips the value checks (no host
    sync): the simulator's step uses it for poses it derives from validated ones.
    """

    rotation: torch.Tensor
    translation: torch.Tensor
    linear_velocity: Optional[torch.Tensor] = None
    angular_velocity: Optional[torch.Tensor] = None
    check: InitVar[bool] = True

    def __post_init__(self, check: bool) -> None:
        if not check:
            return
        for name in ("rotation", "translation", "linear_velocity", "angular_velocity"):
            v = getattr(self, name)
            if v is not None and not isinstance(v, torch.Tensor):
                raise ValueError(f"Pose.{name} must be a tensor; got {type(v).__name__}")
        check_rotation(self.rotation, "Pose.rotation")
        batch = tuple(self.rotation.shape[:-2])
        for name in ("translation", "linear_velocity", "angular_velocity"):
            v = getattr(self, name)
            if v is None:
                continue
            if tuple(v.shape) != batch + (3,):
                raise ValueError(f"Pose.{name} must have shape {batch + (3,)} to match rotation "
                                 f"{tuple(self.rotation.shape)}; got {tuple(v.shape)}")
            if not bool(torch.isfinite(v).all()):
                raise ValueError(f"Pose.{name} contains NaN/Inf")
        if (self.linear_velocity is None) != (self.angular_velocity is None):
            raise ValueError("Pose needs both linear_velocity and angular_velocity, or neither")

    # -- construction ------------------------------------------------------------------
    @staticmethod
    def identity(device=None, dtype=torch.float32) -> "Pose":
        z = torch.zeros(3, device=device, dtype=dtype)
        return Pose(torch.eye(3, device=device, dtype=dtype), z, z.clone(), z.clone(), check=False)

    @staticmethod
    def from_rotvec(rotvec, translation=(0.0, 0.0, 0.0), linear_velocity=None, angular_velocity=None,
                    device=None, dtype=torch.float32) -> "Pose":
        """Pose from an axis-angle vector (radians) and a translation (metres)."""
        as_t = lambda a: None if a is None else torch.as_tensor(a, device=device, dtype=dtype)  # noqa: E731
        return Pose(axis_angle_to_matrix(as_t(rotvec)), as_t(translation), as_t(linear_velocity),
                    as_t(angular_velocity))

    @staticmethod
    def stack(poses: Sequence["Pose"]) -> "Pose":
        """Stack B poses (same batch shape each) into one pose with a new leading dim B, e.g.
        B motions of one groom simulated as a scene batch. Velocities are kept only if every
        pose has them."""
        poses = list(poses)
        if not poses:
            raise ValueError("Pose.stack needs at least one pose")
        vel = all(p.has_velocity for p in poses)
        st = lambda name: torch.stack([getattr(p, name) for p in poses])  # noqa: E731
        return Pose(st("rotation"), st("translation"), st("linear_velocity") if vel else None,
                    st("angular_velocity") if vel else None, check=False)

    def to(self, device=None, dtype=None) -> "Pose":
        """The pose on ``device`` / in ``dtype`` (self when nothing changes: no ops)."""
        dev = None if device is None else torch.device(device)
        r = self.rotation
        if (dev is None or (r.device.type == dev.type and (dev.index is None or r.device.index == dev.index))) and \
                (dtype is None or r.dtype == dtype) and all(t is None or (t.device == r.device and t.dtype == r.dtype)
                                                            for t in (self.translation, self.linear_velocity,
                                                                      self.angular_velocity)):
            return self
        f = lambda t: None if t is None else t.to(device=device, dtype=dtype)  # noqa: E731
        return Pose(f(self.rotation), f(self.translation), f(self.linear_velocity), f(self.angular_velocity),
                    check=False)

    def with_velocity(self, linear_velocity, angular_velocity) -> "Pose":
        """The same pose with these velocities ((..., 3) m/s and rad/s, world frame)."""
        return Pose(self.rotation, self.translation, linear_velocity, angular_velocity, check=False)

    @property
    def batch_shape(self) -> torch.Size:
        """The pose's leading batch dims."""
        return self.rotation.shape[:-2]

    @property
    def has_velocity(self) -> bool:
        return self.linear_velocity is not None and self.angular_velocity is not None

    # -- maps --------------------------------------------------------------------------
    def to_world(self, p: torch.Tensor) -> torch.Tensor:
        """Local points (..., K, 3) (K any number of points) → world points (..., K, 3)."""
        r, t = self._bcast(p)
        return torch.einsum("...ij,...kj->...ki", r, p) + t[..., None, :]

    def to_local(self, x: torch.Tensor) -> torch.Tensor:
        """World points (..., K, 3) → local points (..., K, 3)."""
        r, t = self._bcast(x)
        return torch.einsum("...ji,...kj->...ki", r, x - t[..., None, :])

    def rotate(self, d: torch.Tensor) -> torch.Tensor:
        """Local directions (..., K, 3) → world directions (no translation)."""
        r, _ = self._bcast(d)
        return torch.einsum("...ij,...kj->...ki", r, d)

    def unrotate(self, d: torch.Tensor) -> torch.Tensor:
        """World directions (..., K, 3) → local directions."""
        r, _ = self._bcast(d)
        return torch.einsum("...ji,...kj->...ki", r, d)

    def velocity_at(self, x: torch.Tensor) -> torch.Tensor:
        """Rigid-body velocity (..., K, 3) m/s at world points x (..., K, 3); zero if unknown."""
        if not self.has_velocity:
            return torch.zeros_like(x)
        _, t = self._bcast(x)
        v, w = _as_dtype(self.linear_velocity, x.dtype), _as_dtype(self.angular_velocity, x.dtype)
        v, w = v.reshape(t.shape[:-1] + (1, 3)), w.reshape(t.shape[:-1] + (1, 3))  # (..., 1, 3), as t
        return v + torch.linalg.cross(w, x - t[..., None, :])

    def _bcast(self, p: torch.Tensor):
        r, t = _as_dtype(self.rotation, p.dtype), _as_dtype(self.translation, p.dtype)
        # pose batch dims must be a suffix-compatible prefix of p's leading dims
        extra = p.dim() - 2 - (r.dim() - 2)
        if extra < 0:
            raise ValueError(f"pose has batch shape {tuple(r.shape[:-2])} but points have shape {tuple(p.shape)}")
        if extra:
            lead = r.shape[:-2]
            r, t = r.reshape(lead + (1,) * extra + (3, 3)), t.reshape(lead + (1,) * extra + (3,))
        return r, t

    # -- motion over a frame ----------------------------------------------------------
    def relative_rotvec(self, other: "Pose") -> torch.Tensor:
        """Axis-angle (world frame) of the rotation taking this pose's R to ``other``'s."""
        return matrix_to_axis_angle(other.rotation @ self.rotation.transpose(-1, -2))

    def interpolate(self, other: "Pose", s: float, dt: float) -> "Pose":
        """Pose at fraction ``s`` ∈ [0, 1] of a frame of length ``dt`` from self to other.

        Rotation: constant angular velocity (slerp). Translation: cubic Hermite when both
        ends carry velocities (so substeps see the motion's own accelerations), else linear.
        Velocities at s are interpolated linearly (or derived from the change of pose).
        """
        if s <= 0.0:
            return self
        if s >= 1.0:
            return other
        rv = self.relative_rotvec(other)
        rot = axis_angle_to_matrix(rv * s) @ self.rotation
        p0, p1 = self.translation, other.translation
        if self.has_velocity and other.has_velocity:
            v0, v1 = self.linear_velocity * dt, other.linear_velocity * dt
            h00, h10 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s
            h01, h11 = -2 * s**3 + 3 * s**2, s**3 - s**2
            trans = h00 * p0 + h10 * v0 + h01 * p1 + h11 * v1
            lin = (1 - s) * self.linear_velocity + s * other.linear_velocity
            ang = (1 - s) * self.angular_velocity + s * other.angular_velocity
        else:
            trans = (1 - s) * p0 + s * p1
            lin, ang = (p1 - p0) / dt, rv / dt
        return Pose(rot, trans, lin, ang, check=False)


def _pose_flatten(p: Pose):
    return [p.rotation, p.translation, p.linear_velocity, p.angular_velocity], None


def _pose_unflatten(children, _context) -> Pose:
    return Pose(*children, check=False)


pytree.register_pytree_node(Pose, _pose_flatten, _pose_unflatten,
                            flatten_with_keys_fn=lambda p: ([(pytree.GetAttrKey(k), getattr(p, k)) for k in
                                                             ("rotation", "translation", "linear_velocity",
                                                              "angular_velocity")], None))

