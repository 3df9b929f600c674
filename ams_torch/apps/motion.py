"""Head motions: rigid poses with consistent linear and angular velocities (SI units).

Every motion is a callable ``motion(t) -> Pose`` (t in seconds) whose pose carries its own
velocities (m/s, rad/s, world frame), analytic where the motion has a closed form.
``motion.poses(frames, dt)`` gives the end-of-frame poses ``t = dt, 2dt, …, frames·dt`` that
:meth:`ams_torch.Simulator.step` takes. Build one from a dict with :func:`make_motion`
(``{"type": "shake", "amplitude": 0.6, ...}``), as scene files do.

Motions: :class:`Static`, :class:`Shake` (about an axis, default y), :class:`Nod` (about x),
:class:`Spin` (constant rate after a smooth ramp), :class:`RollerCoaster` (a vertical loop
with peak accelerations of several g, then a stop), :class:`Keyframes` (interpolated) and
:func:`recorded` (a pose sequence from an ``.npz``).
"""
from __future__ import annotations

import abc
import math
from typing import Sequence

import numpy as np
import torch

from ams_torch.geometry.pose import Pose, axis_angle_to_matrix, matrix_to_axis_angle

__all__ = ["Motion", "Static", "Shake", "Nod", "Spin", "RollerCoaster", "Keyframes", "recorded",
           "make_motion", "MOTIONS"]

G = 9.81


def _unit(axis) -> np.ndarray:
    a = np.asarray(axis, dtype=np.float64)
    n = np.linalg.norm(a)
    if a.shape != (3,) or not n > 0:
        raise ValueError(f"motion axis must be a non-zero 3-vector; got {axis}")
    return a / n


class Motion(abc.ABC):
    """Base class: subclasses define ``state(t) -> (rotvec (3,), translation (3,) m,
    linear velocity (3,) m/s, angular velocity (3,) rad/s)`` as float64 numpy arrays."""

    @abc.abstractmethod
    def state(self, t: float):
        """(rotvec, translation, linear velocity, angular velocity) at t seconds."""

    def __call__(self, t: float, device=None, dtype=torch.float32) -> Pose:
        rv, tr, lin, ang = self.state(float(t))
        rot = axis_angle_to_matrix(torch.as_tensor(rv, dtype=torch.float64))
        as_t = lambda a: torch.as_tensor(np.asarray(a, dtype=np.float64))  # noqa: E731
        return Pose(rot, as_t(tr), as_t(lin), as_t(ang)).to(device=device, dtype=dtype)

    def poses(self, frames: int, dt: float, device=None, dtype=torch.float32) -> list:
        """End-of-frame poses for t = dt, 2dt, …, frames·dt: a list of ``frames`` :class:`Pose`."""
        return [self(k * dt, device=device, dtype=dtype) for k in range(1, frames + 1)]


class Static(Motion):
    """The head stays at the identity pose, at rest."""

    def state(self, t):
        z = np.zeros(3)
        return z, z, z, z


class Shake(Motion):
    """Rotation about ``axis`` by angle(t) = amplitude·sin(2π f t) (radians, Hz), exact ω; with
    ``translation`` (3,) m also a translation ``translation``·sin(2π f t) (exact velocity)."""

    def __init__(self, amplitude: float = 0.6, frequency: float = 1.5, axis=(0.0, 1.0, 0.0),
                 translation=(0.0, 0.0, 0.0)):
        self.amplitude, self.frequency, self.axis = float(amplitude), float(frequency), _unit(axis)
        self.translation = np.asarray(translation, dtype=np.float64)
        if self.translation.shape != (3,) or not np.isfinite(self.translation).all():
            raise ValueError(f"Shake.translation must be three finite numbers (m); got {translation}")

    def state(self, t):
        w = 2 * math.pi * self.frequency
        z = np.zeros(3)
        tr, lin = z, z
        if self.translation.any():
            tr, lin = self.translation * math.sin(w * t), self.translation * w * math.cos(w * t)
        return (self.axis * self.amplitude * math.sin(w * t), tr, lin,
                self.axis * self.amplitude * w * math.cos(w * t))


class Nod(Shake):
    """A nod: :class:`Shake` about the x axis (default amplitude 0.35 rad at 1 Hz)."""

    def __init__(self, amplitude: float = 0.35, frequency: float = 1.0, axis=(1.0, 0.0, 0.0)):
        super().__init__(amplitude, frequency, axis)


