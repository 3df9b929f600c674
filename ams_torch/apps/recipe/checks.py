"""Validating a recipe's tables (top level, [store], [split]); the scene of every value each
sampler can produce is checked by :func:`ams_torch.apps.recipe.core.check_sampler_values`."""
from __future__ import annotations

from ams_torch.apps.recipe.samplers import RecipeError, _fail, check_samplers, has_sampler, is_sampler
from ams_torch.apps.scene.checks import (ABSENT, boolean, check_table, integer, is_number, list_of, number, one_of,
                                         string)

__all__ = ["STORE", "STORE_DEFAULTS", "SPLIT", "SPLITS", "SPLIT_DEFAULTS", "HOLD_OUT", "TOP", "check_top",
           "motion_types", "motion_common", "guide_counts"]

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
