"""Shared helpers of the benchmark scripts (``scripts/bench_*.py``): the machine a result was
measured on, and device-synchronised timing. Not part of the public API."""
from __future__ import annotations

import contextlib
import os
import platform
import statistics
import time
from typing import Callable, Tuple

import torch

__all__ = ["machine_info", "machine", "sync", "median_ms", "shown_args"]


def machine_info(device="cpu") -> dict:
    """What the numbers were measured on: CPU model, logical cores, torch version and threads,
    the GPU (when ``device`` is CUDA) and the 1-minute load average now."""
    device = torch.device(device)
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    return {
        "threads": torch.get_num_threads(),
        "cpu_cores": os.cpu_count(),
        "torch": str(torch.__version__),
        "cpu": cpu,
        "gpu": torch.cuda.get_device_name(device) if device.type == "cuda" else None,
        "cuda": torch.version.cuda if device.type == "cuda" else None,
        "load_avg_1min_at_start": round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else None,
    }


def machine(device="cpu") -> str:
    """One line naming the machine (see :func:`machine_info`)."""
    i = machine_info(device)
    desc = f"{i['cpu']}, {i['cpu_cores']} logical CPUs, torch {i['torch']}, {i['threads']} threads"
    if i["gpu"]:
        desc = f"{i['gpu']} (CUDA {i['cuda']}); host: {desc}"
    return desc


def sync(device) -> None:
    """Wait for the device (CUDA) before reading a clock."""
    device = torch.device(device)
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def stage_timer(device, acc: dict):
    """A ``timer(name)`` context manager for ``Simulator(stage_timer=...)``: adds each stage's
    wall time (s, device synchronised before and after) to ``acc[name]``."""
    @contextlib.contextmanager
    def timer(name):
        sync(device)
        t = time.perf_counter()
        yield
        sync(device)
        acc[name] = acc.get(name, 0.0) + time.perf_counter() - t

    return timer


def median_ms(fn: Callable[[], object], device="cpu", repeats: int = 5, time_cap: float = 20.0,
              min_repeats: int = 3) -> Tuple[float, int]:
    """Median wall time of ``fn()`` in ms after one warm-up call, synchronising the device
    around every call; between ``min_repeats`` and ``repeats`` timed calls, as many as fit in
    ``time_cap`` seconds. Returns (median ms, timed calls)."""
    sync(device)
    t0 = time.perf_counter()
    fn()
    sync(device)
    warm = time.perf_counter() - t0
    n = max(min(min_repeats, repeats), min(repeats, int(time_cap / max(warm, 1e-9))))
    times = []
    for _ in range(n):
        sync(device)
        t0 = time.perf_counter()
        fn()
        sync(device)
        times.append(time.perf_counter() - t0)
    return statistics.median(times) * 1e3, n


def shown_args(argv=None, hide=("--note", "--out")) -> str:
    """The command-line arguments as one string, without the options in ``hide`` and their
    values (``--note`` text is printed apart; an output folder is no part of the setting)."""
    import sys

    argv = list(sys.argv[1:] if argv is None else argv)
    shown, i = [], 0
    while i < len(argv):
        a = argv[i]
        if a in hide:
            i += 2
            continue
        if not any(a.startswith(h + "=") for h in hide):
            shown.append(a)
        i += 1
    return " ".join(shown)
