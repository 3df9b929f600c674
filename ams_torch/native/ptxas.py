"""Registers, spills, stack and shared memory of every CUDA kernel, from ``nvcc -Xptxas -v``, and
their committed budget (``csrc/common/ptxas_budget.json``).

Needs nvcc, not a GPU: each ``.cu`` file of the build table is compiled to a cubin for each
architecture and ptxas's report is parsed per kernel (names demangled to ``file:kernel<type>``).
Reports are cached (``<cache root>/ptxas/``) by nvcc version, architecture, flags and the sources.

Budget per kernel (checked for every architecture the budget names): ``registers`` per
architecture at most (measured + 10 %, never above a ``__launch_bounds__`` cap), no spilled bytes, ``stack_bytes`` and
``shared_bytes`` at most. A kernel not in the budget is a failure too: a new kernel gets a budget
(``python -m ams_torch.native.ptxas --write-budget`` measures and writes one, 10 % headroom on
registers; review the diff).

Command line: ``python -m ams_torch.native.ptxas [--arch 90 ...] [--json OUT] [--write-budget]``
prints a table and the budget violations (exit status 1 when there are some).
"""
from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import re
import shutil
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Dict, List, Optional, Sequence

from ams_torch.native import build as _build

BUDGET_PATH = _build.CSRC_ROOT / "common" / "ptxas_budget.json"
FLAGS = ["-std=c++17", "-O3"]
_ENTRY = re.compile(r"Compiling entry function '([^']+)' for '(sm_\w+)'")
_PROPS = re.compile(r"Function properties for (\S+)")
_FRAME = re.compile(r"(\d+) bytes stack frame, (\d+) bytes spill stores, (\d+) bytes spill loads")
_USED = re.compile(r"Used (\d+) registers(?:, used (\d+) barriers)?(?:, (\d+) bytes cumulative stack size)?"
                   r"(?:, (\d+) bytes smem)?")


def kernel_sources() -> List[tuple]:
    """(source relative to csrc/, its headers) for every .cu file of the production CUDA backends."""
    out = []
    for name, sources, headers, namespace, device in _build._BACKENDS.values():
        if device == "cuda":
            out += [(s, tuple(headers)) for s in sources if s.endswith(".cu")]
    return out


def find_nvcc() -> Optional[str]:
    from torch.utils import cpp_extension

    for cand in (os.environ.get("NVCC"), cpp_extension.CUDA_HOME and str(Path(cpp_extension.CUDA_HOME, "bin", "nvcc")),
                 shutil.which("nvcc")):
        if cand and Path(cand).exists():
            return cand
    return None


def _demangle(names: Sequence[str]) -> Dict[str, str]:
    tool = shutil.which("c++filt")
    if tool is None or not names:
        return {n: n for n in names}
    proc = subprocess.run([tool], input="\n".join(names), capture_output=True, text=True, timeout=60)
    return dict(zip(names, proc.stdout.splitlines())) if proc.returncode == 0 else {n: n for n in names}


def short_name(demangled: str) -> str:
    """``void ns::(anonymous namespace)::frame_kernel<double>(...)`` -> ``frame_kernel<double>``."""
    text = demangled[5:] if demangled.startswith("void ") else demangled
    depth, end = 0, len(text)
    for i, c in enumerate(text):
        if c == "<":
            depth += 1
        elif c == ">":
            depth -= 1
        elif c == "(" and depth == 0 and not text.startswith("(anonymous", i):
            end = i
            break
    head = text[:end]
    depth, start = 0, 0
    for i, c in enumerate(head):
        if c == "<":
            depth += 1
        elif c == ">":
            depth -= 1
        elif depth == 0 and head.startswith("::", i):
            start = i + 2
    return head[start:]


def parse(text: str) -> Dict[str, dict]:
    """ptxas's ``-v`` output -> {mangled kernel: {registers, spill_bytes, stack_bytes, shared_bytes,
    barriers}} (entry functions only)."""
    out: Dict[str, dict] = {}
    current = None
    props: Dict[str, tuple] = {}
    prop_name = None
    for line in text.splitlines():
        m = _ENTRY.search(line)
        if m:
            current = m.group(1)
            out[current] = {"registers": 0, "spill_bytes": 0, "stack_bytes": 0, "shared_bytes": 0, "barriers": 0}
            continue
        m = _PROPS.search(line)
        if m:
            prop_name = m.group(1)
            continue
        m = _FRAME.search(line)
        if m and prop_name is not None:
            props[prop_name] = (int(m.group(1)), int(m.group(2)) + int(m.group(3)))
            continue
        m = _USED.search(line)
        if m and current is not None:
            k = out[current]
            k["registers"] = int(m.group(1))
            k["barriers"] = int(m.group(2) or 0)
            k["shared_bytes"] = int(m.group(4) or 0)
            stack, spill = props.get(current, (0, 0))
            k["stack_bytes"] = max(stack, int(m.group(3) or 0))
            k["spill_bytes"] = spill
            current = None
    return out


def _cache_file(rel: str, headers: Sequence[str], arch: str, nvcc: str) -> Path:
    h = hashlib.sha256()
    h.update(json.dumps([arch, FLAGS, _build._tool_version([nvcc, "--version"])]).encode())
    for f in (rel, *headers):
        h.update(f.encode())
        h.update((_build.CSRC_ROOT / f).read_bytes())
    return _build.cache_root() / "ptxas" / f"{Path(rel).stem}-sm{arch}-{h.hexdigest()[:16]}.json"


