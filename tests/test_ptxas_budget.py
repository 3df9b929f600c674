"""Registers, spills, stack and shared memory of every CUDA kernel (``nvcc -Xptxas -v``, no GPU needed)
against the committed budget ``ams_torch/native/csrc/common/ptxas_budget.json``, for each
architecture it names (sm_80, sm_90, sm_120). ptxas reports are cached by source, architecture and
nvcc version, so only a changed kernel is recompiled.

A kernel over its budget, spilling, or missing from it fails: if the change is deliberate, rewrite
the budget (``python -m ams_torch.native.ptxas --write-budget``) and say why in the commit.
"""
from __future__ import annotations

from pathlib import Path

import pytest

from ams_torch.native import ptxas

SAMPLE = """\
ptxas info    : 0 bytes gmem
ptxas info    : Compiling entry function '_ZN9ams_torch6banded12_GLOBAL__N_112solve_kernelIdEEvPT_S4_ll' for 'sm_90'
ptxas info    : Function properties for _ZN9ams_torch6banded12_GLOBAL__N_112solve_kernelIdEEvPT_S4_ll
    24 bytes stack frame, 32 bytes spill stores, 68 bytes spill loads
ptxas info    : Used 128 registers, used 0 barriers, 24 bytes cumulative stack size
ptxas info    : Compile time = 413.546 ms
ptxas info    : Function properties for __internal_accurate_pow
    0 bytes stack frame, 0 bytes spill stores, 0 bytes spill loads
ptxas info    : Compiling entry function '_ZN9ams_torch6banded12_GLOBAL__N_116transpose_kernelIfEEvPKT_PS3_ll' for 'sm_90'
ptxas info    : Function properties for _ZN9ams_torch6banded12_GLOBAL__N_116transpose_kernelIfEEvPKT_PS3_ll
    0 bytes stack frame, 0 bytes spill stores, 0 bytes spill loads
ptxas info    : Used 36 registers, used 1 barriers, 4224 bytes smem
"""


def test_parse_ptxas_report():
    got = ptxas.parse(SAMPLE)
    solve = got["_ZN9ams_torch6banded12_GLOBAL__N_112solve_kernelIdEEvPT_S4_ll"]
    assert solve == {"registers": 128, "spill_bytes": 100, "stack_bytes": 24, "shared_bytes": 0, "barriers": 0}
    tr = got["_ZN9ams_torch6banded12_GLOBAL__N_116transpose_kernelIfEEvPKT_PS3_ll"]
    assert tr == {"registers": 36, "spill_bytes": 0, "stack_bytes": 0, "shared_bytes": 4224, "barriers": 1}
    assert len(got) == 2  # __internal_accurate_pow is not an entry
    assert ptxas.short_name("void ams_torch::banded::(anonymous namespace)::solve_kernel<double>(double*, long)") \
        == "solve_kernel<double>"
    assert ptxas.short_name("void ams_torch::frame::transpose_batch_kernel<float>(ams_torch::frame::"
                            "TransposeBatch<float>)") == "transpose_batch_kernel<float>"


def test_violations_name_the_kernel_and_the_excess():
    budget = {"kernels": {"a.cu:k<double>": {"registers": {"90": 128}, "spill_bytes": 0, "stack_bytes": 0,
                                             "shared_bytes": 0}}}
    use = {"registers": 130, "spill_bytes": 8, "stack_bytes": 0, "shared_bytes": 0, "barriers": 0}
    bad = ptxas.violations({"90": {"a.cu:k<double>": use, "a.cu:new<float>": use}}, budget)
    assert "sm_90 a.cu:k<double>: registers 130 > budget 128" in bad
    assert "sm_90 a.cu:k<double>: spill_bytes 8 > budget 0" in bad
    assert any("a.cu:new<float>: not in the budget" in b for b in bad)
    ok = dict(use, registers=120, spill_bytes=0)
    assert ptxas.violations({"90": {"a.cu:k<double>": ok}}, budget) == []


def test_every_kernel_within_its_budget():
    nvcc = ptxas.find_nvcc()
    if nvcc is None:
        pytest.skip("nvcc not found")
    budget = ptxas.load_budget()
    found = ptxas.reports(budget["arches"], nvcc, jobs=2)
    sources = {rel for rel, _ in ptxas.kernel_sources()}
    csrc = Path(ptxas._build.CSRC_ROOT)
    on_disk = {str(p.relative_to(csrc)) for p in csrc.rglob("*.cu") if p.parts[-2] != "emulation"}
    assert sources == on_disk  # every production .cu file is in the build table, so it is checked here
    for arch in budget["arches"]:
        assert {name.split(":")[0] for name in found[arch]} == sources, arch  # every file has kernels
    bad = ptxas.violations(found, budget)
    assert not bad, "\n".join(bad) + "\n" + ptxas.table(found)
