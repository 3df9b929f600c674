"""Guide-to-dense interpolation: the benchmark and its baselines (SPEC §11).

- :class:`Interpolator` (:mod:`baselines.protocol`): what a method implements (``fit``,
  ``predict``, optional causal ``reset``/``step``) and the samples it is given;
  :func:`resolve_method` finds one by built-in name, ``package.module:factory`` or entry point.
- :mod:`baselines.methods`: the built-ins that learn nothing (``rigid``, ``nearest``,
  ``skinning``, ``blend``, ``skinning+pushout``); :mod:`baselines.learned`: the learned ones (``upsampler``,
  ``temporal``, ``collision``, ``agnostic``).
- :mod:`baselines.metrics`: fidelity against the dense simulation, each with a known-answer test.
- :mod:`baselines.bench`: ``ams-torch bench-interp`` (datasets or suites → results.json,
  leaderboard.md, plots); :mod:`baselines.cost`: ms/frame against dense simulation.
- :func:`select_guides`, :class:`LinearHairSkinning`: guide selection and linear hair skinning.
"""
from .guides import fps_order, select_guides
from .skinning import LinearHairSkinning
from .protocol import Interpolator, MethodError, resolve_method
from . import metrics

__all__ = ["Interpolator", "MethodError", "resolve_method", "select_guides", "fps_order", "LinearHairSkinning",
           "metrics"]
