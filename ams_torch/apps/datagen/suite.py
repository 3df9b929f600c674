"""Suites: a folder of recipes generated together, each into its own dataset folder.

``ams-torch generate FOLDER --out OUT`` generates every ``FOLDER/*.toml`` (sorted by file name)
into ``OUT/<recipe name>/``, one after the other, with the same options (``--shards``,
``--shard``, ``--backend``, ``--device``, ``--sequences``). A recipe whose ``requires`` paths are
absent (e.g. real assets in ``../shared/assets``) is skipped with a message; any other invalid
recipe fails before anything is simulated. Each dataset resumes as a single recipe does. Read a
suite back with :func:`ams_torch.apps.data.list_datasets` (its dataset folders).
"""
from __future__ import annotations

import glob
import os
from typing import Callable, Dict, List, Optional, Sequence, Tuple

from ams_torch.apps.recipe import MissingRequirement, Recipe, load_recipe

__all__ = ["suite_recipes", "generate_suite"]


def suite_recipes(folder: str, overrides: Optional[dict] = None) -> Tuple[List[Recipe], List[str]]:
    """The recipes of a suite folder (``*.toml``, sorted by file name), validated: (recipes,
    messages for the skipped ones). Two recipes of one name (one output folder) are refused."""
    paths = sorted(glob.glob(os.path.join(folder, "*.toml")))
    if not paths:
        raise FileNotFoundError(f"{folder}: no recipe (*.toml) in this folder")
    recipes, skipped = [], []
    for p in paths:
        try:
            recipes.append(load_recipe(p, overrides))
        except MissingRequirement as err:
            skipped.append(f"skipping {os.path.basename(p)}: {err}")
    names: Dict[str, str] = {}
    for r in recipes:
        if r.name in names:
            raise ValueError(f"{folder}: recipes {names[r.name]} and {r.where} have the same name {r.name!r} (one "
                             f"output folder each); rename one")
        names[r.name] = r.where
    return recipes, skipped


def generate_suite(folder: str, out: str, *, shards: Optional[Sequence[int]] = None, num_shards: int = 1,
                   device=None, backend: str = "local", sequences: Optional[int] = None, progress: bool = True,
                   log: Callable[[str], None] = print, wait: bool = False, ray_address: Optional[str] = None,
                   cpus_per_task: float = 1.0) -> Dict[str, List[str]]:
    """Generate every recipe of suite ``folder`` into ``out/<recipe name>``; returns ``{name: shard
    paths}``. ``shards``/``num_shards``/``device``/``wait`` as :func:`~ams_torch.apps.datagen.generate`
    (``backend="ray"``: :func:`~ams_torch.apps.datagen.generate_ray` with ``ray_address`` and
    ``cpus_per_task``); ``sequences`` overrides every recipe's sequence count."""
    from ams_torch.apps.datagen.ray_backend import generate_ray
    from ams_torch.apps.datagen.shards import generate

    recipes, skipped = suite_recipes(folder, {"sequences": sequences} if sequences is not None else None)
    for msg in skipped:
        log(msg)
    out_paths = {}
    for r in recipes:
        dest = os.path.join(out, r.name)
        log(f"recipe {r.name} ({os.path.basename(r.where)}): {r.num_sequences} sequences x {r.frames} frames in "
            f"{r.num_groups} batch group(s) of up to {r.batch}; output {dest}")
        if backend == "ray":
            out_paths[r.name] = generate_ray(r, dest, num_shards, address=ray_address, device=device,
                                             cpus_per_task=cpus_per_task, progress=progress, log=log, wait=wait)
        else:
            out_paths[r.name] = generate(r, dest, shards=shards, num_shards=num_shards, device=device,
                                         progress=progress, log=log, wait=wait)
    return out_paths
