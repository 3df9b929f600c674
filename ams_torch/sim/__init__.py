"""The AMS strand dynamics (SPEC §1–5, §7): parameters, the fixed model, the state, one function
per physical term, the system assembly, inextensibility, the pure frame step and the
``torch.nn.Module`` wrapper :class:`Simulator`.

Imports :mod:`ams_torch.stages`, :mod:`ams_torch.solver` and :mod:`ams_torch.geometry`.
"""
from ams_torch.sim.integrator import SimulationDiverged
from ams_torch.sim.model import State
from ams_torch.sim.params import Params
from ams_torch.sim.simulator import Simulator

__all__ = ["Params", "Simulator", "State", "SimulationDiverged"]
