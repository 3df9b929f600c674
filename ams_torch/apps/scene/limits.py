"""What a scene may ask for, and what it will cost, checked before anything is allocated.

- :data:`RANGES`: the bounds of the scene keys whose size drives memory or run time (strands,
  particles, grid and SDF resolutions, substeps, rounds, iterations, frames, the picture size)
  and of the physical values whose absurd magnitudes would otherwise surface as a divergence
  ("try more substeps") or an overflow far from the key (lengths, speeds, gravity, dt). The
  scene tables apply them (:func:`check_range`), so recipes get them for every sampler value.
- :func:`estimate_memory`: bytes a validated scene needs, by part, from its sizes (strands ×
  particles × scenes simulated together, the hair–hair grid R³, the head SDF's samples,
  substeps), with per-unit costs measured on this library (``docs/reliability.md``).
- :func:`check_memory`: refuse a scene whose estimate exceeds the memory available (or a
  ``--max-memory`` the user sets), naming the estimate, the largest part and its keys.
"""
from __future__ import annotations

import math
import os
import re
from typing import Dict, Optional, Tuple

from ams_torch.geometry.sdf import MAX_RESOLUTION

__all__ = ["RANGES", "check_range", "estimate_memory", "check_memory", "parse_size", "available_memory",
           "format_size", "MemoryLimitError"]

_M = 1e3  # metres: the largest length a scene value may take
#: "[section].key" (collider sections as "[colliders[]]") -> (low, high, unit); numbers, and each
#: component of a vector, must lie in [low, high]
RANGES: Dict[str, Tuple[float, float, str]] = {
    # sizes: memory and time
    "frames": (1, 10**7, "frames"), "substeps": (1, 10**4, "substeps"), "scale": (0, 1e3, "× strands"),
    "[params].substeps": (1, 10**4, "substeps"), "[params].collision_inextensibility": (0, 100, "rounds"),
    "[params].num_pinned": (0, 4096, "particles"), "[params].check_every": (0, 10**7, "frames"),
    "[groom].strands": (1, 10**7, "strands"), "[groom].particles": (4, 4096, "particles per strand"),
    "[groom.growth].steps": (1, 4096, "growth steps"), "[groom.growth].step": (1e-4, 1.0, "m per growth step"),
    "[groom.growth].length": (0, 10.0, "m"), "[groom.growth].sdf_resolution": (8, MAX_RESOLUTION, "samples"),
    "[head].sdf_resolution": (8, MAX_RESOLUTION, "samples along the longest side (the SDF's limit)"),
    "[hair_hair].resolution": (2, 1024, "cells per axis"), "[hair_hair].pressure_iterations": (0, 10**4, "sweeps"),
    "[hair_hair].collision_max_per_cell": (1, 1024, "particles"), "[hair_hair].bounds_padding": (0, 100, "× the side"),
    "[render].size": (0.16, 81.92, "inches (16 to 8192 pixels at 100 dpi)"), "[render].fps": (0, 1000, "frames/s"),
    "[render].every": (1, 10**7, "frames"),
    # physical values: an absurd magnitude is named here, not met as a divergence
    "dt": (1e-7, 10.0, "s"), "[params].dt": (1e-7, 10.0, "s"), "[params].gravity": (-1e4, 1e4, "m/s² (about 1000 g)"),
    "[params].max_relative_speed": (0, 1e9, "m/s"), "[params].root_length": (0, _M, "m"),
    "[params].integrity_length": (0, _M, "m"),
    "[groom].length": (0, _M, "m"), "[groom].radius": (0, _M, "m"), "[groom].spread": (0, _M, "m"),
    "[groom].compare_offset": (-_M, _M, "m"), "[groom].min_length": (0, _M, "m"),
    "[groom].max_bind_distance": (0, _M, "m"), "[head].radius": (0, _M, "m"),
    "[hair_hair].collision_radius": (0, _M, "m"),
    "[wind].speed": (0, 1e3, "m/s"), "[wind].gust": (0, 1e3, "m/s"), "[wind].gust_frequency": (-1e4, 1e4, "Hz"),
    "[wind].noise_scale": (0, _M, "m"), "[wind].noise_frequency": (-1e4, 1e4, "Hz"),
    "[motion].amplitude": (-1e3, 1e3, "rad"), "[motion].frequency": (-1e4, 1e4, "Hz"),
    "[motion].rate": (-1e4, 1e4, "rad/s"), "[motion].radius": (0, 1e5, "m"), "[motion].peak_g": (0, 1e3, "g"),
    "[trim].point": (-_M, _M, "m"),
    **{f"[colliders[]].{k}": (-_M, _M, "m") for k in ("center", "a", "b", "point", "radius", "thickness",
                                                      "cut_height")},
}
_INDEX = re.compile(r"\[(\d+)\]")


