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

A sampler is a one-key table: ``{ uniform = [lo, hi] }``, ``{ log_uniform = [lo, hi] }``,
``{ randint = [lo, hi] }`` (inclusive), ``{ choice = [a, b, ...] }``. Vectors may hold samplers
(``direction = [1, 0, { uniform = [-0.5, 0.5] }]``).

Seeding. Sequence i's random draws come from ``SeedSequence([h, seed], spawn_key=(1, i))`` and
its group's from ``spawn_key=(0, g)`` with g = i // batch, where h is a hash of the recipe's
content (everything except ``name``, ``description``, ``sequences`` and ``[store]``). So a
sequence depends on (recipe, index) alone: any shard on any machine draws the same sequence,
and raising ``sequences`` keeps the existing ones.

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

__all__ = ["RecipeError", "Recipe", "load_recipe", "parse_recipe", "SAMPLERS", "STORE_DEFAULTS"]

SAMPLERS = ("uniform", "log_uniform", "randint", "choice")
_TOP = {"name", "description", "sequences", "frames", "batch", "seed", "dt", "substeps", "dtype", "head", "groom",
        "params", "stages", "hair_hair", "colliders", "motion", "wind", "store"}
_NOT_HASHED = ("name", "description", "sequences", "store")
STORE_DEFAULTS = {"positions": True, "velocities": False, "guides": 0, "poses": True, "precision": "float32",
                  "compression": "gzip", "compression_level": 4}
_RANDOM_MOTION = {"keys": 4, "duration": None, "max_angle": 0.6, "max_translation": 0.05}
_GROUP, _SEQUENCE = 0, 1


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
            return
        if not (isinstance(arg, list) and len(arg) == 2 and all(
                isinstance(a, (int, float)) and not isinstance(a, bool) and math.isfinite(a) for a in arg)):
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
    if isinstance(keys, bool) or not isinstance(keys, int) or keys < 1:
        _fail(where, f"[motion] (random): keys must be a positive integer; got {keys!r}")
    duration = float(a["duration"]) if a["duration"] is not None else frames * dt
    if not duration > 0:
        _fail(where, f"[motion] (random): duration must be positive (s); got {a['duration']!r}")
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
        from ams_torch.apps.motion import MOTIONS

        m = self.raw.get("motion")
        if m is None:
            return {"type": "static"}
        types = set(MOTIONS) | {"random", "recorded"}
        kind = sample(m.get("type", "static"), rng)
        if kind not in types:
            _fail(where, f"[motion].type must be one of {sorted(types)}; got {kind!r}")
        common = {k: v for k, v in m.items() if k != "type" and k not in types}
        args = sample(common, rng)
        args.update(sample(m.get(kind, {}), rng))
        if kind == "random":
            return _random_keyframes(args, self.frames, self.frame_dt, rng, where)
        if kind == "recorded" and "path" in args and not os.path.isabs(args["path"]):
            args["path"] = os.path.join(self.base, args["path"])
        return {"type": kind, **args}

    def group_scene(self, g: int) -> dict:
        """The validated scene (see :func:`ams_torch.apps.scene.parse_scene`) that simulates batch group g;
        its ``motion`` is the group's first sequence's (the others differ only in motion and wind)."""
        spec = self.group_spec(g)
        first = self.sequence_spec(self.group_sequences(g)[0])
        scene = {"name": f"{self.name}/group{g}", "frames": self.frames, "groom": spec["groom"],
                 "params": spec["params"], "motion": first["motion"]}
        for k in ("dt", "substeps", "head", "stages", "hair_hair", "colliders"):
            if k in self.raw:
                scene[k] = copy.deepcopy(self.raw[k])
        if first["wind"] is not None:
            scene["wind"] = first["wind"]
        try:
            return parse_scene(scene, where=f"{self.where} (group {g})", base=self.base)
        except SceneError as err:
            raise RecipeError(str(err)) from None

    def to_json(self) -> str:
        return _canonical(self.raw)


def load_recipe(path: str, overrides: Optional[dict] = None) -> Recipe:
    """Read and validate a recipe TOML file; ``overrides`` replace top-level keys
    (e.g. ``{"sequences": 2}``)."""
    raw = read_toml(path, "recipe", RecipeError, overrides)
    return parse_recipe(raw, where=path, base=os.path.dirname(os.path.abspath(path)))


def _int(raw: dict, key: str, where: str, default=None, minimum: int = 1) -> int:
    v = raw.get(key, default)
    if isinstance(v, bool) or not isinstance(v, int) or v < minimum:
        _fail(where, f"{key} must be an integer >= {minimum}; got {v!r}")
    return v


