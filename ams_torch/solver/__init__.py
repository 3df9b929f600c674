"""The banded strand solve (SPEC §4): plain-torch reference and the ``ams_torch::solve_banded`` op,
whose native kernels (``ams_torch/native/csrc/banded``) :mod:`ams_torch.native` builds lazily.

Imports only :mod:`ams_torch.native` (the bottom layer, beside :mod:`ams_torch.geometry`).
"""
from ams_torch.native.build import NativeBuildWarning, native_status
from ams_torch.solver.op import solve_banded
from ams_torch.solver.reference import banded_matvec, banded_to_dense, solve_banded_dense, solve_banded_plain

__all__ = ["solve_banded", "native_status", "NativeBuildWarning", "solve_banded_plain", "solve_banded_dense",
           "banded_to_dense", "banded_matvec"]
