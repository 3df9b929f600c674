"""What the registered ops of the step share: the dtypes their native kernels take
(:mod:`ams_torch.native.dispatch`, where the native-or-torch rule lives), and a pose's tensors in the
layout the ops read (batch () or the scenes')."""
from __future__ import annotations

from typing import NamedTuple, Optional, get_type_hints

import torch

from ams_torch.geometry.pose import Pose
from ams_torch.native.dispatch import NATIVE_DTYPES
from ams_torch.sim.state import Config

__all__ = ["NATIVE_DTYPES", "as_like", "pose_tensors", "FrameSettings", "settings_schema", "frame_op_schema"]



def as_like(t: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """t on x's device and dtype (t itself when it already is)."""
    return t if t.dtype == x.dtype and t.device == x.device else t.to(device=x.device, dtype=x.dtype)


def pose_tensors(pose: Optional[Pose], x: torch.Tensor) -> tuple:
    """[R, t, lin, ω] for the op (batch () or x's scenes) and whether the pose has velocities."""
    batch = x.shape[:-3]
    if pose is None:
        pose = Pose.identity(device=x.device, dtype=x.dtype)
    r, t = as_like(pose.rotation, x), as_like(pose.translation, x)
    vel = pose.has_velocity
    lin, ang = (as_like(pose.linear_velocity, x), as_like(pose.angular_velocity, x)) if vel else (t, t)
    out = []
    for a, tail in ((r, 2), (t, 1), (lin, 1), (ang, 1)):
        if tuple(a.shape[:-tail]) not in ((), tuple(batch)):  # a prefix of the scene dims: broadcast
            own = a.shape[:-tail]
            a = a.reshape(own + (1,) * (len(batch) - len(own)) + a.shape[-tail:]).expand(
                batch + a.shape[-tail:]).contiguous()
        out.append(a)
    return out, vel


# -- the frame's settings: one named, typed struct --------------------------------------------------
_INTEGRITY = ("none", "hookean", "nonhookean")  # Config.integrity_model -> the kernels' code (its index)
_SCHEMA_TYPES = {float: "float", int: "SymInt", bool: "bool"}


class FrameSettings(NamedTuple):
    """The :class:`~ams_torch.sim.state.Config` fields the frame kernels read, in the order they
    cross to every frame op (``ams_torch::frame_dynamics``, ``frame_assembly``, ``frame_contact``,
    ``frame_dynamics_diff``, ``frame_dynamics_adjoint``). Its C++ twin is the X-macro
    ``AMS_FRAME_SETTINGS`` of ``csrc/frame/frame.h`` (same names, order and types; a test compares
    them). Field names are Config's, so :meth:`of` and :meth:`config` need no list of their own; the
    ops' schemas are made from this table (:func:`settings_schema`). A new flag of the kernels is
    its Config field, one line here, one line of the X-macro, and its use (``docs/native.md``).

    dt: frame length, s; substeps: M; ftl_damping: follow-the-leader's velocity correction;
    integrity_model: 0 none, 1 Hookean, 2 non-Hookean; the rest: the Config flags.
    """
    dt: float
    substeps: int
    ftl_damping: float
    integrity_model: int
    angular: bool
    angular_reaction: bool
    implicit_angular: bool
    geometric_stiffness: bool
    inextensibility: bool

    @classmethod
    def of(cls, config) -> "FrameSettings":
        """The settings of ``config`` (a Config), as plain Python numbers."""
        values = {f: getattr(config, f) for f in cls._fields}
        values["integrity_model"] = _INTEGRITY.index(config.integrity_model)
        return cls(**{f: kind(values[f]) for f, kind in _FIELD_TYPES.items()})

    def config(self, **others) -> Config:
        """A Config with these settings (and ``others``' fields), for the torch definition."""
        values = self._asdict()
        values["integrity_model"] = _INTEGRITY[int(values["integrity_model"])]
        return Config(**values, **others)


#: {field: float, int or bool} of :class:`FrameSettings`, in order (read once: traceable uses)
_FIELD_TYPES = {f: get_type_hints(FrameSettings)[f] for f in FrameSettings._fields}


def settings_schema() -> str:
    """The settings' part of a frame op's schema: ``float dt, SymInt substeps, …``."""
    return ", ".join(f"{_SCHEMA_TYPES[kind]} {f}" for f, kind in _FIELD_TYPES.items())


def frame_op_schema(head: str, tail: str, returns: str) -> str:
    """A frame op's schema: ``(head, <the settings>, tail) -> returns``."""
    return f"({head}, {settings_schema()}{', ' + tail if tail else ''}) -> {returns}"
