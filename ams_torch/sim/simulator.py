"""The user-facing simulator: a thin ``torch.nn.Module`` over the pure :func:`~ams_torch.sim.stepping.step`."""
from __future__ import annotations

from typing import Mapping, Optional, Sequence, Union

import torch

from ams_torch.geometry.pose import Pose
from ams_torch.sim import stepping as step_mod
from ams_torch.sim.backends import resolve_backend
from ams_torch.sim.builder import ModelBuilder, make_config
from ams_torch.sim.model import coefficients, sag_free_offset
from ams_torch.sim.params import Params
from ams_torch.sim.state import Control, ExternalForce, State
from ams_torch.stages.collide import Collider
from ams_torch.stages.hair_hair import HairHair

__all__ = ["Simulator"]

BACKENDS = ("auto", "torch", "native")


DTYPES = (torch.float32, torch.float64)


def _check_device_dtype(device, dtype) -> torch.device:
    """The simulator's device, or a ValueError naming what is wrong with ``device``/``dtype``."""
    if dtype not in DTYPES:
        why = " (half precision cannot hold the strands' solve: it needs float32 at least)" \
            if isinstance(dtype, torch.dtype) and dtype.is_floating_point else ""
        raise ValueError(f"dtype must be torch.float32 or torch.float64; got {dtype!r}{why}")
    try:
        device = torch.device(device) if device is not None else torch.device("cpu")
    except (RuntimeError, TypeError) as err:
        raise ValueError(f"device {device!r} is not a torch device ({err})") from None
    if device.type == "meta":
        raise ValueError("device 'meta' holds no data and cannot simulate; use cpu or cuda")
    try:
        torch.empty(1, device=device, dtype=dtype)
    except (RuntimeError, AssertionError, TypeError) as err:
        raise ValueError(f"device {str(device)!r} cannot hold {dtype} tensors here: {err}") from None
    return device


class _CheckedForce:
    """A callable external force checked like a tensor at every call (metadata only: shape,
    dtype, device; no host sync): its result must be a floating tensor of the state's shape or
    broadcast to it, and is converted to the simulator's dtype and device. Whether it held
    NaN/Inf is kept as a device-side flag (``nonfinite``) that :meth:`Simulator.step` folds
    into the state's divergence record, so a divergence it caused blames the input."""

    def __init__(self, fn, shape, dtype, device):
        self.fn, self.shape, self.dtype, self.device = fn, tuple(shape), dtype, device
        self.nonfinite = None

    def __call__(self, x, v, t):
        out = self.fn(x, v, t)
        want = f"a tensor of shape {self.shape} (..., S, N, 3) newtons, or one that broadcasts to it"
        if not isinstance(out, torch.Tensor):
            raise ValueError(f"external_force(x, v, t) must return {want}; it returned {type(out).__name__}")
        if not out.is_floating_point():
            raise ValueError(f"external_force(x, v, t) must return a floating-point tensor; it returned {out.dtype}")
        try:
            ok = torch.broadcast_shapes(out.shape, self.shape) == self.shape
        except RuntimeError:
            ok = False
        if not ok:
            raise ValueError(f"external_force(x, v, t) must return {want}; it returned shape {tuple(out.shape)}")
        out = out.to(device=self.device, dtype=self.dtype)
        bad = ~torch.isfinite(out.sum())
        self.nonfinite = bad if self.nonfinite is None else self.nonfinite | bad
        return out


