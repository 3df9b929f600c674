"""The :class:`Recipe`: sizes, seeding, draws of groups and sequences, splits, and the scene each
batch group simulates; reading and validating recipe files."""
from __future__ import annotations

import copy
import hashlib
import json
import os
from dataclasses import dataclass
from typing import Any, Dict, List, Optional

import numpy as np

from ams_torch.apps.recipe.checks import (SPLIT_DEFAULTS, SPLITS, STORE_DEFAULTS, check_top, guide_counts,
                                          motion_common, motion_types)
from ams_torch.apps.recipe.samplers import (MissingRequirement, RecipeError, _fail, first, has_sampler, is_sampler,
                                            key_name, options, put, sample, sites)
from ams_torch.apps.scene import SceneError, parse_scene, read_toml
from ams_torch.apps.scene.checks import is_number

__all__ = ["Recipe", "load_recipe", "parse_recipe", "check_sampler_values", "sampled_scenes", "check_recipe_memory",
           "variants"]

_NOT_HASHED = ("name", "description", "sequences", "store", "split", "single_groom", "requires")
_RANDOM_MOTION = {"keys": 4, "duration": None, "max_angle": 0.6, "max_translation": 0.05}
_GROUP, _SEQUENCE, _SPLIT = 0, 1, 2


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
    def guide_counts(self) -> List[int]:
        """The guide counts G of ``[store].guides``, sorted (``guides = [64, 256]`` -> [64, 256]); the
        stored guide order holds the largest; each count is also simulated alone when
        ``[store].guides_alone`` (the default)."""
        return guide_counts(self.store)

    @property
    def alone_counts(self) -> List[int]:
        """The guide counts simulated alone (none when ``[store].guides_alone = false``)."""
        return self.guide_counts if self.store["guides_alone"] else []

    @property
    def colliders_vary(self) -> bool:
        """Whether ``[[colliders]]`` holds samplers (each batch group draws its own colliders)."""
        return has_sampler(self.raw.get("colliders", []))

    @property
    def groom_varies(self) -> bool:
        """Whether the batch groups can have different grooms: ``[groom]`` holds samplers, or a
        preset groom without ``seed`` (each group then draws its own seed)."""
        groom = self.raw.get("groom", {"kind": "sphere"})
        return has_sampler(groom) or ("preset" in groom and "seed" not in groom)

    def groom_note(self) -> str:
        """One line saying how many grooms the batch groups grow, and why."""
        if not self.groom_varies:
            return f"grooms: one groom for all {self.num_groups} batch group(s)"
        why = ("[groom].seed is not set, so each batch group draws its own seed"
               if "seed" not in self.raw.get("groom", {}) and not has_sampler(self.raw.get("groom", {}))
               else "[groom] holds samplers, drawn per batch group")
        distinct = len({_canonical(self.group_spec(g)["groom"]) for g in range(self.num_groups)})
        return f"grooms: {distinct} different groom(s) in {self.num_groups} batch group(s) ({why})"

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
        """The shares ``{"train", "valid", "test"}`` of ``[split]``."""
        given = self.raw.get("split", {})
        return {k: float(given.get(k, SPLIT_DEFAULTS[k])) for k in SPLITS}

    @property
    def split_rules(self) -> Dict[str, Any]:
        """The whole ``[split]``: shares, ``by`` and ``hold_out`` (see :mod:`ams_torch.apps.recipe.splits`)."""
        given = self.raw.get("split", {})
        return {**self.split_ratios, "by": given.get("by", "group"), "hold_out": given.get("hold_out", {})}

    def _splits(self) -> tuple:
        cached = self.__dict__.get("_split_cache")
        if cached is None:
            from ams_torch.apps.recipe.splits import compute_splits

            cached = self.__dict__["_split_cache"] = compute_splits(self)
        return cached

    def group_splits(self) -> List[str]:
        """The split (``"train"``, ``"valid"`` or ``"test"``) of every batch group (before the
        motion hold-out): the group hold-outs go to test, the rest is a permutation of the units
        (groups, or grooms with ``[split].by = "groom"``) drawn from the recipe's seed, cut into runs
        whose lengths are the shares times the number of units, rounded by largest remainder."""
        return list(self._splits()[0])

    def sequence_split(self, i: int) -> str:
        """The split of sequence i (that of its batch group, or test when its motion is held out)."""
        return self._splits()[1][i]

    def sequence_holdout(self, i: int) -> List[str]:
        """Why sequence i is held out (``"motion"``, ``"collider"``, ``"groom_seed"``, ``"preset"``), or []."""
        return list(self._splits()[2][i])

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
        groom = sample(self.raw.get("groom", {"kind": "sphere"}), rng, g)
        if "seed" not in groom and ("preset" in groom):
            groom["seed"] = int(rng.integers(0, 2**31 - 1))
        params = sample(self.raw.get("params", {}), rng, g)
        out = {"group": g, "groom": groom, "params": params}
        if "colliders" in self.raw:  # drawn last: recipes without samplers there draw as before
            out["colliders"] = sample(self.raw["colliders"], rng, g)
        return out

    def sequence_spec(self, i: int) -> Dict[str, Any]:
        """The draws of sequence i: concrete ``motion`` (a motion dict for
        :func:`ams_torch.make_motion`) and ``wind`` (Wind fields, or None)."""
        if not 0 <= i < self.num_sequences:
            raise IndexError(f"sequence {i} out of range (recipe {self.name!r} has {self.num_sequences})")
        rng = self.rng(_SEQUENCE, i)
        where = f"{self.where} (sequence {i})"
        kind, motion = self._draw_motion(rng, where, i)
        wind = None
        w = self.raw.get("wind")
        if w is not None:
            p = float(w.get("probability", 1.0))
            on = bool(rng.uniform() < p)  # always drawn, so later draws do not depend on p
            drawn = sample({k: v for k, v in w.items() if k != "probability"}, rng, i)
            seed = int(rng.integers(0, 2**31 - 1))
            if on:
                drawn.setdefault("seed", seed)
                wind = drawn
        return {"index": i, "group": i // self.batch, "seed": self.sequence_seed(i), "motion": motion, "wind": wind,
                "motion_type": kind}

    def _draw_motion(self, rng: np.random.Generator, where: str, index: int = 0) -> tuple:
        """(the drawn motion type, e.g. "random", and the concrete motion dict) of sequence ``index``."""
        m = self.raw.get("motion")
        if m is None:
            return "static", {"type": "static"}
        kind = sample(m.get("type", "static"), rng, index)
        if not isinstance(kind, str) or kind not in motion_types():
            _fail(where, f"[motion].type must be one of {sorted(motion_types())}; got {kind!r}")
        args = sample(motion_common(m), rng, index)
        args.update(sample(m.get(kind, {}), rng, index))
        return kind, self._concrete_motion(kind, args, rng, where)

    def _concrete_motion(self, kind: str, args: dict, rng: np.random.Generator, where: str) -> dict:
        if kind == "random":
            return _random_keyframes(args, self.frames, self.frame_dt, rng, where)
        if kind == "recorded" and isinstance(args.get("path"), str) and not os.path.isabs(args["path"]):
            args["path"] = os.path.join(self.base, args["path"])
        return {"type": kind, **args}

    def make_scene(self, groom: dict, params: dict, motion: dict, wind: Optional[dict], name: str, where: str,
                   colliders: Optional[list] = None) -> dict:
        """The validated scene of concrete ``groom``/``params``/``motion``/``wind`` tables (and the
        drawn ``colliders``; default the recipe's, which must then hold no sampler) with the
        recipe's fixed sections; a :class:`RecipeError` (naming the key) when it is invalid."""
        scene = {"name": name, "frames": self.frames, "groom": groom, "params": params, "motion": motion}
        for k in ("dt", "substeps", "head", "stages", "hair_hair", "colliders"):
            if k in self.raw:
                scene[k] = copy.deepcopy(self.raw[k])
        if colliders is not None:
            scene["colliders"] = copy.deepcopy(colliders)
        if wind is not None:
            scene["wind"] = wind
        try:
            scene = parse_scene(scene, where=where, base=self.base)
        except SceneError as err:
            raise RecipeError(str(err)) from None
        guides = max(self.guide_counts, default=0)
        strands = max(1, int(round(scene["groom"].get("strands", 1000) * float(scene["scale"]))))
        if guides > strands and "file" not in scene["groom"]:
            _fail(where, f"[store].guides = {self.store['guides']} exceeds the groom's {strands} strands")
        if guides and scene["groom"]["compare_ms"]:
            _fail(where, "[store].guides with [groom].compare_ms: the doubled groom (AMS and mass-spring copies) has "
                         "no single guide order; store no guides or compare on separate runs")
        return scene

    def group_scene(self, g: int) -> dict:
        """The validated scene (see :func:`ams_torch.apps.scene.parse_scene`) that simulates batch group g;
        its ``motion`` is the group's first sequence's (the others differ only in motion and wind)."""
        spec = self.group_spec(g)
        first = self.sequence_spec(self.group_sequences(g)[0])
        return self.make_scene(spec["groom"], spec["params"], first["motion"], first["wind"], f"{self.name}/group{g}",
                               f"{self.where} (group {g})", colliders=spec.get("colliders"))

    def to_json(self) -> str:
        return _canonical(self.raw)