def _range_key(key: str) -> str:
    """``[colliders[2]].radius`` → ``[colliders[]].radius``; ``[colliders[0].motion].rate`` →
    ``[motion].rate`` (a collider's motion has the head motion's bounds)."""
    key = _INDEX.sub("[]", key)
    return re.sub(r"^\[colliders\[\]\.motion\]", "[motion]", key)


def check_range(value, key: str, fail) -> None:
    """``fail(message)`` when a number (or a component of a list of numbers) checked under
    ``key`` is outside its :data:`RANGES` bound."""
    bound = RANGES.get(_range_key(key))
    if bound is None:
        return
    lo, hi, unit = bound
    values = value if isinstance(value, (list, tuple)) else [value]
    for v in values:
        if isinstance(v, (int, float)) and not isinstance(v, bool) and not lo <= v <= hi:
            fail(f"{key} = {v!r} is outside what this library runs: it must lie in [{lo:g}, {hi:g}] ({unit})")


# -- memory -------------------------------------------------------------------------------------
#: bytes per simulated particle in float32 (state, model, the step's temporaries, the groom's
#: growth; measured peak at 64k-256k particles: torch path 1.8 KB, native 0.6 KB)
PARTICLE_BYTES = 2048
#: bytes per hair–hair grid cell in float32 while it runs (measured 31 B to build)
GRID_CELL_BYTES = 64
#: bytes per SDF sample while it is built (point-cloud-utils' queries, float64; measured 284-309 B)
SDF_SAMPLE_BYTES = 320
#: bytes per point of a growing strand (float64 points and the step's temporaries)
GROWTH_POINT_BYTES = 96
#: bytes per substep per scene (the substeps' head poses)
SUBSTEP_BYTES = 1024


def _strands(scene: dict) -> int:
    g = scene.get("groom", {})
    s = max(1, int(round(g.get("strands", 1000) * float(scene.get("scale", 1.0)))))
    return 2 * s if g.get("compare_ms") else s


def estimate_memory(scene: dict, itemsize: int = 4, batch: int = 1) -> Dict[str, Tuple[int, str]]:
    """Bytes a validated scene needs, by part: ``{part: (bytes, what drives it)}``. ``itemsize``:
    4 (float32) or 8 (float64); ``batch``: scenes simulated together (a recipe's ``batch``)."""
    g = scene.get("groom", {})
    s, n = _strands(scene), int(g.get("particles") or 32)
    scale = itemsize / 4
    keys = "[groom].strands" + (" × scale" if float(scene.get("scale", 1.0)) != 1.0 else "") + " × [groom].particles"
    parts = {"particles": (int(batch * s * n * PARTICLE_BYTES * scale),
                           f"{batch * s * n:.3g} particles ({keys}" + (f" × batch {batch}" if batch > 1 else "") + ")")}
    stages = scene.get("stages", {})
    if stages.get("hair_hair"):
        r = int(scene.get("hair_hair", {}).get("resolution", 128))
        parts["hair_hair"] = (int(r ** 3 * GRID_CELL_BYTES * scale), f"the {r}³ hair–hair grid ([hair_hair].resolution)")
    head = scene.get("head", {})
    sdfs = []  # built one after the other: the largest one counts
    meshed = head.get("mesh") not in ("sphere", "none", None)
    if stages.get("collisions") and head.get("collide", True) and meshed:
        sdfs.append((int(head.get("sdf_resolution", 64)), "[head].sdf_resolution"))
    growth = g.get("growth", {}) if "preset" in g else None
    if growth is not None and growth.get("collide", True) and meshed:
        sdfs.append((int(growth.get("sdf_resolution", 128)), "[groom.growth].sdf_resolution"))
    if sdfs:
        r, key = max(sdfs)
        parts["sdf"] = (r ** 3 * SDF_SAMPLE_BYTES, f"the {r}³ SDF of the head ({key})")
    if growth is not None:
        length, step = growth.get("length"), float(growth.get("step", 0.005))
        k = int(growth["steps"]) if "steps" in growth else \
            math.ceil(float(length) / step) if isinstance(length, (int, float)) and not isinstance(length, bool) else n
        parts["growth"] = (s * (k + 1) * GROWTH_POINT_BYTES, f"{s:.3g} strands grown {k} steps ([groom.growth].steps, "
                                                           f"or length / step)")
    m = int(scene.get("substeps", scene.get("params", {}).get("substeps", 1)))
    parts["substeps"] = (batch * m * SUBSTEP_BYTES, f"{m} substeps (substeps)")
    return parts