class Simulator(torch.nn.Module):
    """Simulate a groom with the AMS model.

    Args:
        rest_positions: (S, N, 3) metres, rest shape in the head frame (array or tensor).
        params: :class:`Params` (SI units); defaults to ``Params()``.
        device, dtype: where and in what precision to simulate (float32 by default).
        pose: the head pose at t = 0 (default: identity, at rest).
        hair_hair: :class:`HairHair` settings to enable hair–hair interaction (SPEC §6);
            ``None`` (default) allocates no grid and runs no grid code.
        colliders: colliders for the hair–solid stage (SPEC §8), e.g. ``MeshCollider``,
            ``SphereCollider``; an empty list or None builds no SDF and runs no collision code.
            The simulator keeps its own copies, converted to its device and dtype.
        learnable: names of Params material fields to make ``nn.Parameter`` s of the module, for
            ``torch.optim.Adam(sim.parameters())``: e.g. ``("integrity_rate", "drag")`` with the
            default per-length material, ``("integrity_stiffness", "drag")`` with a per-particle one.
        backend: "torch" (the differentiable definition), "native" (the fused kernels, see
            :mod:`ams_torch.sim.native`; an error naming the kernels that cannot be built) or "auto"
            (the default: native when they can be built, torch otherwise, one warning per backend
            that cannot). The kernels the configuration needs are built here, not in the first
            step. A frame whose inputs require grad runs its strand dynamics on the native kernel
            with its native adjoint (:mod:`ams_torch.sim.native_grad`) and its other stages on the
            torch definition (``ams_torch.native_status()["gradients"]``); gradients equal the torch
            definition's.
        stages: the frame's stages, in order (default :data:`ams_torch.sim.stepping.STAGES`; swap or
            wrap one with :func:`~ams_torch.sim.stepping.replace_stage` / ``wrap_stage``).

    The fixed data is ``sim.model`` (a registered submodule: ``.to()``, ``.double()``,
    ``state_dict()`` work), the frozen settings ``sim.config``; ``sim.step`` builds a
    :class:`~ams_torch.sim.state.Control` and calls the pure step.

    Example (run by ``tests/test_doctests.py``):

        >>> import ams_torch as at
        >>> from ams_torch.apps.motion import Shake
        >>> from ams_torch.grooms.simple import sphere_groom
        >>> rest = sphere_groom(8, 12)                            # (S, N, 3) m
        >>> sim = at.Simulator(rest, at.Params(), learnable=("integrity_rate", "drag"), backend="torch")
        >>> state = sim.initial_state()
        >>> for pose in Shake().poses(3, sim.params.dt):
        ...     state = sim.step(state, pose)
        >>> state.x.shape                                        # state.x, state.v: (S, N, 3)
        torch.Size([8, 12, 3])
        >>> sorted(name for name, _ in sim.named_parameters())
        ['model.drag', 'model.integrity_rate']
    """

    def __init__(self, rest_positions, params: Optional[Params] = None, *, device=None,
                 dtype: torch.dtype = torch.float32, pose: Optional[Pose] = None,
                 hair_hair: Optional[HairHair] = None, colliders: Optional[Sequence[Collider]] = None,
                 learnable: Sequence[str] = (), backend: str = "auto", stages: Optional[Sequence] = None):
        super().__init__()
        if backend not in BACKENDS:
            raise ValueError(f"backend must be one of {BACKENDS}; got {backend!r}")
        params = params if params is not None else Params()
        if not isinstance(params, Params):
            raise ValueError(f"params must be an ams_torch.Params; got {type(params).__name__}")
        device = _check_device_dtype(device, dtype)
        params.check_dtype(dtype)
        builder = ModelBuilder(rest_positions, params, device=device, dtype=dtype).set_learnable(*learnable)
        builder.set_hair_hair(hair_hair)
        for c in colliders or ():
            builder.add_collider(c)
        self.model = builder.finalize()
        self.requested_backend = backend
        self.config = make_config(self.model, self._resolve_backend(backend, device, dtype, hair_hair is not None,
                                                                    bool(self.model.colliders)))
        #: run the divergence guard every this many frames (0: never); from ``params.check_every``
        #: (a policy of the run, not physics: it may be changed on a built simulator)
        self.check_every = int(params.check_every)
        #: the frame's stages (:data:`ams_torch.sim.stepping.STAGES` unless given)
        self.stages = tuple(step_mod.STAGES if stages is None else stages)
        init = (pose or Pose.identity(dtype=dtype)).to(device=device, dtype=dtype)
        if init.rotation.shape != (3, 3):
            raise ValueError(f"pose (the head pose at t = 0) must be a single pose; got rotation "
                             f"{tuple(init.rotation.shape)} (give a batch of poses to initial_state)")
        z = torch.zeros(3, device=device, dtype=dtype)
        self.register_buffer("initial_rotation", init.rotation.clone())
        self.register_buffer("initial_translation", init.translation.clone())
        self.register_buffer("initial_linear_velocity", (init.linear_velocity if init.has_velocity else z).clone())
        self.register_buffer("initial_angular_velocity", (init.angular_velocity if init.has_velocity else z).clone())
        self._frames = 0  # calls of step, to run the divergence guard every check_every frames

    @staticmethod
    def _resolve_backend(backend: str, device, dtype, hair_hair: bool = False, colliders: bool = False) -> str:
        """"auto": the fused native kernels when they can be built for this device and dtype, else
        torch; "native": the same, but an error naming each backend it needs that cannot be had;
        "torch": the definition. Every native backend the configuration uses (frame, collisions,
        hair–hair grid, banded solve) is built here, once, not inside a step; one warning per
        backend that cannot be (:func:`ams_torch.sim.backends.resolve_backend`)."""
        return resolve_backend(backend, device, dtype, hair_hair, colliders)

    # -- properties ------------------------------------------------------------------------
    @property
    def params(self) -> Params:
        """The model's Params (frozen: they made the model and the config; ``params.replace(...)``
        and a new simulator change them)."""
        return self.model.params

    @property
    def hair_hair(self) -> Optional[HairHair]:
        """The hair–hair settings the model was built with (None: the stage is off)."""
        return self.model.hair_hair_settings

    @property
    def device(self) -> torch.device:
        return self.model.rest_positions.device

    @property
    def dtype(self) -> torch.dtype:
        return self.model.rest_positions.dtype

    @property
    def initial_pose(self) -> Pose:
        """The head pose at t = 0 (with velocities)."""
        return Pose(self.initial_rotation, self.initial_translation, self.initial_linear_velocity,
                    self.initial_angular_velocity, check=False)

    @property
    def colliders(self) -> list:
        """The simulator's colliders (its own copies, on its device and dtype)."""
        return list(self.model.colliders)

    def drag_coefficient(self) -> torch.Tensor:
        """γ_i = drag rate × m_i, (S, N) kg/s (e.g. the wind's coefficient: air moving at u pushes
        with γ u); from the model's current (possibly learnable) values."""
        return coefficients(self.model).drag

    @property
    def hair_hair_grid(self):
        """The hair–hair grid (fixed data of the stage), or None when the stage is off."""
        return self.model.hair_hair

    # -- state ---------------------------------------------------------------------------
    def initial_state(self, pose: Optional[Pose] = None) -> State:
        """The groom at rest in its grown shape, moving rigidly with ``pose`` (default: the
        simulator's initial pose). The pose may carry scene batch dims (B, 3, 3): the state is
        then (B, S, N, 3). Ghosts get this scene's sag-free offset (SPEC §5) when ``params.sag_free``,
        computed here once (gravity seen in the head frame of ``pose``)."""
        if pose is not None and not isinstance(pose, Pose):
            raise ValueError(f"pose must be an ams_torch.Pose; got {type(pose).__name__}")
        pose = (pose or self.initial_pose).to(device=self.device, dtype=self.dtype)
        if not pose.has_velocity:
            z = torch.zeros_like(pose.translation)
            pose = pose.with_velocity(z, z.clone())
        m = self.model
        batch = pose.rotation.shape[:-2]
        rest = m.rest_positions.expand(batch + m.rest_positions.shape)
        x = pose.to_world(rest)
        v = pose.velocity_at(x)
        if m.sag_free:
            c = coefficients(m)
            offset = pose.unrotate(sag_free_offset(c.mass, m.gravity, c.integrity).expand_as(rest))
        else:
            offset = torch.zeros_like(rest)
        dev = self.device
        return State(x=x, v=v, ghost_rest=rest + offset, sag_offset=offset, pose=pose,
                     time=torch.zeros((), device=dev, dtype=self.dtype),
                     frame=torch.zeros((), device=dev, dtype=torch.int64),
                     diverged_frame=torch.full((), -1, device=dev, dtype=torch.int64),
                     diverged_input=torch.zeros((), device=dev, dtype=torch.bool),
                     overflow_frame=torch.full((), -1, device=dev, dtype=torch.int64))

    # -- dynamics -----------------------------------------------------------------------
    def control(self, state: State, pose: Optional[Pose] = None, *,
                collider_poses: Union[None, Sequence[Optional[Pose]], Mapping[int, Pose]] = None,
                external_force: ExternalForce = None) -> Control:
        """Validate a frame's inputs against ``state`` and this simulator, and make its
        :class:`~ams_torch.sim.state.Control`. Raises ``ValueError`` naming the argument and the
        expected shape or dtype."""
        if not isinstance(state, State):
            raise ValueError(f"state must be an ams_torch State (from initial_state or step); got "
                             f"{type(state).__name__}")
        s, n = self.model.num_strands, self.model.num_particles
        x, v = state.x, state.v
        if x.shape[-3:] != (s, n, 3) or v.shape != x.shape:
            raise ValueError(f"state.x/v must have shape (..., {s}, {n}, 3); got x {tuple(x.shape)}, v {tuple(v.shape)}")
        if x.dtype != self.dtype or v.dtype != self.dtype:
            raise ValueError(f"state is {x.dtype} but the simulator is {self.dtype}: use initial_state() of this "
                             f"simulator, or convert the simulator (sim.double()/sim.float())")
        if x.device != self.device:
            raise ValueError(f"state is on {x.device} but the simulator is on {self.device}")
        for name in ("ghost_rest", "sag_offset"):
            t = getattr(state, name)
            if not isinstance(t, torch.Tensor) or t.shape != x.shape:
                got = tuple(t.shape) if isinstance(t, torch.Tensor) else type(t).__name__
                raise ValueError(f"state.{name} has shape {got} but state.x {tuple(x.shape)}: a state's tensors share "
                                 f"their scene dims (make it with initial_state, and replace x, v, ghost_rest and "
                                 f"sag_offset together)")
        batch = tuple(x.shape[:-3])
        if pose is not None:
            if not isinstance(pose, Pose):
                raise ValueError(f"pose must be an ams_torch.Pose or None; got {type(pose).__name__}")
            if tuple(pose.batch_shape) not in ((), batch):
                want = "(3, 3)" + (f" (one pose for every scene) or {batch + (3, 3)}" if batch else
                                   " (the state holds one scene)")
                raise ValueError(f"pose has batch shape {tuple(pose.batch_shape)} but the state's scenes are "
                                 f"{batch}: give rotation {want}")
            pose = pose.to(device=self.device, dtype=self.dtype)
        if isinstance(external_force, torch.Tensor):
            try:
                ok = torch.broadcast_shapes(external_force.shape, x.shape) == x.shape
            except RuntimeError:
                ok = False
            if not ok:
                raise ValueError(f"external_force must have shape {tuple(x.shape)} (..., S, N, 3) newtons, or "
                                 f"broadcast to it; got {tuple(external_force.shape)}")
            if not external_force.is_floating_point():
                raise ValueError(f"external_force must be a floating-point tensor; got {external_force.dtype}")
            external_force = external_force.to(device=self.device, dtype=self.dtype)
        elif callable(external_force) and not isinstance(external_force, _CheckedForce):
            external_force = _CheckedForce(external_force, x.shape, self.dtype, self.device)
        elif external_force is not None and not callable(external_force):
            raise ValueError(f"external_force must be a tensor, a callable f(x, v, t) or None; got "
                             f"{type(external_force).__name__}")
        return Control(pose=pose, collider_poses=self._collider_poses(collider_poses), time=state.time,
                       external_force=external_force)

    def _collider_poses(self, collider_poses) -> tuple:
        count = len(self.model.colliders)
        if collider_poses is None:
            return ()
        if count == 0:
            raise ValueError("collider_poses given but the simulator has no colliders")
        if isinstance(collider_poses, Mapping):
            bad = [i for i in collider_poses if not (isinstance(i, int) and 0 <= i < count)]
            if bad:
                raise ValueError(f"collider_poses: index {bad[0]!r} out of range (have {count} colliders)")
            collider_poses = [collider_poses.get(i) for i in range(count)]
        collider_poses = list(collider_poses)
        if len(collider_poses) != count:
            raise ValueError(f"got {len(collider_poses)} collider poses for {count} colliders")
        out = []
        for i, p in enumerate(collider_poses):
            if p is not None and not isinstance(p, Pose):
                raise ValueError(f"collider_poses[{i}] must be an ams_torch.Pose or None; got {type(p).__name__}")
            out.append(None if p is None else p.to(device=self.device, dtype=self.dtype))
        return tuple(out)

    def step(self, state: State, pose: Optional[Pose] = None, *, collider_poses=None,
             external_force: ExternalForce = None, timer=None) -> State:
        """Advance one frame of ``params.dt`` seconds.

        Args:
            state: current state.
            pose: head pose at the end of the frame (None: the head stays still).
            collider_poses: poses for the colliders at the end of the frame (a list aligned with
                ``colliders``, or ``{index: Pose}``; None entries keep a collider's own pose):
                world poses, or relative to the head for colliders with ``follow_head=True``.
            external_force: (..., S, N, 3) newtons, or ``f(x, v, t) -> force`` (t: 0-d tensor, s).
            timer: optional per-stage context-manager factory (see :func:`ams_torch.sim.stepping.step`).
        Returns:
            the new :class:`State` (``.x``, ``.v``: (..., S, N, 3)).
        Raises:
            ValueError: an input of the wrong type, shape, dtype or device (named).
            SimulationDiverged: the divergence guard (every ``params.check_every`` frames) found
                non-finite or exploding particles (names the frame and strands), or (its subclass
                :class:`~ams_torch.sim.stepping.GridOverflow`) the hair occupied more blocks than the
                hair–hair grid holds.
        """
        control = self.control(state, pose, collider_poses=collider_poses, external_force=external_force)
        new = step_mod.step(self.model, state, control, self.config, timer, self.stages)
        force = control.external_force
        if isinstance(force, _CheckedForce) and force.nonfinite is not None:  # a callable's NaN: the input's fault
            first = (state.diverged_frame < 0) & (new.diverged_frame >= 0)
            new = new.replace(diverged_input=torch.where(first, new.diverged_input | force.nonfinite,
                                                         new.diverged_input))
        every = self.check_every
        if every and not torch.compiler.is_compiling():  # compiled: call sim.check(state) yourself
            self._frames += 1
            if self._frames % every == 0:
                self.check(new)
        return new

    def check(self, state: State) -> None:
        """Read the state's divergence and grid-overflow flags (one host sync) and raise
        :class:`~ams_torch.sim.stepping.SimulationDiverged` naming the first bad frame and strands if it
        is set (:class:`~ams_torch.sim.stepping.GridOverflow` for the grid). ``step`` calls it every
        ``params.check_every`` frames, except under ``torch.compile``, where the caller decides when
        to check (the flags keep the first bad frame meanwhile)."""
        step_mod.check_state(state, self.config, self.model.hair_hair)

    forward = step