def load_recipe(path: str, overrides: Optional[dict] = None) -> Recipe:
    """Read and validate a recipe TOML file; ``overrides`` replace top-level keys
    (e.g. ``{"sequences": 2}``)."""
    raw = read_toml(path, "recipe", RecipeError, overrides)
    return parse_recipe(raw, where=path, base=os.path.dirname(os.path.abspath(path)))


def parse_recipe(raw: dict, where: str = "recipe", base: str = ".") -> Recipe:
    """Validate a recipe dict (as read from TOML). Raises :class:`RecipeError` naming the key.
    Checks the structure and the samplers, validates the scene made by every value each
    sampler can produce (:func:`check_sampler_values`), then draws group 0 and sequence 0 and
    validates what they make, so mistakes surface before any simulation."""
    if not isinstance(raw, dict):
        _fail(where, "a recipe must be a table")
    raw = copy.deepcopy(raw)
    raw.setdefault("name", "dataset")
    check_top(raw, where, base)
    for req in raw.get("requires", []):
        path = req if os.path.isabs(req) else os.path.join(base, req)
        if not os.path.exists(path):
            raise MissingRequirement(f"{where}: requires {req!r} ({os.path.normpath(path)}), which is absent (e.g. "
                                     f"the real assets of ../shared/assets); a suite skips this recipe")
    content = {k: v for k, v in raw.items() if k not in _NOT_HASHED}
    digest = hashlib.sha256(_canonical(content).encode()).hexdigest()
    recipe = Recipe(raw=raw, where=where, base=base, hash=digest)
    check_sampler_values(recipe)
    recipe.group_scene(0)
    if raw.get("single_groom") and recipe.groom_varies:
        groom = raw.get("groom", {})
        why = ("[groom] holds samplers" if has_sampler(groom) else
               "[groom].seed is not set, so each batch group draws its own seed")
        _fail(where, f"single_groom = true, but {why}: this recipe would grow up to {recipe.num_groups} different "
                     f"grooms (one per batch group); set [groom].seed = 0 (any integer) and remove the samplers from "
                     f"[groom]")
    if raw.get("split", {}).get("hold_out"):
        from ams_torch.apps.recipe.splits import check_hold_out

        check_hold_out(recipe)
        recipe._splits()  # the hold-outs must leave every split with a positive share some sequences
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


