"""A small simulated dataset for the baselines: generator and reader (HDF5).

:class:`HairDataset` reads two formats: the small files of :func:`generate_dataset` (below) and
the datasets of ``ams-torch generate`` (a folder or one shard file; docs/dataset_format.md):
their sequences must share one groom (a recipe whose ``[groom]`` has no samplers and a fixed
``seed``, or the sequences of one batch group), and the guide order is the stored
``guide_indices`` (``[store] guides = G``: the first k of them are the k-guide choice), else the
farthest-point order of the roots.

File layout of :func:`generate_dataset` (lengths in metres, float32; ``F`` frames, ``S`` strands,
``N`` particles):

- ``/rest`` (S, N, 3): rest shape in the head frame; ``/fps_order`` (S,): farthest-point order of
  the roots (the first G entries are the G-guide choice of :func:`baselines.select_guides`).
- ``/<sequence>/positions`` (F, S, N, 3) dense AMS positions (world), ``/<sequence>/rotation``
  (F, 3, 3) and ``/<sequence>/translation`` (F, 3) the head pose at the end of each frame,
  ``/<sequence>/collider_centre`` (F, 3) the centre of a swept sphere (attrs ``collider_radius``),
  when the sequence has one. Attributes of the file: ``dt`` (s), ``strands``, ``particles``.
"""
from __future__ import annotations

import os
from typing import Dict, List, Optional, Sequence

import h5py
import numpy as np
import torch

import ams_torch as at
from ams_torch.testing import shake_poses, sphere_groom

from .guides import fps_order

__all__ = ["random_motion", "sweep_poses", "simulate_sequence", "generate_dataset", "HairDataset",
           "is_generated"]


def random_motion(frames: int, dt: float, rng: np.random.Generator, scale: float = 1.0) -> List[at.Pose]:
    """A random head shake (random axis, amplitude 0.3–0.9 rad, 0.8–2 Hz, translation ≤ 5 cm)."""
    axis = rng.normal(size=3) + np.array([0.0, 1.5, 0.0])
    return shake_poses(frames, dt, amplitude=scale * float(rng.uniform(0.3, 0.9)),
                       frequency=float(rng.uniform(0.8, 2.0)), axis=tuple(axis / np.linalg.norm(axis)),
                       translation_amplitude=tuple(scale * rng.uniform(-0.05, 0.05, size=3)))


def sweep_poses(frames: int, dt: float, start, end) -> List[at.Pose]:
    """A collider frame moving at constant speed from ``start`` to ``end`` (metres) over the frames."""
    start, end = np.asarray(start, float), np.asarray(end, float)
    vel = (end - start) / (frames * dt)
    out = []
    for k in range(1, frames + 1):
        p = start + (end - start) * k / frames
        out.append(at.Pose(torch.eye(3), torch.tensor(p, dtype=torch.float32),
                           torch.tensor(vel, dtype=torch.float32), torch.zeros(3)))
    return out


def simulate_sequence(rest: torch.Tensor, head_poses: Sequence[at.Pose], colliders: Sequence = (),
                      collider_poses: Optional[Sequence[Sequence[at.Pose]]] = None,
                      params: Optional[at.Params] = None, dtype=torch.float32) -> torch.Tensor:
    """Dense AMS simulation of ``rest`` (S, N, 3) m. ``collider_poses[f]`` is the list of world
    poses of the colliders at frame f. Returns positions (F, S, N, 3) metres."""
    sim = at.Simulator(rest, params or at.Params(), dtype=dtype, colliders=list(colliders) or None)
    state = sim.initial_state()
    xs = []
    for f, pose in enumerate(head_poses):
        cp = None if not colliders else list(collider_poses[f])
        state = sim.step(state, pose, collider_poses=cp)
        xs.append(state.x)
    return torch.stack(xs)


def generate_dataset(path: str, strands: int = 256, particles: int = 12, sequences: int = 3,
                     frames: int = 30, seed: int = 0, sphere: bool = True,
                     params: Optional[at.Params] = None) -> str:
    """Simulate ``sequences`` random shakes of a ``sphere_groom`` (half of them with a sphere of
    radius 6 cm swept through the hair) and write them to ``path`` (atomically). Returns path."""
    params = params or at.Params()
    rng = np.random.default_rng(seed)
    rest = sphere_groom(strands, particles, seed=seed)
    tmp = f"{path}.tmp{os.getpid()}"
    with h5py.File(tmp, "w") as h:
        h.attrs.update(dt=params.dt, strands=strands, particles=particles)
        h["rest"] = rest.numpy()
        h["fps_order"] = fps_order(rest[:, 0], strands).numpy()
        for q in range(sequences):
            poses = random_motion(frames, params.dt, rng)
            cols, cposes, centres = [], None, None
            if sphere and q % 2 == 1:
                z = float(rng.uniform(-0.15, 0.15))
                y = float(rng.uniform(-0.15, -0.05))
                sweep = sweep_poses(frames, params.dt, (-0.45, y, z), (0.45, y, z))
                cols = [at.stages.SphereCollider(radius=0.06)]
                cposes = [[p] for p in sweep]
                centres = np.stack([p.translation.numpy() for p in sweep])
            x = simulate_sequence(rest, poses, cols, cposes, params)
            g = h.create_group(f"seq_{q:03d}")
            g["positions"] = x.numpy().astype(np.float32)
            g["rotation"] = torch.stack([p.rotation for p in poses]).numpy()
            g["translation"] = torch.stack([p.translation for p in poses]).numpy()
            if centres is not None:
                g["collider_centre"] = centres.astype(np.float32)
                g.attrs["collider_radius"] = 0.06
    os.replace(tmp, path)
    return path


