"""The native kernels: C++/CUDA sources (``csrc/``, one folder per op, shared headers in
``csrc/common``), their lazy build and cache (:mod:`~ams_torch.native.build`, :mod:`~ams_torch.native.cache`,
:mod:`~ams_torch.native.cuda_arch`), the smoke tests run after loading (:mod:`~ams_torch.native.probes`),
the CUDA emulation of the tests (:mod:`~ams_torch.native.emulation`) and the ptxas budget
(:mod:`~ams_torch.native.ptxas`). The ops these kernels implement are registered where their torch
definitions live (:mod:`ams_torch.solver.op`, :mod:`ams_torch.sim.native`, ...); ``docs/native.md``.

Imports nothing else of ams_torch (the bottom layer). Nothing is compiled at import.
"""
from ams_torch.native.build import NativeBuildWarning, native_status

__all__ = ["native_status", "NativeBuildWarning"]