def available_memory(device=None) -> Optional[int]:
    """Bytes of memory available now: the free memory of a CUDA ``device``, else the host's
    (``MemAvailable`` of /proc/meminfo, or the available physical pages); None when unknown."""
    if device is not None and str(device).startswith("cuda"):
        try:
            import torch

            return int(torch.cuda.mem_get_info(torch.device(device))[0])
        except (RuntimeError, AssertionError, ValueError):
            return None
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_AVPHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return None


_UNITS = {"": 1, "b": 1, "k": 2**10, "kb": 10**3, "kib": 2**10, "m": 2**20, "mb": 10**6, "mib": 2**20,
          "g": 2**30, "gb": 10**9, "gib": 2**30, "t": 2**40, "tb": 10**12, "tib": 2**40}


def parse_size(text: str, what: str = "--max-memory") -> int:
    """Bytes from ``"8G"``, ``"512MiB"``, ``"1.5GB"``, ``"2e9"``; ValueError naming ``what``."""
    m = re.fullmatch(r"\s*([0-9.eE+]+)\s*([A-Za-z]*)\s*", str(text))
    try:
        value = float(m.group(1)) * _UNITS[m.group(2).lower()]
    except (AttributeError, KeyError, ValueError):
        raise ValueError(f"{what} must be a size such as 8G, 512M or 2e9 (bytes); got {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"{what} must be a positive size; got {text!r}")
    return int(value)


def format_size(n: float) -> str:
    for unit, size in (("TiB", 2**40), ("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if n >= size:
            return f"{n / size:.1f} {unit}"
    return f"{int(n)} B"


class MemoryLimitError(ValueError):
    """A scene needs more memory than is available (or than ``--max-memory``)."""


def check_memory(scene: dict, itemsize: int = 4, batch: int = 1, device=None, limit: Optional[int] = None,
                 where: str = "scene") -> int:
    """Raise :class:`MemoryLimitError` when :func:`estimate_memory` exceeds ``limit`` bytes (default:
    :func:`available_memory` of ``device``), naming the estimate, the largest part and its keys.
    Returns the estimate (bytes)."""
    parts = estimate_memory(scene, itemsize, batch)
    total = sum(b for b, _ in parts.values())
    have = limit if limit is not None else available_memory(device)
    if have is not None and total > have:
        name, (big, what) = max(parts.items(), key=lambda kv: kv[1][0])
        source = "--max-memory" if limit is not None else f"available on {'this machine' if device is None or not str(device).startswith('cuda') else device}"
        raise MemoryLimitError(f"{where}: the run needs about {format_size(total)} of memory, more than the "
                               f"{format_size(have)} {source}; the largest part is {what}: {format_size(big)}. "
                               f"Lower it (or set --max-memory if you know the estimate is too high)")
    return total