class Spin(Motion):
    """Spin about ``axis`` at ``rate`` rad/s, reached with a linear ramp over ``ramp`` seconds."""

    def __init__(self, rate: float = 6.0, ramp: float = 0.5, axis=(0.0, 1.0, 0.0)):
        if ramp < 0:
            raise ValueError(f"Spin.ramp must be >= 0 s; got {ramp}")
        self.rate, self.ramp, self.axis = float(rate), float(ramp), _unit(axis)

    def state(self, t):
        r = self.ramp
        if t < r:
            ang, om = self.rate * t * t / (2 * r), self.rate * t / r
        else:
            ang, om = self.rate * (t - r / 2), self.rate
        z = np.zeros(3)
        return self.axis * ang, z, z, self.axis * om


class RollerCoaster(Motion):
    """A ride of ``loops`` turns around a vertical loop of ``radius`` m in the x–y plane, then a stop.

    The car's angle φ(t) along the loop has rate φ' = Ω sin²(π t / duration) for t ≤ duration
    (smooth start and stop) and stays put afterwards; Ω = sqrt(peak_g · g / radius), so the
    peak centripetal acceleration is ``peak_g`` g, and duration = 4π loops / Ω so the car ends
    where it started, upright (``duration`` attribute, s). The head sits in the car at
    ``(r sin φ, r (1 − cos φ), 0)`` and pitches with it (rotation φ about z). Velocities are
    exact derivatives.
    """

    def __init__(self, radius: float = 0.5, peak_g: float = 4.0, loops: int = 1):
        if not (radius > 0 and peak_g > 0 and loops >= 1):
            raise ValueError(f"RollerCoaster needs radius > 0, peak_g > 0, loops >= 1; "
                             f"got {radius}, {peak_g}, {loops}")
        self.radius, self.peak_g, self.loops = float(radius), float(peak_g), int(loops)
        self.omega = math.sqrt(self.peak_g * G / self.radius)
        self.duration = 4 * math.pi * self.loops / self.omega

    def angle(self, t: float):
        """(φ rad, φ' rad/s) at time t (s)."""
        d, om = self.duration, self.omega
        t = min(max(t, 0.0), d)
        phi = om * (t / 2 - d / (4 * math.pi) * math.sin(2 * math.pi * t / d))
        rate = om * math.sin(math.pi * t / d) ** 2 if t < d else 0.0
        return phi, rate

    def state(self, t):
        phi, rate = self.angle(t)
        r = self.radius
        tr = np.array([r * math.sin(phi), r * (1 - math.cos(phi)), 0.0])
        lin = np.array([r * math.cos(phi), r * math.sin(phi), 0.0]) * rate
        z = np.array([0.0, 0.0, 1.0])
        return z * phi, tr, lin, z * rate


class Keyframes(Motion):
    """Interpolated key poses: ``times`` (K,) s increasing; ``rotvecs`` (K, 3) rad (axis-angle);
    ``translations`` (K, 3) m. Translation: cubic Hermite with Catmull–Rom tangents (velocity
    its exact derivative); rotation: slerp at constant angular velocity within each interval.
    Before the first key and after the last the pose holds, at rest."""

    def __init__(self, times: Sequence[float], rotvecs=None, translations=None):
        t = np.asarray(times, dtype=np.float64)
        if t.ndim != 1 or len(t) < 1 or np.any(np.diff(t) <= 0) or not np.all(np.isfinite(t)):
            raise ValueError("Keyframes.times must be a non-empty, strictly increasing list of seconds")
        k = len(t)
        rv = np.zeros((k, 3)) if rotvecs is None else np.asarray(rotvecs, dtype=np.float64)
        tr = np.zeros((k, 3)) if translations is None else np.asarray(translations, dtype=np.float64)
        if rv.shape != (k, 3) or tr.shape != (k, 3):
            raise ValueError(f"Keyframes.rotvecs and translations must have shape ({k}, 3); "
                             f"got {rv.shape} and {tr.shape}")
        self.times, self.translations = t, tr
        self.rotations = axis_angle_to_matrix(torch.as_tensor(rv))  # (K, 3, 3) float64
        tan = np.zeros_like(tr)
        if k > 1:
            tan[1:-1] = (tr[2:] - tr[:-2]) / (t[2:] - t[:-2])[:, None]
        self.tangents = tan  # zero velocity at the ends

    def state(self, t):
        ts, k = self.times, len(self.times)
        z = np.zeros(3)
        if k == 1 or t <= ts[0] or t >= ts[-1]:
            i = 0 if (k == 1 or t <= ts[0]) else k - 1
            return matrix_to_axis_angle(self.rotations[i]).numpy(), self.translations[i], z, z
        i = int(np.searchsorted(ts, t, side="right") - 1)
        h = ts[i + 1] - ts[i]
        s = (t - ts[i]) / h
        p0, p1 = self.translations[i], self.translations[i + 1]
        m0, m1 = self.tangents[i] * h, self.tangents[i + 1] * h
        tr = (2 * s**3 - 3 * s**2 + 1) * p0 + (s**3 - 2 * s**2 + s) * m0 + (-2 * s**3 + 3 * s**2) * p1 \
            + (s**3 - s**2) * m1
        lin = ((6 * s**2 - 6 * s) * p0 + (3 * s**2 - 4 * s + 1) * m0 + (-6 * s**2 + 6 * s) * p1
               + (3 * s**2 - 2 * s) * m1) / h
        r0, r1 = self.rotations[i], self.rotations[i + 1]
        rel = matrix_to_axis_angle(r1 @ r0.T)
        rot = axis_angle_to_matrix(rel * s) @ r0
        return matrix_to_axis_angle(rot).numpy(), tr, lin, (rel / h).numpy()


