"""Test helpers of the learned baselines: :func:`toy_dataset` generates a tiny dataset with
``ams-torch generate``; :func:`DenseGuides` opens it as the benchmark's items (see
``baselines/protocol.py``) with the dense run's own copies of the guides as the guide input."""
from __future__ import annotations

from pathlib import Path


from ams_torch.apps.data import HairSequenceDataset

TOY = """
description = "toy dataset of the learned-baseline tests"
sequences = {sequences}
frames = {frames}
batch = {batch}
seed = {seed}

[head]
mesh = "sphere"
radius = 0.1

[groom]
kind = "sphere"
strands = {strands}
particles = {particles}
length = {length}
seed = {groom_seed}

[stages]
collisions = true
{colliders}
[motion]
type = {{ choice = ["shake", "nod", "random"] }}

[motion.shake]
amplitude = {{ uniform = [0.4, 0.9] }}
frequency = {{ uniform = [1.0, 2.0] }}

[motion.nod]
amplitude = {{ uniform = [0.3, 0.5] }}

[motion.random]
keys = 3

[store]
guides = {guides}

[split]
train = {train}
valid = {valid}
test = {test}
"""

SWEEP = """
[[colliders]]
type = "sphere"
center = [0.0, 0.0, 0.0]
radius = 0.04

[colliders.motion]
type = "keyframes"
times = [0.0, 0.4]
translations = [[-0.2, -0.12, 0.1], [0.2, -0.12, 0.1]]
"""


def toy_dataset(out, *, sequences=8, frames=16, batch=2, strands=48, particles=8, guides=12, length=0.15,
                seed=0, groom_seed=1, collider=False, split=(0.5, 0.25, 0.25)) -> str:
    """Generate a tiny sphere-head dataset into ``out`` (a folder) with ``ams-torch generate``;
    returns the folder."""
    from ams_torch.apps.datagen import generate
    from ams_torch.apps.recipe import load_recipe

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    text = TOY.format(sequences=sequences, frames=frames, batch=batch, seed=seed, strands=strands,
                      particles=particles, length=length, groom_seed=groom_seed, guides=guides,
                      colliders=SWEEP if collider else "", train=split[0], valid=split[1], test=split[2])
    recipe = out.parent / f"{out.name}.toml"
    recipe.write_text(text)
    generate(load_recipe(str(recipe)), str(out), progress=False, log=lambda s: None)
    return str(out)


def DenseGuides(root, guides: int, **kwargs) -> HairSequenceDataset:
    """The benchmark's items with ``G`` guides, the dense run's copies as the guide input
    (``HairSequenceDataset(root, guides=G, guide_source="dense")``). Extra keyword arguments go to
    ``HairSequenceDataset``."""
    return HairSequenceDataset(root, guides=int(guides), guide_source="dense", **kwargs)
