"""ams_torch: dense hair simulation with the Augmented Mass-Spring model in PyTorch.

The names a first simulation needs::

    import ams_torch as at
    groom = at.preset("straight", strands=1000, particles=32)     # grown on at.default_head()
    sim = at.Simulator(groom.rest_positions, at.Params(),
                       colliders=[at.MeshCollider(at.default_head())], hair_hair=at.HairHair(resolution=64))
    state = sim.initial_state()
    state = sim.step(state, pose)                                  # pose: at.Pose

Everything else lives in the subpackages, which import downwards only (no cycles)::

    apps      motion, scene files, recipes, dataset generation and reading, render, CLI
    grooms    Groom, growth and presets, the default head, file formats (io)      → geometry
    sim       Params, ModelBuilder → Model, State/Control/Config, forces, assembly, stepping
              (the stage table), Simulator          → stages, solver, native, geometry
    stages    collisions (colliders), hair–hair grid, wind                → geometry, native
    solver    the banded strand solve and its op                                  → native
    native    lazy build and cache of the C++/CUDA kernels (csrc/), CUDA emulation
    geometry  Pose, SDF grids, mesh loading
"""
from ams_torch import apps, geometry, grooms, sim, solver, stages
from ams_torch.geometry.pose import Pose
from ams_torch.grooms.presets import preset
from ams_torch.grooms.head import default_head
from ams_torch.grooms.io import read_groom, write_groom
from ams_torch.native.build import native_status
from ams_torch.sim.params import Params
from ams_torch.sim.simulator import Simulator
from ams_torch.sim.state import State
from ams_torch.sim.stepping import SimulationDiverged
from ams_torch.stages.collide import MeshCollider
from ams_torch.stages.hair_hair import HairHair

__version__ = "0.1.0"

__all__ = ["Params", "Simulator", "State", "Pose", "HairHair", "MeshCollider", "default_head", "preset",
           "read_groom", "write_groom", "SimulationDiverged", "native_status",
           "apps", "geometry", "grooms", "sim", "solver", "stages", "__version__"]
