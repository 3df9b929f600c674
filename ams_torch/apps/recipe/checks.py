"""Validating a recipe: its tables (top level, [store], [split]) and the scene of every value each
sampler can produce."""
from __future__ import annotations

from typing import TYPE_CHECKING, Optional

import numpy as np

from ams_torch.apps.recipe.samplers import (RecipeError, _fail, check_samplers, first, has_sampler, is_sampler,
                                            key_name, options, put, sites)
from ams_torch.apps.scene.checks import (ABSENT, boolean, check_table, integer, is_number, list_of, number, one_of,
                                         string)

if TYPE_CHECKING:
    from ams_torch.apps.recipe.core import Recipe

__all__ = ["STORE", "STORE_DEFAULTS", "SPLIT", "SPLITS", "SPLIT_DEFAULTS", "HOLD_OUT", "TOP", "check_top",
           "check_sampler_values", "motion_types", "motion_common", "guide_counts", "sampled_scenes",
           "check_recipe_memory"]

SPLITS = ("train", "valid", "test")
SPLIT_DEFAULTS = {"train": 0.8, "valid": 0.1, "test": 0.1}


def motion_types() -> set:
    from ams_torch.apps.motion import MOTIONS

    return set(MOTIONS) | {"random", "recorded"}


def motion_common(m: dict) -> dict:
    """Arguments of ``[motion]`` common to every type (all but ``type`` and the per-type tables)."""
    return {k: v for k, v in m.items() if k != "type" and k not in motion_types()}


def _any(v, key, ctx):
    return v


def _name(v, key, ctx):
    if not isinstance(v, str) or not v or any(c in v for c in "/\\"):
        ctx.fail(f"name must be a non-empty string without slashes; got {v!r}")
    return v


def _table(section: str, spec: dict):
    return lambda v, key, ctx: check_table(v, spec, section, ctx.where, ctx.base, RecipeError)


def _guides(v, key, ctx):
    """``[store].guides``: a count G >= 0 or a list of distinct counts >= 1 (e.g. [64, 256])."""
    one = integer(0, 2**31 - 1)
    if isinstance(v, list):
        if not v:
            ctx.fail(f"{key} must be an integer >= 0 or a non-empty list of integers >= 1; got []")
        counts = [integer(1, 2**31 - 1)(g, f"{key}[{i}]", ctx) for i, g in enumerate(v)]
        if len(set(counts)) != len(counts):
            ctx.fail(f"{key} lists a guide count twice: {v!r}")
        return counts
    return one(v, key, ctx)


def guide_counts(store: dict) -> list:
    """The guide counts of a ``[store]`` table, sorted (``guides = 16`` -> [16]; 0 -> [])."""
    g = store.get("guides", 0)
    return sorted(int(x) for x in g) if isinstance(g, list) else ([int(g)] if g else [])


STORE = {"positions": (boolean, True), "velocities": (boolean, False), "guides": (_guides, 0),
         "poses": (boolean, True), "precision": (one_of("float32", "float16"), "float32"),
         "compression": (one_of("gzip", "lzf", "none"), "gzip"), "compression_level": (integer(0, 9), 4),
         "guides_alone": (boolean, True), "motion_velocities": (boolean, False)}
STORE_DEFAULTS = {k: default for k, (_, default) in STORE.items()}
HOLD_OUT = {"motion": (list_of(string), ABSENT), "collider": (list_of(string), ABSENT),
            "groom_seed": (list_of(integer(0)), ABSENT), "preset": (list_of(string), ABSENT)}
SPLIT = {**{k: (number(0, 1), ABSENT) for k in SPLITS}, "by": (one_of("group", "groom"), ABSENT),
         "hold_out": (_table("split.hold_out", HOLD_OUT), ABSENT)}
TOP = {"name": (_name, ABSENT), "description": (string, ABSENT), "sequences": (integer(1, 10**7), ABSENT),
       "frames": (integer(1, 10**6), ABSENT), "batch": (integer(1, 10**5), ABSENT),
       "dt": (number(0, open_lo=True), ABSENT), "substeps": (integer(1), ABSENT),
       "seed": (integer(0, 2**63 - 1), ABSENT), "dtype": (one_of("float32", "float64"), ABSENT),
       "store": (_table("store", STORE), ABSENT), "split": (_table("split", SPLIT), ABSENT),
       "single_groom": (boolean, ABSENT), "requires": (list_of(string), ABSENT),
       **{k: (_any, ABSENT) for k in ("head", "groom", "params", "stages", "hair_hair", "colliders",
                                      "motion", "wind")}}
