"""The benchmark's built-in methods that learn nothing; importing this module registers them (and
the learned ones of :mod:`baselines.learned`) in :data:`baselines.protocol.BUILTINS`.

- ``rigid``: the rest shape carried by the head (what a groom does with no simulation at all).
- ``nearest``: each strand takes the shape of its nearest guide (by root distance), moved to its
  own root by the head's rotation.
- ``skinning``: linear hair skinning (:class:`~baselines.skinning.LinearHairSkinning`, K nearest
  guides, parallel-transported frames, the head rotation as root frame).
- ``blend``: the K nearest guides blended as skinning weights them, each carrying the strand's rest
  offset by the head rotation only (``nearest`` is K = 1).
- ``skinning+pushout``: skinning, then every free vertex inside the head or a collider is pushed
  out along the SDF normal (:func:`push_out`).

All are causal: ``step`` gives what ``predict`` gives for that frame.
"""
from __future__ import annotations

import hashlib
from abc import abstractmethod
from typing import List, Sequence

import torch

from baselines import learned  # noqa: F401  (registers the learned methods)
from baselines.protocol import Interpolator, register
from baselines.skinning import LinearHairSkinning

__all__ = ["Rigid", "Nearest", "Skinning", "Blend", "SkinningPushOut", "push_out"]


def _world(local: torch.Tensor, rotations: torch.Tensor, translations: torch.Tensor) -> torch.Tensor:
    """Head-frame points (S, N, 3) carried by poses (T, 3, 3), (T, 3) → (T, S, N, 3) m."""
    return torch.einsum("tij,snj->tsni", rotations, local) + translations[:, None, None, :]


