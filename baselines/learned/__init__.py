"""Learned guide-to-dense methods of the benchmark (each an :class:`~baselines.protocol.Interpolator`
registered under its built-in name when this package is imported).

- ``upsampler`` (:class:`Upsampler`): skinning + the per-strand residual MLP of
  :class:`baselines.upsampler.GuideUpsampler`, bound to the groom it was trained on;
- ``agnostic`` (:class:`Agnostic`): a residual MLP on each strand's guide neighbourhood, for any
  groom with the trained number of particles per strand;
- ``collision`` (:class:`Collision`): ``agnostic`` plus signed-distance inputs of the head and
  colliders and a penetration loss;
- ``temporal`` (:class:`Temporal`): a causal GRU residual over the guides' recent motion
  (``reset``/``step`` streaming).

All train through one loop (:func:`baselines.learned.train.fit_method`): windows streamed from
the dataset, validation loss, plateau schedule, early stopping, atomic resumable checkpoints,
DDP when ``torch.distributed`` is initialised. ``scripts/train_interp.py`` runs it from the
command line.
"""
from .base import TRAIN_DEFAULTS, LearnedInterpolator
from .upsampler import Upsampler
from .agnostic import Agnostic
from .collision import Collision
from .temporal import Temporal

__all__ = ["TRAIN_DEFAULTS", "LearnedInterpolator", "Upsampler", "Agnostic", "Collision", "Temporal"]
