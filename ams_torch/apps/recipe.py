"""Dataset recipes: a TOML description of a simulation dataset, and the sequences drawn from it.

A recipe is a scene (:mod:`ams_torch.apps.scene`) whose values may be *samplers*, plus how many
sequences to simulate and what to store. Top level::

    name = "tiny"            # optional, default: file stem
    description = "..."      # optional
    sequences = 8            # Q, number of sequences
    frames = 30              # frames per sequence
    batch = 2                # sequences per groom, simulated together as one batch (default 1)
    seed = 0                 # base seed (default 0)
    dt = 0.0166667           # s, optional (else [params].dt)
    substeps = 1             # optional
    dtype = "float32"        # simulation precision ("float32" or "float64")

    [head]      as in a scene (fixed for the whole dataset)
    [groom]     as in a scene; values may be samplers; drawn once per batch group
    [groom.growth]           growth parameters (samplers allowed)
    [params]    Params fields (samplers allowed); drawn once per batch group
    [stages]    hair_hair, collisions, nonhookean (fixed)
    [hair_hair] HairHair fields (fixed)
    [[colliders]] as in a scene (fixed, with an optional [colliders.motion])
    [motion]    drawn per sequence: ``type`` (a name or a choice), arguments common to every
                type, and per-type argument tables ``[motion.shake]``, ``[motion.nod]``, ...
                Besides the scene motions there is ``random``: ``keys`` random key poses
                (rotation up to ``max_angle`` rad about a random axis, translation up to
                ``max_translation`` m per axis) over ``duration`` s (default: the sequence),
                starting at rest at the identity.
    [wind]      drawn per sequence: ``probability`` (share of sequences with wind, default 1)
                and Wind fields (samplers allowed; ``seed`` drawn when not given)
    [store]     positions = true, velocities = false, guides = 0 (G, farthest-point guide
                strands stored apart), poses = true, precision = "float32" | "float16",
                compression = "gzip" | "lzf" | "none", compression_level = 4 (gzip)
    [split]     train = 0.8, valid = 0.1, test = 0.1: shares of the batch groups in each split
                (non-negative, summing to 1). Whole batch groups go to one split, so no groom
                is in two splits; the assignment is a permutation drawn from the recipe's seed.

A sampler is a one-key table: ``{ uniform = [lo, hi] }``, ``{ log_uniform = [lo, hi] }``,
``{ randint = [lo, hi] }`` (inclusive), ``{ choice = [a, b, ...] }`` (options are plain values,
not samplers). Vectors may hold samplers (``direction = [1, 0, { uniform = [-0.5, 0.5] }]``).
Every value a sampler can produce is validated when the recipe is read: each choice option and
both ends of each range are put, one at a time, into a scene that is then validated, so a typo
in the third option fails at once (naming the key and the value), not after hours of generation.

Seeding. Sequence i's random draws come from ``SeedSequence([h, seed], spawn_key=(1, i))`` and
its group's from ``spawn_key=(0, g)`` with g = i // batch, where h is a hash of the recipe's
content (everything except ``name``, ``description``, ``sequences``, ``[store]`` and ``[split]``). So a
sequence depends on (recipe, index) alone: any shard on any machine draws the same sequence,
and raising ``sequences`` keeps the existing ones. ``Recipe.digest`` hashes the whole recipe
(sizes, storage and split included): files of one dataset must share it.

Usage::

    recipe = load_recipe("datasets/tiny.toml")
    recipe.sequence_spec(3)      # {"index": 3, "group": 1, "motion": {...}, "wind": {...} | None, ...}
    recipe.group_scene(1)        # a validated scene dict (see ams_torch.apps.scene.build)
"""
from __future__ import annotations

import copy
import hashlib
import json
import math
import os
from dataclasses import dataclass
from typing import Any, Dict, List, Optional

import numpy as np

from ams_torch.apps.scene import SceneError, parse_scene, read_toml
from ams_torch.apps.scene.schema import ABSENT, boolean, check_table, integer, is_number, number, one_of, string

__all__ = ["RecipeError", "Recipe", "load_recipe", "parse_recipe", "SAMPLERS", "STORE_DEFAULTS", "SPLITS",
           "SPLIT_DEFAULTS"]