def parse_recipe(raw: dict, where: str = "recipe", base: str = ".") -> Recipe:
    """Validate a recipe dict (as read from TOML). Raises :class:`RecipeError` naming the key.
    Checks the structure and the samplers, then draws group 0 and sequence 0 and validates the
    scene they make, so most mistakes surface before any simulation."""
    raw = copy.deepcopy(raw)
    if not isinstance(raw, dict):
        _fail(where, "a recipe must be a table")
    unknown = sorted(set(raw) - _TOP)
    if unknown:
        _fail(where, f"unknown key(s) {unknown} at the top level; allowed: {sorted(_TOP)}")
    raw.setdefault("name", "dataset")
    if not isinstance(raw["name"], str) or not raw["name"] or any(c in raw["name"] for c in "/\\"):
        _fail(where, f"name must be a non-empty string without slashes; got {raw['name']!r}")
    _int(raw, "sequences", where)
    _int(raw, "frames", where)
    _int(raw, "batch", where, default=1)
    _int(raw, "seed", where, default=0, minimum=0)
    if raw.get("dtype", "float32") not in ("float32", "float64"):
        _fail(where, f"dtype must be 'float32' or 'float64'; got {raw.get('dtype')!r}")
    for key in ("head", "stages", "hair_hair", "dt", "substeps", "colliders", "frames", "batch", "seed",
                "sequences", "dtype"):
        if key in raw and _has_sampler(raw[key]):
            _fail(where, f"{key} is fixed for a whole dataset; samplers are allowed in [groom], [params], "
                         f"[motion] and [wind]")
    for key in ("groom", "params", "motion", "wind"):
        if key in raw:
            if not isinstance(raw[key], dict):
                _fail(where, f"[{key}] must be a table; got {raw[key]!r}")
            _check_samplers(raw[key], where, f"[{key}]")
    if "wind" in raw:
        p = raw["wind"].get("probability", 1.0)
        if isinstance(p, bool) or not isinstance(p, (int, float)) or not 0 <= p <= 1:
            _fail(where, f"[wind].probability must be a number in [0, 1]; got {p!r}")
    store = raw.get("store", {})
    if not isinstance(store, dict):
        _fail(where, "[store] must be a table")
    unknown = sorted(set(store) - set(STORE_DEFAULTS))
    if unknown:
        _fail(where, f"unknown key(s) {unknown} in [store]; allowed: {sorted(STORE_DEFAULTS)}")
    st = {**STORE_DEFAULTS, **store}
    for k in ("positions", "velocities", "poses"):
        if not isinstance(st[k], bool):
            _fail(where, f"[store].{k} must be true or false; got {st[k]!r}")
    if isinstance(st["guides"], bool) or not isinstance(st["guides"], int) or st["guides"] < 0:
        _fail(where, f"[store].guides must be an integer >= 0; got {st['guides']!r}")
    if st["precision"] not in ("float32", "float16"):
        _fail(where, f"[store].precision must be 'float32' or 'float16'; got {st['precision']!r}")
    if st["compression"] not in ("gzip", "lzf", "none"):
        _fail(where, f"[store].compression must be 'gzip', 'lzf' or 'none'; got {st['compression']!r}")
    lvl = st["compression_level"]
    if isinstance(lvl, bool) or not isinstance(lvl, int) or not 0 <= lvl <= 9:
        _fail(where, f"[store].compression_level must be an integer in [0, 9]; got {lvl!r}")
    if not (st["positions"] or st["guides"]):
        _fail(where, "[store] keeps nothing: set positions = true or guides > 0")
    content = {k: v for k, v in raw.items() if k not in _NOT_HASHED}
    digest = hashlib.sha256(_canonical(content).encode()).hexdigest()
    recipe = Recipe(raw=raw, where=where, base=base, hash=digest)
    scene = recipe.group_scene(0)
    from ams_torch.apps.motion import make_motion
    from ams_torch.stages.wind import Wind

    spec = recipe.sequence_spec(0)
    try:
        make_motion(spec["motion"])
        if spec["wind"] is not None:
            Wind(**spec["wind"])
    except (TypeError, ValueError, FileNotFoundError) as err:
        _fail(where, f"sequence 0: {err}")
    g = st["guides"]
    strands = max(1, int(round(scene["groom"].get("strands", 1000) * float(scene["scale"]))))
    if g > strands:
        _fail(where, f"[store].guides = {g} exceeds the groom's {strands} strands")
    return recipe


def _has_sampler(v) -> bool:
    if is_sampler(v):
        return True
    if isinstance(v, dict):
        return any(_has_sampler(x) for x in v.values())
    if isinstance(v, list):
        return any(_has_sampler(x) for x in v)
    return False