def report(rel: str, headers: Sequence[str], arch: str, nvcc: str) -> Dict[str, dict]:
    """{``rel:kernel<type>``: usage} of one .cu file for ``sm_<arch>`` (cached)."""
    cached = _cache_file(rel, headers, arch, nvcc)
    if cached.exists():
        try:
            return json.loads(cached.read_text())
        except ValueError:
            pass
    includes = [f"-I{_build.CSRC_ROOT}"]
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [nvcc, *FLAGS, "-cubin", f"-arch=sm_{arch}", "-Xptxas", "-v", *includes,
               str(_build.CSRC_ROOT / rel), "-o", str(Path(tmp) / "k.cubin")]
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=900)
    if proc.returncode != 0:
        raise RuntimeError(f"nvcc failed on {rel} for sm_{arch}:\n{proc.stderr[-3000:]}")
    raw = parse(proc.stdout + proc.stderr)
    names = _demangle(list(raw))
    out = {f"{rel}:{short_name(names[k])}": v for k, v in raw.items()}
    cached.parent.mkdir(parents=True, exist_ok=True)
    tmpfile = cached.with_suffix(f".{os.getpid()}.tmp")
    tmpfile.write_text(json.dumps(out, indent=1, sort_keys=True))
    os.replace(tmpfile, cached)
    return out


def reports(arches: Sequence[str], nvcc: str, jobs: int = 2) -> Dict[str, Dict[str, dict]]:
    """{arch: {kernel: usage}} for every production .cu file (files compiled ``jobs`` at a time)."""
    tasks = [(rel, headers, arch) for arch in arches for rel, headers in kernel_sources()]
    with ThreadPoolExecutor(max_workers=max(1, jobs)) as pool:
        results = list(pool.map(lambda t: (t[2], report(t[0], t[1], t[2], nvcc)), tasks))
    out: Dict[str, Dict[str, dict]] = {a: {} for a in arches}
    for arch, usage in results:
        out[arch].update(usage)
    return out


def load_budget(path: Path = BUDGET_PATH) -> dict:
    return json.loads(Path(path).read_text())


def violations(found: Dict[str, Dict[str, dict]], budget: dict) -> List[str]:
    """What exceeds the budget (one line each), and kernels it does not know."""
    out = []
    limits = budget["kernels"]
    for arch, kernels in sorted(found.items()):
        for name, use in sorted(kernels.items()):
            lim = limits.get(name)
            if lim is None:
                out.append(f"sm_{arch} {name}: not in the budget ({BUDGET_PATH.name}); give it one")
                continue
            regs = lim["registers"]
            regs = regs.get(arch, max(regs.values())) if isinstance(regs, dict) else regs
            for key, cap in (("registers", regs), ("spill_bytes", lim.get("spill_bytes", 0)),
                             ("stack_bytes", lim.get("stack_bytes", 0)), ("shared_bytes", lim.get("shared_bytes", 0))):
                if use[key] > cap:
                    out.append(f"sm_{arch} {name}: {key} {use[key]} > budget {cap}")
    return out


def measured_budget(found: Dict[str, Dict[str, dict]], previous: Optional[dict] = None) -> dict:
    """A budget from measurements: registers per architecture + 10 % (at most 255, at most a kernel's
    launch-bounds cap), no spills, stack and shared memory as measured."""
    kernels: Dict[str, dict] = {}
    caps = (previous or {}).get("launch_bounds_caps", {})
    for arch, ks in sorted(found.items()):
        for name, use in ks.items():
            k = kernels.setdefault(name, {"registers": {}, "spill_bytes": 0, "stack_bytes": 0, "shared_bytes": 0})
            cap = caps.get(name, 255)
            cap = cap.get(arch, 255) if isinstance(cap, dict) else cap
            k["registers"][arch] = min(255, cap, int(math.ceil(use["registers"] * 1.1)))
            k["stack_bytes"] = max(k["stack_bytes"], use["stack_bytes"])
            k["shared_bytes"] = max(k["shared_bytes"], use["shared_bytes"])
    return {"about": (previous or {}).get("about", ""), "arches": sorted(found),
            "launch_bounds_caps": caps, "kernels": dict(sorted(kernels.items()))}


def table(found: Dict[str, Dict[str, dict]]) -> str:
    lines = [f"{'arch':<6} {'kernel':<62} {'regs':>5} {'spill':>6} {'stack':>6} {'smem':>6}"]
    for arch, ks in sorted(found.items()):
        for name, u in sorted(ks.items()):
            lines.append(f"sm_{arch:<3} {name:<62} {u['registers']:>5} {u['spill_bytes']:>6} {u['stack_bytes']:>6} "
                         f"{u['shared_bytes']:>6}")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--arch", nargs="*", help="architectures, e.g. 90 120 (default: the budget's)")
    ap.add_argument("--json", type=Path, help="write {arch: {kernel: usage}} here")
    ap.add_argument("--write-budget", action="store_true", help="measure and rewrite the committed budget")
    ap.add_argument("--jobs", type=int, default=2)
    args = ap.parse_args(argv)
    nvcc = find_nvcc()
    if nvcc is None:
        print("error: nvcc not found (set CUDA_HOME or NVCC)", file=sys.stderr)
        return 2
    budget = load_budget() if BUDGET_PATH.exists() else None
    arches = args.arch or (budget["arches"] if budget else ["90"])
    found = reports(arches, nvcc, args.jobs)
    print(table(found))
    if args.json:
        args.json.write_text(json.dumps(found, indent=1, sort_keys=True))
    if args.write_budget:
        BUDGET_PATH.write_text(json.dumps(measured_budget(found, budget), indent=1) + "\n")
        print(f"wrote {BUDGET_PATH}")
        return 0
    bad = violations({a: k for a, k in found.items() if budget and a in budget["arches"]}, budget) if budget else []
    for line in bad:
        print("over budget:", line)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