SAMPLERS = ("uniform", "log_uniform", "randint", "choice")
_NOT_HASHED = ("name", "description", "sequences", "store", "split")
SPLITS = ("train", "valid", "test")
SPLIT_DEFAULTS = {"train": 0.8, "valid": 0.1, "test": 0.1}
_RANDOM_MOTION = {"keys": 4, "duration": None, "max_angle": 0.6, "max_translation": 0.05}
_GROUP, _SEQUENCE, _SPLIT = 0, 1, 2


class RecipeError(SceneError):
    """A recipe is invalid; the message names the file and the key."""


def _fail(where: str, msg: str):
    raise RecipeError(f"{where}: {msg}")


def is_sampler(v) -> bool:
    return isinstance(v, dict) and len(v) == 1 and next(iter(v)) in SAMPLERS


def _check_samplers(v, where: str, key: str) -> None:
    """Check every sampler inside v (tables, lists) is well formed."""
    if is_sampler(v):
        kind, arg = next(iter(v.items()))
        if kind == "choice":
            if not isinstance(arg, list) or not arg:
                _fail(where, f"{key}: choice needs a non-empty list; got {arg!r}")
            for j, a in enumerate(arg):
                if _has_sampler(a):
                    _fail(where, f"{key}: choice option {j + 1} holds a sampler; options are plain values")
            return
        if not (isinstance(arg, list) and len(arg) == 2 and all(is_number(a) for a in arg)):
            _fail(where, f"{key}: {kind} needs [low, high] numbers; got {arg!r}")
        lo, hi = arg
        if lo > hi:
            _fail(where, f"{key}: {kind} needs low <= high; got {arg!r}")
        if kind == "log_uniform" and lo <= 0:
            _fail(where, f"{key}: log_uniform needs positive bounds; got {arg!r}")
        if kind == "randint" and not all(isinstance(a, int) for a in arg):
            _fail(where, f"{key}: randint needs integer bounds; got {arg!r}")
        return
    if isinstance(v, dict):
        if any(k in SAMPLERS for k in v) and len(v) > 1:
            _fail(where, f"{key}: a sampler table has exactly one key (one of {list(SAMPLERS)}); got {sorted(v)}")
        for k, x in v.items():
            _check_samplers(x, where, f"{key}.{k}")
    elif isinstance(v, list):
        for j, x in enumerate(v):
            _check_samplers(x, where, f"{key}[{j}]")


def sample(v, rng: np.random.Generator):
    """Replace every sampler in v (recursively through tables and lists) by a draw from rng."""
    if is_sampler(v):
        kind, arg = next(iter(v.items()))
        if kind == "uniform":
            return float(rng.uniform(arg[0], arg[1]))
        if kind == "log_uniform":
            return float(math.exp(rng.uniform(math.log(arg[0]), math.log(arg[1]))))
        if kind == "randint":
            return int(rng.integers(arg[0], arg[1], endpoint=True))
        return copy.deepcopy(arg[int(rng.integers(len(arg)))])
    if isinstance(v, dict):
        return {k: sample(x, rng) for k, x in v.items()}
    if isinstance(v, list):
        return [sample(x, rng) for x in v]
    return v


def _canonical(d: Any) -> str:
    return json.dumps(d, sort_keys=True, separators=(",", ":"), default=str)


