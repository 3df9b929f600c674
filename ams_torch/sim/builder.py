"""Builder → Model: collect a groom, its material and the stages' fixed data, then build.

In the spirit of Newton's ``ModelBuilder`` (STYLE.md): a :class:`ModelBuilder` collects the rest
positions, the :class:`~ams_torch.Params`, which material fields are learnable, the hair–hair
grid settings and the colliders; :meth:`ModelBuilder.finalize` validates them once and returns a
complete :class:`~ams_torch.sim.model.Model` (its hair–hair grid and colliders built, on one
device and dtype, its Params frozen), and :func:`make_config` the frozen
:class:`~ams_torch.sim.state.Config` the step branches on. :class:`~ams_torch.Simulator` is this
plus a backend choice and the initial pose.

    >>> import torch
    >>> from ams_torch import HairHair, Params
    >>> from ams_torch.grooms.simple import sphere_groom
    >>> from ams_torch.stages.collide import SphereCollider
    >>> builder = ModelBuilder(sphere_groom(8, 12), Params(), dtype=torch.float64)
    >>> builder.add_collider(SphereCollider((0.0, 0.0, 0.0), 0.08)).set_hair_hair(HairHair(resolution=8))
    <ams_torch.sim.builder.ModelBuilder object at ...>
    >>> model = builder.finalize()
    >>> config = make_config(model, backend="torch")
    >>> (model.num_strands, model.num_particles, len(model.colliders), config.colliders, config.hair_hair)
    (8, 12, 1, 1, True)
"""
from __future__ import annotations

import copy
from typing import Optional

import torch

from ams_torch.sim.model import Model, warn_if_no_sag_offset
from ams_torch.sim.params import ANGULAR_FIELD, INTEGRITY_FIELD, Params
from ams_torch.sim.state import Config
from ams_torch.stages.collide import Collider, MeshCollider
from ams_torch.stages.hair_hair import HairHair

__all__ = ["ModelBuilder", "make_config"]


class ModelBuilder:
    """Collects what is fixed for one groom and builds the :class:`~ams_torch.sim.model.Model`.

    Args:
        rest_positions: (S, N, 3) metres, the rest shape in the head frame (array or tensor).
        params: the :class:`~ams_torch.Params` (validated now; the model keeps a frozen copy).
        device, dtype: of every tensor of the model (float32 by default).
    """

    def __init__(self, rest_positions, params: Optional[Params] = None, *, device=None,
                 dtype: torch.dtype = torch.float32):
        params = Params() if params is None else params
        if not isinstance(params, Params):
            raise ValueError(f"params must be an ams_torch.Params; got {type(params).__name__}")
        params.validate()
        self.rest_positions = rest_positions
        self.params = params
        self.device, self.dtype = device, dtype
        self.learnable: tuple = ()
        self.hair_hair: Optional[HairHair] = None
        self.colliders: list = []

    def set_learnable(self, *fields: str) -> "ModelBuilder":
        """Make these Params material fields ``nn.Parameter`` s of the model (checked by finalize)."""
        self.learnable = tuple(fields)
        return self

    def set_hair_hair(self, settings: Optional[HairHair]) -> "ModelBuilder":
        """The hair–hair stage's settings (SPEC §6); None: no grid, no hair–hair code."""
        if settings is not None and not isinstance(settings, HairHair):
            raise ValueError(f"hair_hair must be a HairHair config or None; got {type(settings).__name__}")
        self.hair_hair = settings
        return self

    def add_collider(self, collider: Collider) -> "ModelBuilder":
        """A collider of the hair–solid stage (SPEC §8). The model gets its own copy, on its device
        and dtype (a mesh collider's SDF is built by finalize, not inside the first frame)."""
        if not isinstance(collider, Collider):
            raise ValueError(f"colliders must be ams_torch collider objects; got {type(collider).__name__}")
        self.colliders.append(collider)
        return self

    def finalize(self) -> Model:
        """The complete :class:`~ams_torch.sim.model.Model`: rest data, coefficients, frozen Params,
        the hair–hair grid and the colliders. Warns once when the sag-free offset is undefined."""
        cols = []
        for c in self.colliders:
            c = copy.deepcopy(c).to(device=self.device, dtype=self.dtype)
            if isinstance(c, MeshCollider):
                c.build()
            cols.append(c)
        model = Model(self.rest_positions, self.params, learnable=self.learnable, device=self.device,
                      dtype=self.dtype, hair_hair=self.hair_hair, colliders=cols)
        warn_if_no_sag_offset(self.params)
        return model


def _is_zero(v) -> bool:
    return not isinstance(v, torch.Tensor) and float(v) == 0.0


def make_config(model: Model, backend: str = "torch") -> Config:
    """The frozen :class:`~ams_torch.sim.state.Config` of a built model: the step's static choices.
    Terms that are exactly zero (and not learnable) are not computed. ``backend``: "torch" or
    "native", already resolved (:func:`ams_torch.sim.backends.resolve_backend`)."""
    params = model.params
    off = lambda name: _is_zero(getattr(params, name)) and name not in model.learnable  # noqa: E731
    integrity = "none" if off(INTEGRITY_FIELD[params.material]) else params.integrity_model
    return Config(dt=float(params.dt), substeps=int(params.substeps), integrity_model=integrity,
                  angular=not off(ANGULAR_FIELD[params.material]), angular_reaction=params.angular_reaction,
                  implicit_angular=params.implicit_angular, geometric_stiffness=params.geometric_stiffness,
                  inextensibility=params.inextensibility, ftl_damping=float(params.ftl_damping),
                  collision_rounds=int(params.collision_inextensibility), contact=params.contact,
                  colliders=len(model.colliders), hair_hair=model.hair_hair is not None,
                  max_relative_speed=float(params.max_relative_speed), backend=backend)
