"""The train / valid / test split of a recipe's sequences: shares of whole batch groups (or of
whole grooms) and hold-outs that go to test whatever the shares say.

``[split]`` keys (all optional)::

    train = 0.8            # shares of the units left after the hold-outs (non-negative, sum 1)
    valid = 0.1
    test = 0.1
    by = "group"           # the unit of the shares: "group" (a batch group, the default) or
                           # "groom" (every batch group of one groom together)
    [split.hold_out]       # test-only, whatever the shares say:
    motion = ["roller_coaster"]   # motion types ([motion].type, "random" included): per sequence
    collider = ["capsule"]        # collider types: every batch group that draws one
    groom_seed = [3, 4]           # groom seeds ([groom].seed): every batch group of that groom
    preset = ["ponytail"]         # groom presets: every batch group of that preset

Rules. The groom hold-outs (groom_seed, preset) send whole units to test: with
``by = "groom"`` every batch group of a held-out groom, so a groom is never in two splits. The
shares then split the remaining units: a permutation drawn from the recipe's seed
(``SeedSequence([h, seed], spawn_key=(2, 0))``) cut into runs of share × units, rounded by
largest remainder (so with no hold-outs and ``by = "group"`` the split is the one of format 2).
Last, the scene hold-outs move to test every batch group that draws a held-out collider and
every sequence whose motion type is held out, whatever split their unit has: these are about
unseen colliders and motions, so their grooms may be in train too. Each sequence records why it
is in test: its hold-out tags (``"motion"``, ``"collider"``, ``"groom_seed"``, ``"preset"``;
none for the shares). So the test sequences without the tags "motion" and "collider" show
grooms that no train sequence has, when the split is ``by = "groom"`` (or each batch group has
its own groom).

Every hold-out value must be one the recipe can draw, and the hold-outs must not empty a split
that the shares alone would give sequences, or reading the recipe fails naming the key.
"""
from __future__ import annotations

import json
import math
from typing import TYPE_CHECKING, Dict, List, Tuple

from ams_torch.apps.recipe.samplers import _fail, is_sampler

if TYPE_CHECKING:
    from ams_torch.apps.recipe.core import Recipe

__all__ = ["HOLD_OUT_KINDS", "compute_splits", "check_hold_out", "drawable_values", "collider_types", "describe"]

HOLD_OUT_KINDS = ("motion", "collider", "groom_seed", "preset")
_SPLITS = ("train", "valid", "test")


def drawable_values(v) -> list:
    """The values a plain value or a sampler can produce that are worth naming: a plain value,
    every choice option, or the integers of a randint (None for a continuous range)."""
    if not is_sampler(v):
        return [v]
    kind, arg = next(iter(v.items()))
    if kind in ("choice", "cycle"):
        return list(arg)
    if kind == "randint":
        return list(range(int(arg[0]), int(arg[1]) + 1)) if arg[1] - arg[0] <= 10**6 else None
    return None


def collider_types(v) -> set:
    """Every collider ``type`` that appears in a ``[[colliders]]`` value (plain or samplers)."""
    if isinstance(v, dict):
        found = {v["type"]} if isinstance(v.get("type"), str) else set()
        if isinstance(v.get("type"), dict):  # a sampler of the type
            found |= {t for t in (drawable_values(v["type"]) or []) if isinstance(t, str)}
        for k, x in v.items():
            if k != "type":
                found |= collider_types(x)
        return found
    if isinstance(v, list):
        return set().union(*(collider_types(x) for x in v)) if v else set()
    return set()


def check_hold_out(recipe: "Recipe") -> None:
    """Every held-out value is one the recipe can draw; raises RecipeError naming the key."""
    from ams_torch.apps.recipe.checks import motion_types

    rules = recipe.raw.get("split", {})
    hold = rules.get("hold_out", {})
    where = recipe.where
    groom = recipe.raw.get("groom", {"kind": "sphere"})
    m = recipe.raw.get("motion", {})
    can = {
        "motion": drawable_values(m.get("type", "static")) if isinstance(m, dict) else ["static"],
        "collider": sorted(collider_types(recipe.raw.get("colliders", []))),
        "preset": drawable_values(groom["preset"]) if "preset" in groom else [],
        "groom_seed": drawable_values(groom["seed"]) if "seed" in groom else None,
    }
    for kind, values in hold.items():
        key = f"[split.hold_out].{kind}"
        if kind == "motion":
            bad = [x for x in values if x not in motion_types()]
            if bad:
                _fail(where, f"{key}: {bad[0]!r} is not a motion type (known: {sorted(motion_types())})")
        if kind == "groom_seed" and can["groom_seed"] is None:
            _fail(where, f"{key}: the groom seed is drawn at random per batch group ([groom].seed is not set, or a "
                         f"continuous range), so no seed can be held out; draw it from a list: [groom].seed = "
                         f"{{ choice = [0, 1, 2, 3] }} or {{ randint = [0, 3] }}")
        if kind == "groom_seed" and rules.get("by", "group") != "groom":
            _fail(where, f"{key} holds out grooms: set [split].by = \"groom\" so the other grooms are split whole "
                         f"as well (a groom in two splits would not be held out)")
        missing = [x for x in values if x not in can[kind]]
        if missing:
            _fail(where, f"{key}: the recipe never draws {missing[0]!r} (it can draw {can[kind]}), so nothing would "
                         f"be held out")