def _random_keyframes(args: dict, frames: int, dt: float, rng: np.random.Generator, where: str) -> dict:
    """The ``random`` motion: a concrete ``keyframes`` spec drawn from rng."""
    unknown = sorted(set(args) - set(_RANDOM_MOTION))
    if unknown:
        _fail(where, f"[motion] (random): unknown argument(s) {unknown}; allowed: {sorted(_RANDOM_MOTION)}")
    a = {**_RANDOM_MOTION, **args}
    keys = a["keys"]
    if isinstance(keys, bool) or not isinstance(keys, int) or not 1 <= keys <= 10_000:
        _fail(where, f"[motion] (random): keys must be an integer in [1, 10000]; got {keys!r}")
    if a["duration"] is not None and not (is_number(a["duration"]) and a["duration"] > 0):
        _fail(where, f"[motion] (random): duration must be a positive number (s); got {a['duration']!r}")
    for k in ("max_angle", "max_translation"):
        if not (is_number(a[k]) and a[k] >= 0):
            _fail(where, f"[motion] (random): {k} must be a finite number >= 0; got {a[k]!r}")
    duration = float(a["duration"]) if a["duration"] is not None else frames * dt
    times = np.linspace(0.0, duration, keys + 1)
    axes = rng.normal(size=(keys, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    rotvecs = np.concatenate([np.zeros((1, 3)), axes * rng.uniform(-1, 1, size=(keys, 1)) * float(a["max_angle"])])
    trans = np.concatenate([np.zeros((1, 3)), rng.uniform(-1, 1, size=(keys, 3)) * float(a["max_translation"])])
    return {"type": "keyframes", "times": times.tolist(), "rotvecs": rotvecs.tolist(), "translations": trans.tolist()}


@dataclass
class Recipe:
    """A validated recipe. ``raw`` is the recipe as written (paths as written); ``base`` the
    folder its relative paths are resolved against; ``hash`` the hex digest that seeds it."""

    raw: Dict[str, Any]
    where: str
    base: str
    hash: str

    # -- sizes -----------------------------------------------------------------------------
    @property
    def name(self) -> str:
        return self.raw["name"]

    @property
    def num_sequences(self) -> int:
        return int(self.raw["sequences"])

    @property
    def frames(self) -> int:
        return int(self.raw["frames"])

    @property
    def batch(self) -> int:
        return int(self.raw.get("batch", 1))

    @property
    def num_groups(self) -> int:
        """Batch groups: group g simulates sequences g·batch … (g+1)·batch − 1 together."""
        return -(-self.num_sequences // self.batch)

    @property
    def frame_dt(self) -> float:
        """Frame length (s): the top-level ``dt``, else a fixed ``[params].dt``, else the default."""
        if "dt" in self.raw:
            return float(self.raw["dt"])
        dt = self.raw.get("params", {}).get("dt")
        if isinstance(dt, (int, float)) and not isinstance(dt, bool):
            return float(dt)
        from ams_torch.sim.params import Params

        return Params().dt

    @property
    def store(self) -> Dict[str, Any]:
        return {**STORE_DEFAULTS, **self.raw.get("store", {})}

    @property
    def dtype_name(self) -> str:
        return self.raw.get("dtype", "float32")

    @property
    def digest(self) -> str:
        """SHA-256 (hex) of the whole recipe as validated (sizes, storage and split included):
        the identity of a dataset; every file of one dataset carries the same digest."""
        return hashlib.sha256(_canonical(self.raw).encode()).hexdigest()

    @property
    def split_ratios(self) -> Dict[str, float]:
        return {**SPLIT_DEFAULTS, **self.raw.get("split", {})}

    def group_splits(self) -> List[str]:
        """The split (``"train"``, ``"valid"`` or ``"test"``) of every batch group: a permutation of
        the groups drawn from the recipe's seed, cut into runs whose lengths are the ratios times
        the number of groups, rounded by largest remainder (so they sum to the group count)."""
        cached = self.__dict__.get("_group_splits")
        if cached is None:
            n = self.num_groups
            exact = [self.split_ratios[k] * n for k in SPLITS]
            counts = [int(math.floor(e)) for e in exact]
            by_rest = sorted(range(len(SPLITS)), key=lambda j: (-(exact[j] - counts[j]), j))
            for j in by_rest[:n - sum(counts)]:
                counts[j] += 1
            order = self.rng(_SPLIT, 0).permutation(n)
            cached = [""] * n
            pos = 0
            for name, c in zip(SPLITS, counts):
                for g in order[pos:pos + c]:
                    cached[int(g)] = name
                pos += c
            self.__dict__["_group_splits"] = cached
        return list(cached)

    def sequence_split(self, i: int) -> str:
        """The split of sequence i (that of its batch group)."""
        return self.group_splits()[i // self.batch]

    def group_sequences(self, g: int) -> List[int]:
        """Indices of the sequences of batch group g."""
        if not 0 <= g < self.num_groups:
            raise IndexError(f"group {g} out of range (recipe {self.name!r} has {self.num_groups} groups)")
        return list(range(g * self.batch, min((g + 1) * self.batch, self.num_sequences)))

    def shard_groups(self, shard: int, num_shards: int) -> List[int]:
        """Groups of shard ``shard`` of ``num_shards`` (round robin: g % num_shards == shard)."""
        if not (isinstance(num_shards, int) and num_shards >= 1 and 0 <= shard < num_shards):
            raise ValueError(f"shard must be i/n with 0 <= i < n; got {shard}/{num_shards}")
        return [g for g in range(self.num_groups) if g % num_shards == shard]

    # -- random draws ---------------------------------------------------------------------
    def _seed_sequence(self, kind: int, index: int) -> np.random.SeedSequence:
        entropy = [int(self.hash[:16], 16), int(self.raw.get("seed", 0))]
        return np.random.SeedSequence(entropy, spawn_key=(kind, index))

    def rng(self, kind: int, index: int) -> np.random.Generator:
        """The random stream of a batch group (kind 0) or a sequence (kind 1)."""
        return np.random.default_rng(self._seed_sequence(kind, index))

    def sequence_seed(self, i: int) -> int:
        """A 63-bit integer identifying sequence i's random stream (stored with the sequence)."""
        return int(self._seed_sequence(_SEQUENCE, i).generate_state(1, np.uint64)[0] >> np.uint64(1))

    def group_spec(self, g: int) -> Dict[str, Any]:
        """The draws of batch group g: concrete ``groom`` and ``params`` tables (JSON-friendly)."""
        rng = self.rng(_GROUP, g)
        groom = sample(self.raw.get("groom", {"kind": "sphere"}), rng)
        if "seed" not in groom and ("preset" in groom):
            groom["seed"] = int(rng.integers(0, 2**31 - 1))
        params = sample(self.raw.get("params", {}), rng)
        return {"group": g, "groom": groom, "params": params}

    def sequence_spec(self, i: int) -> Dict[str, Any]:
        """The draws of sequence i: concrete ``motion`` (a motion dict for
        :func:`ams_torch.make_motion`) and ``wind`` (Wind fields, or None)."""
        if not 0 <= i < self.num_sequences:
            raise IndexError(f"sequence {i} out of range (recipe {self.name!r} has {self.num_sequences})")
        rng = self.rng(_SEQUENCE, i)
        where = f"{self.where} (sequence {i})"
        motion = self._draw_motion(rng, where)
        wind = None
        w = self.raw.get("wind")
        if w is not None:
            p = float(w.get("probability", 1.0))
            on = bool(rng.uniform() < p)  # always drawn, so later draws do not depend on p
            drawn = sample({k: v for k, v in w.items() if k != "probability"}, rng)
            seed = int(rng.integers(0, 2**31 - 1))
            if on:
                drawn.setdefault("seed", seed)
                wind = drawn
        return {"index": i, "group": i // self.batch, "seed": self.sequence_seed(i), "motion": motion, "wind": wind}

    def _draw_motion(self, rng: np.random.Generator, where: str) -> dict:
        m = self.raw.get("motion")
        if m is None:
            return {"type": "static"}
        kind = sample(m.get("type", "static"), rng)
        if not isinstance(kind, str) or kind not in _motion_types():
            _fail(where, f"[motion].type must be one of {sorted(_motion_types())}; got {kind!r}")
        args = sample(_motion_common(m), rng)
        args.update(sample(m.get(kind, {}), rng))
        return self._concrete_motion(kind, args, rng, where)

    def _concrete_motion(self, kind: str, args: dict, rng: np.random.Generator, where: str) -> dict:
        if kind == "random":
            return _random_keyframes(args, self.frames, self.frame_dt, rng, where)
        if kind == "recorded" and isinstance(args.get("path"), str) and not os.path.isabs(args["path"]):
            args["path"] = os.path.join(self.base, args["path"])
        return {"type": kind, **args}

    def make_scene(self, groom: dict, params: dict, motion: dict, wind: Optional[dict], name: str, where: str) -> dict:
        """The validated scene of concrete ``groom``/``params``/``motion``/``wind`` tables with the
        recipe's fixed sections; a :class:`RecipeError` (naming the key) when it is invalid."""
        scene = {"name": name, "frames": self.frames, "groom": groom, "params": params, "motion": motion}
        for k in ("dt", "substeps", "head", "stages", "hair_hair", "colliders"):
            if k in self.raw:
                scene[k] = copy.deepcopy(self.raw[k])
        if wind is not None:
            scene["wind"] = wind
        try:
            scene = parse_scene(scene, where=where, base=self.base)
        except SceneError as err:
            raise RecipeError(str(err)) from None
        guides = self.store["guides"]
        strands = max(1, int(round(scene["groom"].get("strands", 1000) * float(scene["scale"]))))
        if guides > strands:
            _fail(where, f"[store].guides = {guides} exceeds the groom's {strands} strands")
        return scene

    def group_scene(self, g: int) -> dict:
        """The validated scene (see :func:`ams_torch.apps.scene.parse_scene`) that simulates batch group g;
        its ``motion`` is the group's first sequence's (the others differ only in motion and wind)."""
        spec = self.group_spec(g)
        first = self.sequence_spec(self.group_sequences(g)[0])
        return self.make_scene(spec["groom"], spec["params"], first["motion"], first["wind"], f"{self.name}/group{g}",
                               f"{self.where} (group {g})")

    def to_json(self) -> str:
        return _canonical(self.raw)


def load_recipe(path: str, overrides: Optional[dict] = None) -> Recipe:
    """Read and validate a recipe TOML file; ``overrides`` replace top-level keys
    (e.g. ``{"sequences": 2}``)."""
    raw = read_toml(path, "recipe", RecipeError, overrides)
    return parse_recipe(raw, where=path, base=os.path.dirname(os.path.abspath(path)))


def _motion_types() -> set:
    from ams_torch.apps.motion import MOTIONS

    return set(MOTIONS) | {"random", "recorded"}


def _motion_common(m: dict) -> dict:
    """Arguments of ``[motion]`` common to every type (all but ``type`` and the per-type tables)."""
    return {k: v for k, v in m.items() if k != "type" and k not in _motion_types()}


def _any(v, key, ctx):
    return v


def _name(v, key, ctx):
    if not isinstance(v, str) or not v or any(c in v for c in "/\\"):
        ctx.fail(f"name must be a non-empty string without slashes; got {v!r}")
    return v


def _table(section: str, spec: dict):
    return lambda v, key, ctx: check_table(v, spec, section, ctx.where, ctx.base, RecipeError)


STORE = {"positions": (boolean, True), "velocities": (boolean, False), "guides": (integer(0, 2**31 - 1), 0),
         "poses": (boolean, True), "precision": (one_of("float32", "float16"), "float32"),
         "compression": (one_of("gzip", "lzf", "none"), "gzip"), "compression_level": (integer(0, 9), 4)}
STORE_DEFAULTS = {k: default for k, (_, default) in STORE.items()}
SPLIT = {k: (number(0, 1), ABSENT) for k in SPLITS}
TOP = {"name": (_name, ABSENT), "description": (string, ABSENT), "sequences": (integer(1, 2**40), ABSENT),
       "frames": (integer(1, 2**31 - 1), ABSENT), "batch": (integer(1, 2**31 - 1), ABSENT),
       "seed": (integer(0, 2**63 - 1), ABSENT), "dtype": (one_of("float32", "float64"), ABSENT),
       "store": (_table("store", STORE), ABSENT), "split": (_table("split", SPLIT), ABSENT),
       **{k: (_any, ABSENT) for k in ("dt", "substeps", "head", "groom", "params", "stages", "hair_hair", "colliders",
                                      "motion", "wind")}}
_FIXED = ("head", "stages", "hair_hair", "dt", "substeps", "colliders")


def _check_top(raw: dict, where: str, base: str) -> None:
    check_table(raw, TOP, "top level", where, base, RecipeError)
    for key in ("sequences", "frames"):
        if key not in raw:
            _fail(where, f"{key} must be an integer >= 1; got nothing (the key is required)")
    for key in _FIXED:
        if key in raw and _has_sampler(raw[key]):
            _fail(where, f"{key} is fixed for a whole dataset; samplers are allowed in [groom], [params], "
                         f"[motion] and [wind]")
    for key in ("groom", "params", "motion", "wind"):
        if key in raw:
            if not isinstance(raw[key], dict):
                _fail(where, f"[{key}] must be a table; got {raw[key]!r}")
            _check_samplers(raw[key], where, f"[{key}]")
    for kind in _motion_types() & set(raw.get("motion", {})):
        if not isinstance(raw["motion"][kind], dict):
            _fail(where, f"[motion.{kind}] must be a table of that motion's arguments; got {raw['motion'][kind]!r}")
    p = raw.get("wind", {}).get("probability", 1.0)
    if not (is_number(p) and 0 <= p <= 1):
        _fail(where, f"[wind].probability must be a number in [0, 1]; got {p!r}")
    st = {**STORE_DEFAULTS, **raw.get("store", {})}
    if not (st["positions"] or st["guides"]):
        _fail(where, "[store] keeps nothing: set positions = true or guides > 0")
    if "split" in raw:
        raw["split"] = ratios = {k: float(raw["split"].get(k, 0.0)) for k in SPLITS}  # a share left out is 0
        total = sum(ratios.values())
        if abs(total - 1.0) > 1e-6:
            _fail(where, f"[split] shares must sum to 1; got {' + '.join(f'{k} {v:g}' for k, v in ratios.items())} "
                         f"= {total:g}")


def parse_recipe(raw: dict, where: str = "recipe", base: str = ".") -> Recipe:
    """Validate a recipe dict (as read from TOML). Raises :class:`RecipeError` naming the key.
    Checks the structure and the samplers, validates the scene made by every value each
    sampler can produce (:func:`check_sampler_values`), then draws group 0 and sequence 0 and
    validates what they make, so mistakes surface before any simulation."""
    if not isinstance(raw, dict):
        _fail(where, "a recipe must be a table")
    raw = copy.deepcopy(raw)
    raw.setdefault("name", "dataset")
    _check_top(raw, where, base)
    content = {k: v for k, v in raw.items() if k not in _NOT_HASHED}
    digest = hashlib.sha256(_canonical(content).encode()).hexdigest()
    recipe = Recipe(raw=raw, where=where, base=base, hash=digest)
    check_sampler_values(recipe)
    recipe.group_scene(0)
    from ams_torch.apps.motion import make_motion
    from ams_torch.stages.wind import Wind

    spec = recipe.sequence_spec(0)
    try:
        make_motion(spec["motion"])
        if spec["wind"] is not None:
            Wind(**spec["wind"])
    except (TypeError, ValueError, FileNotFoundError) as err:
        _fail(where, f"sequence 0: {err}")
    return recipe


def _has_sampler(v) -> bool:
    if is_sampler(v):
        return True
    if isinstance(v, dict):
        return any(_has_sampler(x) for x in v.values())
    if isinstance(v, list):
        return any(_has_sampler(x) for x in v)
    return False


# -- every value a sampler can produce -------------------------------------------------------
def _sites(v, path: tuple = ()):
    """(path, sampler) of every sampler inside v; a path is a tuple of keys and list indices."""
    if is_sampler(v):
        yield path, v
    elif isinstance(v, dict):
        for k, x in v.items():
            yield from _sites(x, path + (k,))
    elif isinstance(v, list):
        for j, x in enumerate(v):
            yield from _sites(x, path + (j,))


def _options(sampler: dict) -> List[tuple]:
    """(value, description) of each value a sampler can produce that decides validity: every
    choice option, both ends of a range (integers for randint)."""
    kind, arg = next(iter(sampler.items()))
    if kind == "choice":
        return [(a, f"choice option {j + 1} of {len(arg)}") for j, a in enumerate(arg)]
    conv = int if kind == "randint" else float
    return [(conv(arg[0]), f"{kind} low end"), (conv(arg[1]), f"{kind} high end")]


def _first(v):
    """v with every sampler replaced by its first option."""
    if is_sampler(v):
        return copy.deepcopy(_options(v)[0][0])
    if isinstance(v, dict):
        return {k: _first(x) for k, x in v.items()}
    if isinstance(v, list):
        return [_first(x) for x in v]
    return v


def _put(v, path: tuple, value):
    out = copy.deepcopy(v)
    node = out
    for p in path[:-1]:
        node = node[p]
    node[path[-1]] = copy.deepcopy(value)
    return out


def _key(section: str, path: tuple) -> str:
    return f"[{section}]" + "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in path)


def _variants(recipe: Recipe) -> list:
    """(site, label, overrides) for every value each sampler can produce; a site is one sampler
    (its first variant is its first option), overrides replace the base draw (``kind`` and
    ``margs`` the motion, ``g``/``p``/``w`` the groom/params/wind tables)."""
    raw = recipe.raw
    m = raw.get("motion", {"type": "static"})
    types = m.get("type", "static")
    kinds = _options(types) if is_sampler(types) else [(types, "")]
    kinds += [(k, f"[motion.{k}] table") for k in sorted(_motion_types() & set(m)) if k not in [x for x, _ in kinds]]
    out = []
    for kind, how in kinds:
        label = f"[motion].type = {kind!r}{f' ({how})' if how else ''}"
        if not isinstance(kind, str) or kind not in _motion_types():
            _fail(recipe.where, f"{label}: must be one of {sorted(_motion_types())}")
        args = {**_motion_common(m), **m.get(kind, {})}
        out.append(("type", label, {"kind": kind, "margs": _first(args)}))
        for path, smp in _sites(args):
            sec = "motion" if path[0] in _motion_common(m) else f"motion.{kind}"
            out += [((kind,) + path, f"{_key(sec, path)} = {v!r} ({d}, motion {kind})",
                     {"kind": kind, "margs": _first(_put(args, path, v))}) for v, d in _options(smp)]
    wind = {k: v for k, v in raw["wind"].items() if k != "probability"} if "wind" in raw else {}
    for section, table, arg in (("groom", raw.get("groom", {"kind": "sphere"}), "g"), ("params", raw.get("params", {}), "p"),
                                ("wind", wind, "w")):
        for path, smp in _sites(table):
            out += [((section,) + path, f"{_key(section, path)} = {v!r} ({d})", {arg: _first(_put(table, path, v))})
                    for v, d in _options(smp)]
    return out


def check_sampler_values(recipe: Recipe) -> None:
    """Validate the scene of every value each sampler of the recipe can produce, one sampler at
    a time, the others at their first option (first checked on its own: when that base is
    invalid, the sampler whose other option repairs it is named). Raises :class:`RecipeError`
    naming the key, the value and the problem: ``[groom].preset = 'mohak' (choice option 3 of 3): ...``."""
    raw, where, rng = recipe.raw, recipe.where, np.random.default_rng(0)
    variants = _variants(recipe)
    kind0 = next((o["kind"] for _, _, o in variants if "kind" in o), "static")
    base = {"g": _first(raw.get("groom", {"kind": "sphere"})), "p": _first(raw.get("params", {})),
            "w": _first({k: v for k, v in raw["wind"].items() if k != "probability"}) if "wind" in raw else None,
            "kind": kind0, "margs": _first({**_motion_common(raw.get("motion", {})), **raw.get("motion", {}).get(kind0, {})})}

    def problem(over: dict) -> Optional[str]:
        d = {**base, **over}
        try:
            motion = recipe._concrete_motion(d["kind"], d["margs"], rng, where)
            recipe.make_scene(d["g"], d["p"], motion, d["w"], f"{recipe.name}/check", where)
        except RecipeError as err:
            return str(err)[len(where) + 2:] if str(err).startswith(f"{where}: ") else str(err)
        return None

    first = {}
    for site, label, _ in variants:
        first.setdefault(site, label)
    err = problem({})
    if err is not None:
        culprit = next((first[site] for site, _, over in variants if problem(over) is None), None) or \
            next((label for label in first.values() if label.split(" = ")[0] in err), None)
        _fail(where, f"{culprit or 'with every sampler at its first option'}: {err}")
    for _, label, over in variants:
        err = problem(over)
        if err is not None:
            _fail(where, f"{label}: {err}")