def recorded(path: str) -> Keyframes:
    """A recorded pose sequence from an ``.npz`` with ``translations`` (F, 3) m and either
    ``rotations`` (F, 3, 3) (proper rotations: orthonormal, det +1) or ``rotvecs`` (F, 3) rad,
    and either ``times`` (F,) s or a scalar ``dt`` s (sample k at k·dt). Velocities are the exact
    derivatives of the interpolation (:class:`Keyframes`). Raises ``ValueError`` naming the file,
    the array and the first bad frame (a matrix that is not a rotation is never replaced)."""
    import os

    from ams_torch.geometry.pose import check_rotation

    if not os.path.isfile(path):
        raise FileNotFoundError(f"recorded motion: no such file {path!r}")
    with np.load(path) as data:
        keys = set(data.files)
        if "translations" not in keys or not ({"rotations", "rotvecs"} & keys) or not ({"times", "dt"} & keys):
            raise ValueError(f"recorded motion {path!r} needs 'translations', 'rotations' or 'rotvecs', "
                             f"and 'times' or 'dt'; it has {sorted(keys)}")
        tr = np.asarray(data["translations"], dtype=np.float64)
        if tr.ndim != 2 or tr.shape[1] != 3 or not np.isfinite(tr).all():
            raise ValueError(f"recorded motion {path!r}: translations must be finite with shape (F, 3); got "
                             f"{tr.shape}")
        if "rotvecs" in keys:
            rv = np.asarray(data["rotvecs"], dtype=np.float64)
            if rv.shape != tr.shape or not np.isfinite(rv).all():
                raise ValueError(f"recorded motion {path!r}: rotvecs must be finite with shape {tr.shape}; got "
                                 f"{rv.shape}")
        else:
            stored = np.asarray(data["rotations"])
            rot = stored.astype(np.float64)
            if rot.shape != (len(tr), 3, 3):
                hint = (" (homogeneous 4×4 matrices: store their upper-left 3×3 as rotations and their last "
                        "column as translations)" if rot.shape[1:] == (4, 4) else "")
                raise ValueError(f"recorded motion {path!r}: rotations must have shape ({len(tr)}, 3, 3); got "
                                 f"{rot.shape}{hint}")
            try:
                # the tolerance of the stored precision (a float32 recording is orthonormal to ~1e-7)
                check_rotation(torch.as_tensor(stored if stored.dtype == np.float32 else rot), "rotations")
            except ValueError as err:
                raise ValueError(f"recorded motion {path!r}: {str(err).replace('at index (', 'at frame (')}") from None
            rv = matrix_to_axis_angle(torch.as_tensor(rot)).numpy()
        times = np.asarray(data["times"], dtype=np.float64) if "times" in keys else \
            float(data["dt"]) * np.arange(len(tr))
    return Keyframes(times, rv, tr)


MOTIONS = {"static": Static, "shake": Shake, "nod": Nod, "spin": Spin, "roller_coaster": RollerCoaster,
           "keyframes": Keyframes}


def make_motion(spec) -> Motion:
    """A motion from a dict ``{"type": name, **arguments}`` (names: static, shake, nod, spin,
    roller_coaster, keyframes, recorded (argument ``path``)), a name, or None (static)."""
    if spec is None:
        return Static()
    if isinstance(spec, str):
        spec = {"type": spec}
    if isinstance(spec, Motion):
        return spec
    spec = dict(spec)
    kind = spec.pop("type", "static")
    if kind == "recorded":
        if set(spec) != {"path"}:
            raise ValueError(f"motion.recorded takes exactly the key 'path'; got {sorted(spec)}")
        return recorded(spec["path"])
    if kind not in MOTIONS:
        raise ValueError(f"motion.type must be one of {sorted(MOTIONS) + ['recorded']}; got {kind!r}")
    try:
        return MOTIONS[kind](**spec)
    except TypeError as err:
        raise ValueError(f"motion ({kind}): {err}") from None