def _fingerprint(*tensors: torch.Tensor) -> str:
    """A digest of the tensors' values, shapes, dtypes and device (to reuse a per-groom binding)."""
    h = hashlib.sha1()
    for t in tensors:
        h.update(f"{tuple(t.shape)}{t.dtype}{t.device}".encode())
        h.update(t.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


def _pinned_mask(num_pinned: torch.Tensor, n: int) -> torch.Tensor:
    """(S, N) bool: the particles that follow the head."""
    return torch.arange(n, device=num_pinned.device)[None, :] < num_pinned[:, None]


class _PerFrame(Interpolator):
    """A method whose frame t depends only on frame t's input: predict = step of every frame."""

    causal = True

    def _prepare(self, sample: dict) -> None:
        self._sample = sample

    @abstractmethod
    def _frames(self, guides: torch.Tensor, rotations: torch.Tensor, translations: torch.Tensor,
                collider_poses: Sequence) -> torch.Tensor:
        """(T, G, N, 3), (T, 3, 3), (T, 3), per-collider poses of batch (T,) → (T, S, N, 3) m."""

    def predict(self, sample: dict) -> torch.Tensor:
        self._prepare(sample)
        return self._frames(sample["guide_positions"], sample["rotations"], sample["translations"],
                            sample["collider_poses"])

    def reset(self, sample: dict) -> None:
        self._prepare(sample)

    def step(self, frame: dict) -> torch.Tensor:
        from ams_torch.geometry.pose import Pose

        poses = [Pose(p.rotation[None], p.translation[None], check=False) for p in frame["collider_poses"]]
        return self._frames(frame["guide_positions"][None], frame["rotation"][None], frame["translation"][None],
                            poses)[0]


class Rigid(_PerFrame):
    """The rest shape carried rigidly by the head: x(t) = R(t) X̄ + T(t)."""

    name = "rigid"

    def _frames(self, guides, rotations, translations, collider_poses):
        return _world(self._sample["rest_positions"].to(guides), rotations, translations)


class Nearest(_PerFrame):
    """Each strand copies its nearest guide's current shape, offset by the rest difference of
    their shapes carried by the head: x_i(t) = g_k(t) + R(t)(X̄_i − X̄_k), k the guide whose rest root
    is nearest."""

    name = "nearest"

    def _prepare(self, sample: dict) -> None:
        super()._prepare(sample)
        rest = sample["rest_positions"]
        rg = rest[sample["guide_index"]]
        self._nearest = torch.cdist(rest[:, 0].double(), rg[:, 0].double()).argmin(1)
        self._offset = rest - rg[self._nearest]  # (S, N, 3) head frame

    def _frames(self, guides, rotations, translations, collider_poses):
        off = torch.einsum("tij,snj->tsni", rotations, self._offset.to(guides))
        return guides[:, self._nearest] + off


class Skinning(_PerFrame):
    """Linear hair skinning from the K nearest guides (:class:`~baselines.skinning.LinearHairSkinning`,
    inverse-distance weights of power ``power``), the head rotation as every guide's root frame."""

    name = "skinning"

    def __init__(self, k: int = 4, power: float = 2.0):
        self.k, self.power = int(k), float(power)
        self._key = None

    def _prepare(self, sample: dict) -> None:
        super()._prepare(sample)
        rest, gi = sample["rest_positions"], sample["guide_index"]
        key = _fingerprint(rest, gi)
        if key != self._key:  # the same groom and guides: keep the binding
            self.skin = LinearHairSkinning(rest, rest[gi], k=self.k, power=self.power).to(rest.device)
            self._key = key

    def _frames(self, guides, rotations, translations, collider_poses):
        return self.skin(guides, root_rotation=rotations)


class Blend(_PerFrame):
    """The K nearest guides (by root distance, inverse-distance weights of power ``power``, as
    :class:`Skinning` binds them), each carrying the strand's rest offset from it by the head
    rotation only: x_i(t) = Σ_k w_k (g_k,i(t) + R(t)(X̄_i − X̄_k,i)). K = 1 is :class:`Nearest`.
    Unlike skinning, a guide's own bending does not rotate the offsets."""

    name = "blend"

    def __init__(self, k: int = 4, power: float = 2.0, chunk: int = 256):
        self.k, self.power, self.chunk = int(k), float(power), int(chunk)
        self._key = None

    def _prepare(self, sample: dict) -> None:
        super()._prepare(sample)
        rest, gi = sample["rest_positions"], sample["guide_index"]
        key = _fingerprint(rest, gi)
        if key != self._key:  # the same groom and guides: keep the binding
            skin = LinearHairSkinning(rest, rest[gi], k=self.k, power=self.power).to(rest.device)
            self._index, self._weights = skin.guide_index, skin.weights  # (S, K)
            self._offset = rest[:, None] - rest[gi][self._index]  # (S, K, N, 3) head frame
            self._key = key

    def _frames(self, guides, rotations, translations, collider_poses):
        out = []
        for lo in range(0, self._index.shape[0], self.chunk):
            idx = self._index[lo:lo + self.chunk]
            off = torch.einsum("tij,sknj->tskni", rotations, self._offset[lo:lo + self.chunk].to(guides))
            moved = guides[:, idx] + off  # (T, s, K, N, 3)
            out.append((self._weights[lo:lo + self.chunk].to(guides)[None, :, :, None, None] * moved).sum(2))
        return torch.cat(out, 1)


def push_out(x: torch.Tensor, colliders: List, poses: Sequence, free: torch.Tensor, passes: int = 4,
             skin: float = 0.0) -> torch.Tensor:
    """Move the free vertices that are inside a collider out along its normal.

    x: (T, S, N, 3) m world; colliders: ams_torch colliders (their own frames); poses: one world
    :class:`~ams_torch.Pose` of batch (T,) per collider; free: (S, N) bool, the vertices that may
    move; ``passes`` rounds over the colliders (grid normals are approximate); ``skin`` m: the
    distance outside the surface a pushed vertex ends at. A vertex with σ < −skin goes to
    x − (σ − skin) n (SPEC §8's push-out). Returns the new positions (T, S, N, 3).
    """
    t, s, n, _ = x.shape
    if tuple(free.shape) != (s, n):
        raise ValueError(f"push_out: free must be (S, N) = {(s, n)}; got {tuple(free.shape)}")
    free = free.to(x.device)
    for _ in range(passes if colliders else 0):
        for col, pose in zip(colliders, poses):
            r, tr = pose.rotation.to(x), pose.translation.to(x)
            local = torch.einsum("tji,tpj->tpi", r, x.reshape(t, s * n, 3) - tr[:, None, :])  # Rᵀ(x − T)
            sigma, normal = col.distance_and_normal(local.reshape(-1, 3))
            sigma, normal = sigma.reshape(t, s * n), normal.reshape(t, s * n, 3)
            depth = torch.where(free.reshape(1, s * n) & (sigma < skin), sigma - skin, torch.zeros_like(sigma))
            move = torch.einsum("tij,tpj->tpi", r, -depth[..., None] * normal)  # back to world axes
            x = x + move.reshape(t, s, n, 3)
    return x


class SkinningPushOut(Skinning):
    """Skinning, then the free vertices inside the head or a collider pushed out along the SDF
    normal (:func:`push_out`, ``passes`` rounds)."""

    name = "skinning+pushout"

    def __init__(self, k: int = 4, power: float = 2.0, passes: int = 4):
        super().__init__(k, power)
        self.passes = int(passes)

    def _frames(self, guides, rotations, translations, collider_poses):
        x = super()._frames(guides, rotations, translations, collider_poses)
        s = self._sample
        free = ~_pinned_mask(s["num_pinned"], x.shape[-2])
        return push_out(x, s["colliders"], collider_poses, free, self.passes)


register("rigid")(Rigid)
register("nearest")(Nearest)
register("skinning")(Skinning)
register("blend")(Blend)
register("skinning+pushout")(SkinningPushOut)