# -- the scene of every value each sampler can produce ---------------------------------------
def variants(recipe: Recipe) -> list:
    """(site, label, overrides) for every value each sampler can produce; a site is one sampler
    (its first variant is its first option), overrides replace the base draw (``kind`` and
    ``margs`` the motion, ``g``/``p``/``w`` the groom/params/wind tables)."""
    raw = recipe.raw
    m = raw.get("motion", {"type": "static"})
    types = m.get("type", "static")
    kinds = options(types) if is_sampler(types) else [(types, "")]
    kinds += [(k, f"[motion.{k}] table") for k in sorted(motion_types() & set(m)) if k not in [x for x, _ in kinds]]
    out = []
    for kind, how in kinds:
        label = f"[motion].type = {kind!r}{f' ({how})' if how else ''}"
        if not isinstance(kind, str) or kind not in motion_types():
            _fail(recipe.where, f"{label}: must be one of {sorted(motion_types())}")
        args = {**motion_common(m), **m.get(kind, {})}
        out.append(("type", label, {"kind": kind, "margs": first(args)}))
        for path, smp in sites(args):
            sec = "motion" if path[0] in motion_common(m) else f"motion.{kind}"
            out += [((kind,) + path, f"{key_name(sec, path)} = {v!r} ({d}, motion {kind})",
                     {"kind": kind, "margs": first(put(args, path, v))}) for v, d in options(smp)]
    wind = {k: v for k, v in raw["wind"].items() if k != "probability"} if "wind" in raw else {}
    for section, table, arg in (("groom", raw.get("groom", {"kind": "sphere"}), "g"),
                                ("params", raw.get("params", {}), "p"), ("wind", wind, "w"),
                                ("colliders", raw.get("colliders", []), "c")):
        for path, smp in sites(table):
            out += [((section,) + path, f"{key_name(section, path)} = {v!r} ({d})", {arg: first(put(table, path, v))})
                    for v, d in options(smp)]
    return out


