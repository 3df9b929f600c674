"""Inputs of the learned methods, built from a strand's neighbourhood, not from a per-groom table.

Everything is expressed in the head frame (a world point x is the row Rᵀ (x − T) for the head
rotation R and translation T), where the skinning of :class:`~baselines.skinning.LinearHairSkinning`
with an identity root frame equals the world skinning carried by the head. Lengths are divided by
a length ``scale`` (m) so that the inputs are of order one.

- :class:`GroomBinding`: one groom's binding to its guides (its K nearest guides by root,
  skinning weights, the per-strand static inputs, the pinned mask), built from
  ``rest_positions``, ``guide_index`` and ``num_pinned`` of any sample; :class:`BindingCache`
  keeps the bindings of the grooms seen last.
- :func:`collider_sdf`: signed distance and outward normal of points to every collider.
"""
from __future__ import annotations

from collections import OrderedDict
from typing import List, Sequence, Tuple

import torch
from torch import nn

from baselines.skinning import LinearHairSkinning

__all__ = ["to_head", "to_world", "world_up", "GroomBinding", "BindingCache", "collider_sdf", "pose_tensors",
           "sdf_inputs", "penetration_mm2"]


def to_head(x: torch.Tensor, rot: torch.Tensor, trans: torch.Tensor) -> torch.Tensor:
    """World points x (F, ..., 3) m, head rotation (F, 3, 3), translation (F, 3) m → head frame
    (F, ..., 3) m (rows Rᵀ (x − T))."""
    f = rot.shape[0]
    return ((x.reshape(f, -1, 3) - trans[:, None, :]) @ rot).reshape(x.shape)


def to_world(p: torch.Tensor, rot: torch.Tensor, trans: torch.Tensor) -> torch.Tensor:
    """Head-frame points p (F, ..., 3) m → world (F, ..., 3) m (rows R p + T)."""
    f = rot.shape[0]
    return (p.reshape(f, -1, 3) @ rot.transpose(-1, -2) + trans[:, None, :]).reshape(p.shape)


def world_up(rot: torch.Tensor) -> torch.Tensor:
    """The world +y axis in the head frame, Rᵀ e_y: (..., 3, 3) → (..., 3) (tells the model where
    gravity points)."""
    return rot[..., 1, :]


