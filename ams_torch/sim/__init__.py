"""The AMS strand dynamics (SPEC §1–5, §7): parameters, the fixed model, the state, one function
per physical term, the system assembly, the frame's dynamics, inextensibility, the pure frame step and the
``torch.nn.Module`` wrapper :class:`Simulator`.

Imports :mod:`ams_torch.stages`, :mod:`ams_torch.solver`, :mod:`ams_torch.native` and :mod:`ams_torch.geometry`.
"""
from ams_torch.sim.model import Coefficients, Model, coefficients
from ams_torch.sim.builder import ModelBuilder, make_config
from ams_torch.sim.params import Params
from ams_torch.sim.simulator import Simulator
from ams_torch.sim.state import Config, Control, State
from ams_torch.sim.stepping import SimulationDiverged, check_state, step
from ams_torch.sim.rollout import Rollout, rollout

__all__ = ["Params", "Simulator", "Model", "ModelBuilder", "make_config", "State", "Control", "Config", "step",
           "check_state", "SimulationDiverged", "Coefficients", "coefficients", "rollout", "Rollout"]
