"""Guide-strand interpolation baselines (SPEC §11).

- :func:`select_guides`: choose guide strands (farthest-point sampling or k-means on roots).
- :class:`LinearHairSkinning`: dense strands from their K nearest guides with parallel-transported
  frames.
- :mod:`baselines.upsampler`: a small neural residual on top of skinning.
- :mod:`baselines.metrics`: fidelity against the dense simulation (errors in mm).
- :mod:`baselines.data`: a small simulated HDF5 dataset (generator + reader).
"""
from .guides import fps_order, select_guides
from .skinning import LinearHairSkinning
from . import metrics

__all__ = ["select_guides", "fps_order", "LinearHairSkinning", "metrics"]