class GroomBinding(nn.Module):
    """A groom bound to its guides, with the per-strand inputs that do not change over time.

    Args:
        rest: (S, N, 3) m, the dense rest shape (head frame).
        guide_index: (G,) long, which strands are the guides.
        num_pinned: (S,) long, particles from the root that follow the head (no residual there).
        k: guides per strand (capped at G). scale: length scale, m.

    Per strand i with guides g_1..g_K (nearest roots) and weights w_k, the static inputs are
    ``(rest_i − rest_i,0)``, ``(rest g_k − rest_i)`` for every vertex, and ``w_k`` (lengths /
    scale): :attr:`static_dim` = 3N (K + 1) + K numbers; :meth:`inputs` adds the dynamic ones.
    """

    def __init__(self, rest: torch.Tensor, guide_index: torch.Tensor, num_pinned: torch.Tensor, k: int = 4,
                 scale: float = 0.05):
        super().__init__()
        rest = rest.detach()
        gi = guide_index.to(rest.device).long()
        self.skin = LinearHairSkinning(rest, rest[gi], k=k)
        s, n, _ = rest.shape
        self.k, self.n, self.s, self.scale = self.skin.guide_index.shape[1], n, s, float(scale)
        nbr = self.skin.guide_index  # (S, K) indices into the G guides
        rel = (rest - rest[:, :1]).reshape(s, -1) / scale
        grel = (self.skin.rest_guides[nbr] - rest[:, None]).reshape(s, -1) / scale
        self.register_buffer("static", torch.cat((rel, grel, self.skin.weights), 1))
        mask = (torch.arange(n, device=rest.device)[None, :] >= num_pinned.to(rest.device)[:, None]).to(rest.dtype)
        self.register_buffer("mask", mask[..., None])  # (S, N, 1): 0 on the pinned prefix

    @property
    def static_dim(self) -> int:
        return self.static.shape[1]

    @staticmethod
    def dynamic_dim(k: int, n: int) -> int:
        """Length of the dynamic inputs of :meth:`inputs` for K guides of N particles."""
        return 3 * n * (k + 1) + 3

    def skinned(self, guides_head: torch.Tensor, strands: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        """Skinning of ``strands`` (B,) from head-frame guides (F, G, N, 3): (their guides (F, B, K, N, 3),
        skinned strands (F, B, N, 3)), m, head frame."""
        f = guides_head.shape[0]
        b = strands.shape[0]
        gk = guides_head[:, self.skin.guide_index[strands]]  # (F, B, K, N, 3)
        eye = torch.eye(3, dtype=gk.dtype, device=gk.device).expand(f * b, 3, 3)
        flat = self.skin.gathered(gk.reshape(f * b, self.k, self.n, 3), strands.repeat(f), eye)
        return gk, flat.view(f, b, self.n, 3)

    def inputs(self, guides_head: torch.Tensor, up: torch.Tensor, strands: torch.Tensor):
        """Inputs of ``strands`` (B,) at F frames: guides (F, G, N, 3) m and the world up axis
        (F, 3) in the head frame. Returns (inputs (F, B, static_dim + dynamic_dim), skinned
        (F, B, N, 3) m head frame, neighbour guides (F, B, K, N, 3) m head frame).

        Dynamic inputs: each guide's displacement from its rest shape, the skinned strand's from
        its rest shape (lengths / scale), and the up axis."""
        gk, sk = self.skinned(guides_head, strands)
        f, b = sk.shape[:2]
        dg = (gk - self.skin.rest_guides[self.skin.guide_index[strands]]).reshape(f, b, -1) / self.scale
        ds = (sk - self.skin.rest_dense[strands]).reshape(f, b, -1) / self.scale
        feats = torch.cat((self.static[strands].expand(f, b, -1), dg, ds, up[:, None, :].expand(f, b, 3)), -1)
        return feats, sk, gk


def _binding_key(rest: torch.Tensor, guide_index: torch.Tensor, num_pinned: torch.Tensor) -> tuple:
    r = rest.detach().double()
    return (tuple(rest.shape), tuple(guide_index.tolist()), float(r.sum()), float(r.square().sum()),
            float((r * torch.arange(1, r.numel() + 1, dtype=r.dtype, device=r.device).view(r.shape)).sum()),
            int(num_pinned.sum()), str(rest.device))


class BindingCache:
    """The :class:`GroomBinding` of the last ``size`` grooms seen (keyed by rest shape, guides and
    pinned counts)."""

    def __init__(self, size: int = 8):
        self.size = size
        self._map: "OrderedDict[tuple, GroomBinding]" = OrderedDict()

    def get(self, rest, guide_index, num_pinned, k: int, scale: float) -> GroomBinding:
        key = _binding_key(rest, guide_index, num_pinned) + (k, scale)
        b = self._map.get(key)
        if b is None:
            b = GroomBinding(rest, guide_index, num_pinned, k=k, scale=scale)
            self._map[key] = b
            while len(self._map) > self.size:
                self._map.popitem(last=False)
        else:
            self._map.move_to_end(key)
        return b

    def clear(self) -> None:
        self._map.clear()


def pose_tensors(poses: Sequence, frames: int) -> List[Tuple[torch.Tensor, torch.Tensor]]:
    """(rotation (F, 3, 3), translation (F, 3)) of each collider pose (a Pose of batch (F,) or ())."""
    out = []
    for p in poses:
        r, t = p.rotation, p.translation
        out.append((r.expand(frames, 3, 3) if r.dim() == 2 else r, t.expand(frames, 3) if t.dim() == 1 else t))
    return out


def collider_sdf(points: torch.Tensor, colliders: Sequence, poses: Sequence[Tuple[torch.Tensor, torch.Tensor]]
                 ) -> Tuple[torch.Tensor, torch.Tensor]:
    """Signed distance (C, F, P) m (negative inside) and outward unit normal (C, F, P, 3) (world)
    of world points (F, P, 3) to each collider at its world pose (rotation (F, 3, 3), translation
    (F, 3) m). No colliders: shapes (0, F, P) and (0, F, P, 3)."""
    if len(colliders) == 0:
        return points.new_zeros((0,) + points.shape[:-1]), points.new_zeros((0,) + points.shape)
    ds, ns = [], []
    for col, (r, t) in zip(colliders, poses):
        local = (points - t[:, None, :].to(points)) @ r.to(points)
        d, n = col.distance_and_normal(local)
        ds.append(d)
        ns.append(n @ r.to(points).transpose(-1, -2))
    return torch.stack(ds), torch.stack(ns)


def sdf_inputs(points_world: torch.Tensor, rot: torch.Tensor, colliders: Sequence, poses, reach: float
               ) -> torch.Tensor:
    """Per-vertex collision inputs of strands (F, B, N, 3) m world: the nearest collider's signed
    distance clamped to ±``reach`` m and divided by it, and its outward normal in the head frame
    (zero farther than ``reach``): (F, B, 4N)."""
    f, b, n, _ = points_world.shape
    if len(colliders) == 0:
        z = points_world.new_zeros(f, b, n, 4)
        z[..., 0] = 1.0
        return z.reshape(f, b, 4 * n)
    d, nrm = collider_sdf(points_world.reshape(f, b * n, 3), colliders, poses)
    dmin, which = d.min(0)  # (F, B·N)
    nn_ = torch.gather(nrm, 0, which[None, ..., None].expand(1, f, b * n, 3))[0]
    near = (dmin < reach).to(nrm.dtype)[..., None]
    n_head = (nn_ @ rot) * near  # world → head axes (rows Rᵀ n)
    sd = (dmin / reach).clamp(-1.0, 1.0)[..., None]
    return torch.cat((sd, n_head), -1).reshape(f, b, 4 * n)


def penetration_mm2(points_world: torch.Tensor, colliders: Sequence, poses, mask: torch.Tensor) -> torch.Tensor:
    """Mean over the unmasked vertices of Σ_c max(0, −σ_c)² in mm² (the squared depth inside each
    collider) of strands (F, B, N, 3) m world; ``mask`` (B, N, 1) 1 where counted."""
    if len(colliders) == 0:
        return points_world.new_zeros(())
    f, b, n, _ = points_world.shape
    d, _ = collider_sdf(points_world.reshape(f, b * n, 3), colliders, poses)
    pen = (-d * 1000.0).clamp_min(0).square().sum(0).view(f, b, n)
    m = mask[..., 0].to(pen)
    return (pen * m).sum() / (m.sum() * f).clamp_min(1)
