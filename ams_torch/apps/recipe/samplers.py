"""Samplers in recipes: their syntax, drawing from them, and the values each can produce."""
from __future__ import annotations

import copy
import math
from typing import List

import numpy as np

from ams_torch.apps.scene import SceneError
from ams_torch.apps.scene.checks import is_number

__all__ = ["RecipeError", "MissingRequirement", "SAMPLERS", "is_sampler", "sample", "check_samplers", "has_sampler",
           "sites", "options",
           "first", "put", "key_name"]

SAMPLERS = ("uniform", "log_uniform", "randint", "choice", "cycle")
_LISTS = ("choice", "cycle")  # samplers over a list of plain options


class RecipeError(SceneError):
    """A recipe is invalid; the message names the file and the key."""


class MissingRequirement(RecipeError):
    """A recipe's ``requires`` path (e.g. a folder of real assets) is absent; a suite skips it."""


def _fail(where: str, msg: str):
    raise RecipeError(f"{where}: {msg}")


def is_sampler(v) -> bool:
    return isinstance(v, dict) and len(v) == 1 and next(iter(v)) in SAMPLERS


def check_samplers(v, where: str, key: str) -> None:
    """Check every sampler inside v (tables, lists) is well formed."""
    if is_sampler(v):
        kind, arg = next(iter(v.items()))
        if kind in _LISTS:
            if not isinstance(arg, list) or not arg:
                _fail(where, f"{key}: {kind} needs a non-empty list; got {arg!r}")
            for j, a in enumerate(arg):
                if has_sampler(a):
                    _fail(where, f"{key}: {kind} option {j + 1} holds a sampler; options are plain values")
            return
        if not (isinstance(arg, list) and len(arg) == 2 and all(is_number(a) for a in arg)):
            _fail(where, f"{key}: {kind} needs [low, high] numbers; got {arg!r}")
        lo, hi = arg
        if lo > hi:
            _fail(where, f"{key}: {kind} needs low <= high; got {arg!r}")
        if kind == "log_uniform" and lo <= 0:
            _fail(where, f"{key}: log_uniform needs positive bounds; got {arg!r}")
        if kind == "randint" and not all(isinstance(a, int) and -2**62 <= a < 2**62 for a in arg):
            _fail(where, f"{key}: randint needs integer bounds (within ±2^62); got {arg!r}")
        return
    if isinstance(v, dict):
        if any(k in SAMPLERS for k in v) and len(v) > 1:
            _fail(where, f"{key}: a sampler table has exactly one key (one of {list(SAMPLERS)}); got {sorted(v)}")
        for k, x in v.items():
            check_samplers(x, where, f"{key}.{k}")
    elif isinstance(v, list):
        for j, x in enumerate(v):
            check_samplers(x, where, f"{key}[{j}]")


def sample(v, rng: np.random.Generator, index: int = 0):
    """Replace every sampler in v (recursively through tables and lists) by a draw from rng;
    ``cycle`` takes option ``index mod n`` (index: the batch group's or the sequence's) and
    draws nothing."""
    if is_sampler(v):
        kind, arg = next(iter(v.items()))
        if kind == "cycle":
            return copy.deepcopy(arg[int(index) % len(arg)])
        if kind == "uniform":
            return float(rng.uniform(arg[0], arg[1]))
        if kind == "log_uniform":
            return float(math.exp(rng.uniform(math.log(arg[0]), math.log(arg[1]))))
        if kind == "randint":
            return int(rng.integers(arg[0], arg[1], endpoint=True))
        return copy.deepcopy(arg[int(rng.integers(len(arg)))])
    if isinstance(v, dict):
        return {k: sample(x, rng, index) for k, x in v.items()}
    if isinstance(v, list):
        return [sample(x, rng, index) for x in v]
    return v


def has_sampler(v) -> bool:
    if is_sampler(v):
        return True
    if isinstance(v, dict):
        return any(has_sampler(x) for x in v.values())
    if isinstance(v, list):
        return any(has_sampler(x) for x in v)
    return False


def sites(v, path: tuple = ()):
    """(path, sampler) of every sampler inside v; a path is a tuple of keys and list indices."""
    if is_sampler(v):
        yield path, v
    elif isinstance(v, dict):
        for k, x in v.items():
            yield from sites(x, path + (k,))
    elif isinstance(v, list):
        for j, x in enumerate(v):
            yield from sites(x, path + (j,))


def options(sampler: dict) -> List[tuple]:
    """(value, description) of each value a sampler can produce that decides validity: every
    choice option, both ends of a range (integers for randint)."""
    kind, arg = next(iter(sampler.items()))
    if kind in _LISTS:
        return [(a, f"{kind} option {j + 1} of {len(arg)}") for j, a in enumerate(arg)]
    conv = int if kind == "randint" else float
    return [(conv(arg[0]), f"{kind} low end"), (conv(arg[1]), f"{kind} high end")]


def first(v):
    """v with every sampler replaced by its first option."""
    if is_sampler(v):
        return copy.deepcopy(options(v)[0][0])
    if isinstance(v, dict):
        return {k: first(x) for k, x in v.items()}
    if isinstance(v, list):
        return [first(x) for x in v]
    return v


def put(v, path: tuple, value):
    if not path:  # the whole value is the sampler
        return copy.deepcopy(value)
    out = copy.deepcopy(v)
    node = out
    for p in path[:-1]:
        node = node[p]
    node[path[-1]] = copy.deepcopy(value)
    return out


def key_name(section: str, path: tuple) -> str:
    return f"[{section}]" + "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in path)
