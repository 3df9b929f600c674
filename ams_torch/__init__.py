"""ams_torch: dense hair simulation with the Augmented Mass-Spring model in PyTorch.

The public API is small:

- :class:`Params`: the model's parameters (SI units).
- :class:`Simulator`: ``Simulator(rest_positions, params).initial_state()`` / ``.step(state, pose)``.
- :class:`Pose`: a rigid head pose with its velocities.
- :func:`solve_banded`: the batched banded block-Cholesky strand solve.
- :class:`HairHair`: hair–hair interaction settings (``Simulator(..., hair_hair=HairHair())``).
- :func:`default_head`, :class:`SDFGrid` and the colliders (``Simulator(..., colliders=[...])``).
- :func:`grow`, :func:`preset`, :class:`Groom`, :func:`read_groom` / :func:`write_groom` (grooms and file formats).
- :class:`State`, :class:`SimulationDiverged`.
- :func:`make_motion` (head motions), :class:`Wind`, :func:`load_scene` (TOML scenes; the
  ``ams-torch`` command line in :mod:`ams_torch.cli`).
"""
from .colliders import CapsuleCollider, HollowSphereCollider, MeshCollider, PlaneCollider, SphereCollider
from . import io
from .groom import Groom, resample_strands
from .growth import PRESETS, GrowthParams, grow, preset
from .hair_hair import HairHair
from .io import read_groom, write_groom
from .head import default_head, load_mesh
from .integrator import SimulationDiverged
from .model import State
from .ops import solve_banded
from .params import Params
from .pose import Pose
from .sdf import SDFGrid
from .simulator import Simulator
from .motion import make_motion
from .wind import Wind
from .scene import SceneError, load_scene

__version__ = "0.1.0"

__all__ = ["Params", "Simulator", "Pose", "State", "solve_banded", "SimulationDiverged", "HairHair",
           "default_head", "load_mesh", "SDFGrid", "SphereCollider", "MeshCollider", "CapsuleCollider",
           "PlaneCollider", "HollowSphereCollider",
           "grow", "preset", "GrowthParams", "PRESETS", "Groom", "resample_strands", "io", "read_groom", "write_groom",
           "make_motion", "Wind", "load_scene", "SceneError", "__version__"]
