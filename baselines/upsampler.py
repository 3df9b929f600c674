"""A small neural guide upsampler (SPEC §11): a residual MLP on top of linear hair skinning.

Each dense strand is predicted from its K guides and its rest shape, all expressed in the head
frame (so the network sees the same input for the same hair shape whatever the head pose):

    features = [ (guide_k − rest guide_k) for its K guides,  skinned − rest,  rest − rest root,
                 rest guide roots − rest root, skinning weights ]  (lengths divided by ``scale``)
    dense    = skinned + R · MLP(features) · scale     (residual zero on the pinned particles)

The last layer starts at zero, so an untrained upsampler is exactly the skinning baseline.
"""
from __future__ import annotations

from typing import Optional, Union

import torch
from torch import nn

from .skinning import LinearHairSkinning

__all__ = ["GuideUpsampler", "save_checkpoint", "load_checkpoint"]


class GuideUpsampler(nn.Module):
    """Dense strands from guides: skinning + a learned per-strand residual.

    Args:
        rest_dense: (S, N, 3) metres, dense rest shape (head frame).
        rest_guides: (G, N, 3) metres, guide rest shapes (same N).
        k: guides per strand. hidden, layers: MLP width and number of hidden layers.
        scale: length scale (m) dividing the inputs and multiplying the output.
        pinned: particles from the root that get no residual (they follow the head): one count
            for every strand, or (S,) long, one per strand.

    Call: ``up(guides (..., G, N, 3), rotation (..., 3, 3), translation (..., 3))`` →
    dense (..., S, N, 3) metres, world frame.
    """

    def __init__(self, rest_dense: torch.Tensor, rest_guides: torch.Tensor, k: int = 4, hidden: int = 192,
                 layers: int = 3, scale: float = 0.05, pinned: Union[int, torch.Tensor] = 2):
        super().__init__()
        self.skin = LinearHairSkinning(rest_dense, rest_guides, k=k)
        s, n, _ = self.skin.rest_dense.shape
        k = self.skin.guide_index.shape[1]
        if isinstance(pinned, torch.Tensor) and pinned.dim() > 0:
            if tuple(pinned.shape) != (s,):
                raise ValueError(f"pinned must be one count or (S,) = ({s},) counts; got {tuple(pinned.shape)}")
            pinned = pinned.detach().cpu().long()
        else:
            pinned = int(pinned)
        self.scale, self.pinned, self.k, self.n = float(scale), pinned, k, n
        rd = self.skin.rest_dense
        rel = (rd - rd[:, :1]).reshape(s, -1) / scale
        groots = (self.skin.rest_guides[self.skin.guide_index, 0] - rd[:, None, 0]).reshape(s, -1) / scale
        self.register_buffer("static_features", torch.cat((rel, groots, self.skin.weights), 1))
        dim = k * n * 3 + n * 3 + self.static_features.shape[1]
        mods, width = [], dim
        for _ in range(layers):
            mods += [nn.Linear(width, hidden), nn.SiLU()]
            width = hidden
        last = nn.Linear(width, n * 3)
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)
        self.mlp = nn.Sequential(*mods, last)
        if isinstance(pinned, int):
            mask = (torch.arange(n) >= pinned).to(rd.dtype)[:, None]  # (N, 1)
        else:
            mask = (torch.arange(n)[None, :] >= pinned[:, None]).to(rd.dtype)[..., None]  # (S, N, 1)
        self.register_buffer("residual_mask", mask.to(rd.device))

    def strands_forward(self, guides_k: torch.Tensor, strands: torch.Tensor, rotation: torch.Tensor,
                        translation: torch.Tensor, skinned: Optional[torch.Tensor] = None) -> torch.Tensor:
        """Predict a batch of strands from their own guides.

        guides_k: (B, K, N, 3) metres, positions of guides ``skin.guide_index[strands]``;
        strands: (B,) long; rotation (B, 3, 3), translation (B, 3) m: head pose of each item;
        skinned: (B, N, 3) the skinning result of these items when already computed.
        Returns (B, N, 3) metres.
        """
        r = rotation.to(guides_k)
        t = translation.to(guides_k)
        if skinned is None:
            skinned = self.skin.gathered(guides_k, strands, r)  # (B, N, 3)
        local_g = (guides_k - t[:, None, None, :]) @ r[:, None]  # rows Rᵀ(x − T)
        local_s = (skinned - t[:, None, :]) @ r
        rg = self.skin.rest_guides.to(guides_k)[self.skin.guide_index[strands]]
        dg = (local_g - rg).flatten(1) / self.scale
        ds = (local_s - self.skin.rest_dense.to(guides_k)[strands]).flatten(1) / self.scale
        feats = torch.cat((dg, ds, self.static_features.to(guides_k)[strands]), 1)
        mask = self.residual_mask if self.residual_mask.dim() == 2 else self.residual_mask[strands]
        res = self.mlp(feats).view(-1, self.n, 3) * self.scale * mask.to(guides_k)
        return skinned + res @ r.transpose(-1, -2)

    def forward(self, guides: torch.Tensor, rotation: torch.Tensor, translation: torch.Tensor) -> torch.Tensor:
        """guides (..., G, N, 3) m, rotation (..., 3, 3), translation (..., 3) m → (..., S, N, 3) m."""
        lead = guides.shape[:-3]
        g = guides.reshape((-1,) + guides.shape[-3:])
        f = g.shape[0]
        s = self.skin.guide_index.shape[0]
        gk = g[:, self.skin.guide_index].reshape(f * s, self.k, self.n, 3)
        strands = torch.arange(s, device=g.device).repeat(f)
        rot = rotation.reshape(-1, 3, 3).repeat_interleave(s, 0)
        tr = translation.reshape(-1, 3).repeat_interleave(s, 0)
        skinned = self.skin(g, rotation.reshape(-1, 3, 3)).reshape(f * s, self.n, 3)  # frames once per guide
        return self.strands_forward(gk, strands, rot, tr, skinned).reshape(lead + (s, self.n, 3))


def save_checkpoint(path: str, model: GuideUpsampler, optimizer: Optional[torch.optim.Optimizer] = None,
                    **extra) -> None:
    """Write model (with what is needed to rebuild it), optimizer state and ``extra`` to ``path``
    atomically (temporary file + rename)."""
    import os

    config = {"rest_dense": model.skin.rest_dense.cpu(), "rest_guides": model.skin.rest_guides.cpu(),
              "k": model.k, "hidden": model.mlp[0].out_features, "layers": len(model.mlp) // 2,
              "scale": model.scale, "pinned": model.pinned}
    blob = {"config": config, "model": model.state_dict(),
            "optimizer": optimizer.state_dict() if optimizer is not None else None, **extra}
    tmp = f"{path}.tmp{os.getpid()}"
    torch.save(blob, tmp)
    os.replace(tmp, path)


def load_checkpoint(path: str, map_location="cpu"):
    """(model, checkpoint dict) from a file written by :func:`save_checkpoint`."""
    blob = torch.load(path, map_location=map_location, weights_only=False)
    c = blob["config"]
    model = GuideUpsampler(c["rest_dense"], c["rest_guides"], k=c["k"], hidden=c["hidden"], layers=c["layers"],
                           scale=c["scale"], pinned=c["pinned"])
    model = model.to(c["rest_dense"].dtype)
    model.load_state_dict(blob["model"])
    return model, blob
