"""Grooms: the :class:`Groom` container, procedural growth and presets (SPEC §9), the default
head, simple analytic grooms, and file formats (:mod:`ams_torch.grooms.io`).

Imports only :mod:`ams_torch.geometry`.
"""
from ams_torch.grooms import io
from ams_torch.grooms.groom import Groom, resample_strands
from ams_torch.grooms.growth import GrowthParams, grow
from ams_torch.grooms.presets import PRESETS, preset
from ams_torch.grooms.head import default_head
from ams_torch.grooms.io import read_groom, write_groom

__all__ = ["Groom", "resample_strands", "grow", "preset", "PRESETS", "GrowthParams", "default_head", "read_groom",
           "write_groom", "io"]