_FIXED = ("head", "stages", "hair_hair", "dt", "substeps")


def check_top(raw: dict, where: str, base: str) -> None:
    """The top-level, [store] and [split] tables of a recipe, and where samplers may be."""
    for key in _FIXED:
        if key in raw and has_sampler(raw[key]):
            _fail(where, f"{key} is fixed for a whole dataset; samplers are allowed in [groom], [params], "
                         f"[[colliders]], [motion] and [wind]")
    check_table(raw, TOP, "top level", where, base, RecipeError)
    for key in ("sequences", "frames"):
        if key not in raw:
            _fail(where, f"{key} must be an integer >= 1; got nothing (the key is required)")
    for key in ("groom", "params", "motion", "wind"):
        if key in raw:
            if not isinstance(raw[key], dict) or is_sampler(raw[key]):
                _fail(where, f"[{key}] must be a table (samplers go inside it, one per value); got {raw[key]!r}")
            check_samplers(raw[key], where, f"[{key}]")
    if "colliders" in raw:
        if not (isinstance(raw["colliders"], list) or is_sampler(raw["colliders"])):
            _fail(where, f"[[colliders]] must be an array of tables (or a sampler of such arrays, drawn per batch "
                         f"group); got {raw['colliders']!r}")
        check_samplers(raw["colliders"], where, "[colliders]")
    for kind in motion_types() & set(raw.get("motion", {})):
        if not isinstance(raw["motion"][kind], dict) or is_sampler(raw["motion"][kind]):
            _fail(where, f"[motion.{kind}] must be a table of that motion's arguments (samplers go inside it); "
                         f"got {raw['motion'][kind]!r}")
    p = raw.get("wind", {}).get("probability", 1.0)
    if not (is_number(p) and 0 <= p <= 1):
        _fail(where, f"[wind].probability must be a number in [0, 1]; got {p!r}")
    st = {**STORE_DEFAULTS, **raw.get("store", {})}
    if not (st["positions"] or guide_counts(st)):
        _fail(where, "[store] keeps nothing: set positions = true or guides > 0")
    if "split" in raw:
        ratios = {k: float(raw["split"].get(k, 0.0)) for k in SPLITS}  # a share left out is 0
        total = sum(ratios.values())
        if abs(total - 1.0) > 1e-6:
            _fail(where, f"[split] shares must sum to 1; got {' + '.join(f'{k} {v:g}' for k, v in ratios.items())} "
                         f"= {total:g}")
        raw["split"] = {**ratios, **{k: raw["split"][k] for k in ("by", "hold_out") if k in raw["split"]}}


def variants(recipe: "Recipe") -> list:
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


def _base(recipe: "Recipe", cases: list) -> dict:
    """Every sampler at its first option: the draws the variants of :func:`variants` replace."""
    raw = recipe.raw
    kind0 = next((o["kind"] for _, _, o in cases if "kind" in o), "static")
    return {"g": first(raw.get("groom", {"kind": "sphere"})), "p": first(raw.get("params", {})),
            "w": first({k: v for k, v in raw["wind"].items() if k != "probability"}) if "wind" in raw else None,
            "kind": kind0, "margs": first({**motion_common(raw.get("motion", {})), **raw.get("motion", {}).get(kind0, {})}),
            "c": first(raw.get("colliders", []))}


def sampled_scenes(recipe: "Recipe") -> list:
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


def check_recipe_memory(recipe: "Recipe", device=None, limit: Optional[int] = None) -> int:
    """Refuse a recipe whose largest batch group (its sampler values' largest scene, ``batch``
    sequences simulated together) needs more memory than is available (or ``limit`` bytes):
    :func:`ams_torch.apps.scene.limits.check_memory` naming the estimate and its keys. Returns
    the largest estimate (bytes)."""
    from ams_torch.apps.scene.limits import check_memory, estimate_memory

    itemsize = 8 if recipe.dtype_name == "float64" else 4
    scenes = sampled_scenes(recipe)
    largest = max(scenes, key=lambda sc: sum(b for b, _ in estimate_memory(sc, itemsize, recipe.batch).values()))
    return check_memory(largest, itemsize, recipe.batch, device, limit, where=recipe.where)


def check_sampler_values(recipe: "Recipe") -> None:
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