def is_generated(path: str) -> bool:
    """Whether ``path`` is a dataset of ``ams-torch generate`` (a folder, or a file whose
    ``format`` attribute says so) rather than a file of :func:`generate_dataset`."""
    if os.path.isdir(path):
        return True
    if not os.path.isfile(path):
        raise FileNotFoundError(f"no such dataset {path!r}")
    try:
        with h5py.File(path, "r") as h:
            return h.attrs.get("format") == "ams_torch.dataset"
    except OSError as err:
        raise ValueError(f"{path}: cannot be opened as HDF5 (truncated or corrupt file): {err}") from None


def _sequence_index(name) -> int:
    text = str(name)
    digits = text[4:] if text.startswith("seq_") else text
    if not digits.isdigit():
        raise ValueError(f"sequence {name!r}: give an index (3) or a group name (seq_000003)")
    return int(digits)


def _load_generated(path: str, sequences, split) -> tuple:
    """(names, rest (S, N, 3), guide order, dt, per-sequence arrays) of an ``ams-torch generate`` dataset."""
    from ams_torch.apps.data import HairSequenceDataset

    keep = None if sequences is None else [_sequence_index(n) for n in sequences]
    fields = ["positions", "rotations", "translations"]
    ds = HairSequenceDataset(path, window=1, fields=fields, sequences=keep, split=split)
    indices = [idx for _, _, idx, _ in ds.sequences]
    arrays = {i: ds.sequence_arrays(i) for i in indices}
    rests = {}
    for i in indices:
        rests.setdefault(arrays[i]["rest_positions"].tobytes(), []).append(i)
    if len(rests) > 1:
        groups = sorted({arrays[i]["group"] for i in indices})
        raise ValueError(f"{path}: the sequences come from {len(rests)} different grooms (batch groups {groups}); the "
                         f"upsampler trains on one groom: pick the sequences of one batch group (--sequences), or "
                         f"use a recipe whose [groom] has no samplers and a fixed seed")
    first = arrays[indices[0]]
    rest = torch.from_numpy(np.asarray(first["rest_positions"], dtype=np.float32))
    order = torch.from_numpy(first["guide_indices"]).long() if "guide_indices" in first \
        else fps_order(rest[:, 0], rest.shape[0])
    data = []
    for i in indices:
        f = ds.sequence_frames(i)
        data.append({"positions": torch.from_numpy(f["positions"].astype(np.float32)),
                     "rotation": torch.from_numpy(f["rotations"]), "translation": torch.from_numpy(f["translations"])})
    ds.close()
    return [f"seq_{i:06d}" for i in indices], rest, order, float(first["dt"]), data


class HairDataset(torch.utils.data.Dataset):
    """Windows of ``window`` consecutive frames from the sequences of a dataset: a file of
    :func:`generate_dataset` or a dataset of ``ams-torch generate`` (see the module docstring).

    Loads the chosen sequences into memory. Item i is a dict with ``positions`` (W, S, N, 3) m,
    ``rotation`` (W, 3, 3), ``translation`` (W, 3) m, ``sequence`` (int) and ``start`` (frame).
    Windows start every ``stride`` frames; their order is fixed (sequence, then start).
    ``sequences``: names (``seq_000003``; for generated datasets also indices); ``split``
    (generated datasets): ``"train"``, ``"valid"`` or ``"test"``. ``fps_order``: the guide order
    (all S strands, or the G stored guides of a generated dataset).
    """

    def __init__(self, path: str, window: int = 1, stride: int = 1, sequences: Optional[Sequence[str]] = None,
                 split: Optional[str] = None):
        if is_generated(path):
            self.names, self.rest, self.fps_order, self.dt, self.data = _load_generated(path, sequences, split)
        else:
            if split is not None:
                raise ValueError(f"{path}: split={split!r} needs an `ams-torch generate` dataset (this file has no "
                                 f"splits)")
            with h5py.File(path, "r") as h:
                names = sorted(k for k in h.keys() if k.startswith("seq_"))
                self.names = [n for n in names if sequences is None or n in sequences]
                self.rest = torch.from_numpy(h["rest"][...])
                self.fps_order = torch.from_numpy(h["fps_order"][...]).long()
                self.dt = float(h.attrs["dt"])
                self.data: List[Dict[str, torch.Tensor]] = [
                    {k: torch.from_numpy(h[n][k][...]) for k in ("positions", "rotation", "translation")}
                    for n in self.names]
        if not self.names:
            raise ValueError(f"{path}: no sequences selected (sequences={sequences!r})")
        if window < 1 or stride < 1:
            raise ValueError("window and stride must be ≥ 1")
        self.window = window
        self.items = [(q, s) for q, d in enumerate(self.data)
                      for s in range(0, d["positions"].shape[0] - window + 1, stride)]

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, i: int) -> Dict[str, torch.Tensor]:
        q, s = self.items[i]
        d = self.data[q]
        w = slice(s, s + self.window)
        return {"positions": d["positions"][w], "rotation": d["rotation"][w],
                "translation": d["translation"][w], "sequence": q, "start": s}

    def frames(self):
        """All frames of the loaded sequences: positions (T, S, N, 3), rotation (T, 3, 3),
        translation (T, 3), concatenated in sequence order."""
        cat = lambda k: torch.cat([d[k] for d in self.data])  # noqa: E731
        return cat("positions"), cat("rotation"), cat("translation")
