"""Test helpers of the learned baselines: benchmark items from today's ``HairSequenceDataset``.

:class:`DenseGuides` yields the items ``HairSequenceDataset(..., guides=G)`` yields (see
``baselines/protocol.py``), with the dense run's own copies of the guides as the guide input:
``positions`` (W, S, N, 3), ``guide_positions`` (W, G, N, 3) = ``positions[:, guide_indices[:G]]``,
``guide_index`` (G,), ``rest_positions`` (S, N, 3), ``num_pinned`` (S,), ``rotations``,
``translations``, the collider poses when stored, ``sequence`` and ``start``.
:func:`toy_dataset` generates a tiny dataset with ``ams-torch generate``.
"""
from __future__ import annotations

import json
from pathlib import Path

import torch

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


class DenseGuides(HairSequenceDataset):
    """A ``HairSequenceDataset`` whose items are the benchmark's items with ``G`` guides (the dense
    run's copies). Extra keyword arguments go to ``HairSequenceDataset``."""

    def __init__(self, root, guides: int, **kwargs):
        kwargs.setdefault("fields", None)
        super().__init__(root, **kwargs)
        have = set(self.fields)
        if "positions" not in have:
            raise ValueError("DenseGuides needs the dense positions")
        g0 = self._file(self.sequences[0][0])[self.sequences[0][1]]
        for k in ("collider_rotations", "collider_translations"):
            if k in g0 and k not in have:
                self.fields.append(k)
        self.fields = [k for k in self.fields if k != "guide_positions"]
        self.guides = int(guides)
        self._static = {}

    def static(self, index: int) -> dict:
        """rest_positions, guide_index and num_pinned of sequence ``index`` (cached)."""
        if index not in self._static:
            from ams_torch.apps.scene.schema import make_params
            from ams_torch.sim.model import pinned_counts

            arr = self.sequence_arrays(index)
            order = torch.from_numpy(arr["guide_indices"]).long()
            if self.guides > order.numel():
                raise ValueError(f"the dataset stores {order.numel()} guides; asked for {self.guides}")
            rest = torch.from_numpy(arr["rest_positions"]).to(self.dtype)
            fi, name = self._slot(index)
            scene = json.loads(self._file(fi)[name].attrs["scene"])
            self._static[index] = {"rest_positions": rest, "guide_index": order[:self.guides],
                                   "num_pinned": pinned_counts(make_params(scene), rest.double())}
        return self._static[index]

    def __getitem__(self, i):
        item = super().__getitem__(i)
        st = self.static(item["sequence"])
        item.update({k: v.clone() for k, v in st.items()})
        item["guide_positions"] = item["positions"][:, st["guide_index"]].clone()
        return item
