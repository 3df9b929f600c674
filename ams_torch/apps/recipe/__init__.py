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
    single_groom = true      # optional: the recipe is meant for one groom (checked: no samplers in
                             # [groom], and a preset groom has its seed; else an error at once)
    requires = ["../../shared/assets/x.tfx"]  # optional: paths that must exist (a suite skips the
                             # recipe with a message when one is absent)

    [head]      as in a scene (fixed for the whole dataset)
    [groom]     as in a scene; values may be samplers; drawn once per batch group. A preset
                groom without ``seed`` draws its seed per batch group (one groom per group);
                ``seed = 0`` fixes one groom for the whole dataset
    [groom.growth]           growth parameters (samplers allowed)
    [params]    Params fields (samplers allowed); drawn once per batch group
    [stages]    hair_hair, collisions, nonhookean (fixed)
    [hair_hair] HairHair fields (fixed)
    [[colliders]] as in a scene (with an optional [colliders.motion]); samplers allowed, drawn
                once per batch group, e.g. ``colliders = { cycle = [[{...sphere...}], [{...capsule...}]] }``
    [motion]    drawn per sequence: ``type`` (a name or a choice), arguments common to every
                type, and per-type argument tables ``[motion.shake]``, ``[motion.nod]``, ...
                Besides the scene motions there is ``random``: ``keys`` random key poses
                (rotation up to ``max_angle`` rad about a random axis, translation up to
                ``max_translation`` m per axis) over ``duration`` s (default: the sequence),
                starting at rest at the identity.
    [wind]      drawn per sequence: ``probability`` (share of sequences with wind, default 1)
                and Wind fields (samplers allowed; ``seed`` drawn when not given)
    [store]     positions = true, velocities = false (the simulator's state velocity),
                motion_velocities = false (the velocity the positions imply, (x_k − x_{k−1})/dt),
                guides = 0 (G, or a list [64, 256]: the farthest-point guide order of the
                largest count stored, with the dense run's copies), guides_alone = true (each
                guide count also simulated alone, stored as guides_alone_<G>), poses = true,
                precision = "float32" | "float16", compression = "gzip" | "lzf" | "none",
                compression_level = 4 (gzip)
    [split]     train = 0.8, valid = 0.1, test = 0.1: shares of the batch groups in each split
                (non-negative, summing to 1); by = "group" | "groom" (the unit of the shares);
                [split.hold_out] motion / collider / groom_seed / preset = [...]: test only.
                Whole units go to one split; the assignment is a permutation drawn from the
                recipe's seed (:mod:`ams_torch.apps.recipe.splits`).

A sampler is a one-key table: ``{ uniform = [lo, hi] }``, ``{ log_uniform = [lo, hi] }``,
``{ randint = [lo, hi] }`` (inclusive), ``{ choice = [a, b, ...] }`` (options are plain values,
not samplers), ``{ cycle = [a, b, ...] }`` (no random draw: option ``index mod n``, with index the
batch group's in [groom], [params], [[colliders]] and the sequence's in [motion], [wind]; cycles
of coprime lengths visit every combination). Vectors may hold samplers
(``direction = [1, 0, { uniform = [-0.5, 0.5] }]``).
Every value a sampler can produce is validated when the recipe is read: each choice option and
both ends of each range are put, one at a time, into a scene that is then validated, so a typo
in the third option fails at once (naming the key and the value), not after hours of generation.

Seeding. Sequence i's random draws come from ``SeedSequence([h, seed], spawn_key=(1, i))`` and
its group's from ``spawn_key=(0, g)`` with g = i // batch, where h is a hash of the recipe's
content (everything except ``name``, ``description``, ``sequences``, ``[store]``, ``[split]``,
``single_groom`` and ``requires``). So a
sequence depends on (recipe, index) alone: any shard on any machine draws the same sequence,
and raising ``sequences`` keeps the existing ones. ``Recipe.digest`` hashes the whole recipe
(sizes, storage and split included): files of one dataset must share it.

Usage::

    recipe = load_recipe("datasets/tiny.toml")
    recipe.sequence_spec(3)      # {"index": 3, "group": 1, "motion": {...}, "wind": {...} | None, ...}
    recipe.group_scene(1)        # a validated scene dict (see ams_torch.apps.scene.build)
"""
from ams_torch.apps.recipe.checks import SPLIT_DEFAULTS, SPLITS, STORE_DEFAULTS
from ams_torch.apps.recipe.core import Recipe, check_sampler_values, load_recipe, parse_recipe
from ams_torch.apps.recipe.samplers import SAMPLERS, MissingRequirement, RecipeError, is_sampler, sample

__all__ = ["RecipeError", "MissingRequirement", "Recipe", "load_recipe", "parse_recipe", "SAMPLERS", "STORE_DEFAULTS",
           "SPLITS", "SPLIT_DEFAULTS", "check_sampler_values", "is_sampler", "sample"]