def _base(recipe: Recipe, cases: list) -> dict:
    """Every sampler at its first option: the draws the variants of :func:`variants` replace."""
    raw = recipe.raw
    kind0 = next((o["kind"] for _, _, o in cases if "kind" in o), "static")
    return {"g": first(raw.get("groom", {"kind": "sphere"})), "p": first(raw.get("params", {})),
            "w": first({k: v for k, v in raw["wind"].items() if k != "probability"}) if "wind" in raw else None,
            "kind": kind0, "margs": first({**motion_common(raw.get("motion", {})), **raw.get("motion", {}).get(kind0, {})}),
            "c": first(raw.get("colliders", []))}


def sampled_scenes(recipe: Recipe) -> list:
    """The validated scene of every value each sampler can produce (one sampler at a time, the
    others at their first option, as :func:`check_sampler_values` checks them): e.g. to estimate
    the largest run of a recipe before generating it."""
    rng = np.random.default_rng(0)
    cases = variants(recipe)
    base = _base(recipe, cases)
    out = []
    for over in [{}] + [o for _, _, o in cases]:
        d = {**base, **over}
        motion = recipe._concrete_motion(d["kind"], d["margs"], rng, recipe.where)
        out.append(recipe.make_scene(d["g"], d["p"], motion, d["w"], f"{recipe.name}/check", recipe.where,
                                     colliders=d["c"]))
    return out


def check_recipe_memory(recipe: Recipe, device=None, limit: Optional[int] = None) -> int:
    """Refuse a recipe whose largest batch group (its sampler values' largest scene, ``batch``
    sequences simulated together) needs more memory than is available (or ``limit`` bytes):
    :func:`ams_torch.apps.scene.limits.check_memory` naming the estimate and its keys. Returns
    the largest estimate (bytes)."""
    from ams_torch.apps.scene.limits import check_memory, estimate_memory

    itemsize = 8 if recipe.dtype_name == "float64" else 4
    scenes = sampled_scenes(recipe)
    largest = max(scenes, key=lambda sc: sum(b for b, _ in estimate_memory(sc, itemsize, recipe.batch).values()))
    return check_memory(largest, itemsize, recipe.batch, device, limit, where=recipe.where)


def check_sampler_values(recipe: Recipe) -> None:
    """Validate the scene of every value each sampler of the recipe can produce, one sampler at
    a time, the others at their first option (first checked on its own: when that base is
    invalid, the sampler whose other option repairs it is named). Raises :class:`RecipeError`
    naming the key, the value and the problem: ``[groom].preset = 'mohak' (choice option 3 of 3): ...``."""
    where, rng = recipe.where, np.random.default_rng(0)
    cases = variants(recipe)
    base = _base(recipe, cases)

    def problem(over: dict) -> Optional[str]:
        d = {**base, **over}
        try:
            motion = recipe._concrete_motion(d["kind"], d["margs"], rng, where)
            recipe.make_scene(d["g"], d["p"], motion, d["w"], f"{recipe.name}/check", where, colliders=d["c"])
        except RecipeError as err:
            return str(err)[len(where) + 2:] if str(err).startswith(f"{where}: ") else str(err)
        return None

    first_label = {}
    for site, label, _ in cases:
        first_label.setdefault(site, label)
    err = problem({})
    if err is not None:
        culprit = next((first_label[site] for site, _, over in cases if problem(over) is None), None) or \
            next((label for label in first_label.values() if label.split(" = ")[0] in err), None)
        _fail(where, f"{culprit or 'with every sampler at its first option'}: {err}")
    for _, label, over in cases:
        err = problem(over)
        if err is not None:
            _fail(where, f"{label}: {err}")