def _group_tags(recipe: "Recipe", g: int, hold: dict) -> Tuple[List[str], List[str]]:
    """(groom hold-out tags, scene hold-out tags) of batch group g."""
    spec = recipe.group_spec(g)
    groom = spec["groom"]
    tags = []
    if groom.get("seed") in hold.get("groom_seed", ()):
        tags.append("groom_seed")
    if groom.get("preset") in hold.get("preset", ()):
        tags.append("preset")
    scene = ["collider"] if any(c.get("type") in hold.get("collider", ()) for c in spec.get("colliders", [])) else []
    return tags, scene


def _shares(ratios: dict, n: int) -> List[int]:
    """Units per split: share × n rounded by largest remainder (ties to the earlier split)."""
    exact = [ratios[k] * n for k in _SPLITS]
    counts = [int(math.floor(e)) for e in exact]
    for j in sorted(range(len(_SPLITS)), key=lambda j: (-(exact[j] - counts[j]), j))[:n - sum(counts)]:
        counts[j] += 1
    return counts


def _units(recipe: "Recipe", by: str) -> List[int]:
    """The split unit of every batch group: the group itself, or (``by = "groom"``) the first-seen
    index of its groom, so every group of one groom is in one unit."""
    if by != "groom":
        return list(range(recipe.num_groups))
    key_of = [json.dumps(recipe.group_spec(g)["groom"], sort_keys=True, default=str) for g in range(recipe.num_groups)]
    first: Dict[str, int] = {}
    for k in key_of:
        first.setdefault(k, len(first))
    return [first[k] for k in key_of]


def compute_splits(recipe: "Recipe") -> Tuple[List[str], List[str], List[List[str]]]:
    """(split of every batch group, split of every sequence, hold-out tags of every sequence)
    following the rules of the module docstring. A group's split is that of its unit (the shares
    and the groom hold-outs), before the scene hold-outs."""
    rules = recipe.raw.get("split", {})
    hold = rules.get("hold_out", {})
    ratios = recipe.split_ratios
    n_groups = recipe.num_groups
    unit_of = _units(recipe, rules.get("by", "group"))
    n_units = max(unit_of) + 1 if unit_of else 0
    tagged = any(k in hold for k in ("groom_seed", "preset", "collider"))
    group_tags = [_group_tags(recipe, g, hold) if tagged else ([], []) for g in range(n_groups)]
    unit_tags: List[set] = [set() for _ in range(n_units)]
    for g, u in enumerate(unit_of):
        unit_tags[u] |= set(group_tags[g][0])
    free = [u for u in range(n_units) if not unit_tags[u]]
    counts = _shares(ratios, len(free))
    order = recipe.rng(2, 0).permutation(len(free))  # kind 2: the split stream
    unit_split = ["test"] * n_units
    pos = 0
    for name, c in zip(_SPLITS, counts):
        for i in order[pos:pos + c]:
            unit_split[free[int(i)]] = name
        pos += c
    groups = [unit_split[unit_of[g]] for g in range(n_groups)]
    seq_split, seq_tags = [], []
    held_motion = set(hold.get("motion", ()))
    for i in range(recipe.num_sequences):
        g = i // recipe.batch
        tags = sorted(unit_tags[unit_of[g]] | set(group_tags[g][1]))
        if held_motion and recipe.sequence_spec(i)["motion_type"] in held_motion:
            tags = sorted(set(tags) | {"motion"})
        seq_split.append("test" if tags else groups[g])
        seq_tags.append(tags)
    if hold:  # a split the shares fill without the hold-outs must not be emptied by them
        for name, c, c_all in zip(_SPLITS, counts, _shares(ratios, n_units)):
            if c_all > 0 and name not in seq_split:
                by = rules.get("by", "group")
                _fail(recipe.where, f"[split]: no sequence goes to the {name} split: its share {ratios[name]:g} of "
                                    f"the {len(free)} {by} unit(s) left after the hold-outs (of {n_units}) rounds to "
                                    f"{c}, or the scene hold-outs took them; use more batch groups"
                                    f"{' or grooms' if by == 'groom' else ''}, hold out less, or set {name} = 0")
    return groups, seq_split, seq_tags


def describe(recipe: "Recipe") -> str:
    """One line: how many sequences each split has, and the hold-outs."""
    _, seq, tags = compute_splits(recipe)
    parts = [f"{k} {seq.count(k)}" for k in _SPLITS]
    held = {t for ts in tags for t in ts}
    return f"split: {', '.join(parts)} sequences" + (f" (held out: {', '.join(sorted(held))})" if held else "")
