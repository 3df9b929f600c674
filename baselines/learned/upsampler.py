"""``upsampler``: the residual MLP of :class:`baselines.upsampler.GuideUpsampler` (skinning + a
per-strand, per-frame residual) as a benchmark method, trained to convergence (validation loss,
plateau schedule, early stopping).

It is bound to the groom it was trained on (its rest shape, guides and pinned counts are part of
the model): every training sequence must share one groom, and ``predict`` refuses another one
(use ``agnostic`` for held-out grooms).
"""
from __future__ import annotations

import hashlib

import torch

from baselines.protocol import NotApplicable
from baselines.upsampler import GuideUpsampler

from .base import LearnedInterpolator, mm2, register_method
from .data import check_sample, digest

__all__ = ["Upsampler"]


def _same_groom(model: GuideUpsampler, rest: torch.Tensor, guide_index: torch.Tensor) -> str:
    """'' when (rest, guide_index) is the model's groom, else what differs."""
    mine = model.skin.rest_dense
    if tuple(rest.shape) != tuple(mine.shape):
        return f"the groom has {tuple(rest.shape[:2])} (S, N); the model was trained on {tuple(mine.shape[:2])}"
    if not torch.allclose(rest.to(mine), mine, atol=1e-6, rtol=0):
        return "the groom's rest shape differs from the one the model was trained on"
    gi = model.guide_strands.to(guide_index.device)
    if not torch.equal(guide_index.long(), gi):
        return f"guide_index {guide_index.tolist()[:8]}... differs from the trained {gi.tolist()[:8]}..."
    return ""


@register_method
class Upsampler(LearnedInterpolator):
    """Skinning + the residual MLP of :class:`~baselines.upsampler.GuideUpsampler`, one groom.

    Model options: ``k`` guides per strand, ``hidden`` width, ``layers`` hidden layers, ``scale``
    length scale (m). Training options: :data:`~baselines.learned.base.TRAIN_DEFAULTS`.
    """

    name = "upsampler"
    MODEL_DEFAULTS = {"k": 4, "hidden": 192, "layers": 3, "scale": 0.05}

    def data_meta(self, item: dict) -> dict:
        return {"rest": item["rest_positions"].detach().cpu().float(),
                "guide_index": item["guide_index"].detach().cpu().long(),
                "num_pinned": item["num_pinned"].detach().cpu().long()}

    def meta_key(self, meta: dict):
        return digest([hashlib.sha256(meta["rest"].numpy().tobytes()).hexdigest(), meta["guide_index"].tolist(),
                       meta["num_pinned"].tolist()])

    def unsuitable(self, item: dict, first: dict) -> str:
        rest, mine = item["rest_positions"], first["rest_positions"]
        if rest.shape != mine.shape or not torch.allclose(rest, mine, atol=1e-6, rtol=0):
            return "another groom"
        return ""

    def make_model(self, meta: dict) -> GuideUpsampler:
        o = self.options
        rest, gi = meta["rest"], meta["guide_index"]
        model = GuideUpsampler(rest, rest[gi], k=o["k"], hidden=o["hidden"], layers=o["layers"], scale=o["scale"],
                               pinned=meta["num_pinned"])
        model.register_buffer("guide_strands", gi.clone())
        return model

    def window_loss(self, model, item, strands):
        why = _same_groom(model, item["rest_positions"], item["guide_index"])
        if why:
            raise ValueError(f"upsampler: sequence {item['sequence']}: {why}. The upsampler is bound to one groom: "
                             f"train it on the sequences of one groom, or use 'agnostic'")
        g = item["guide_positions"]
        w, b = g.shape[0], strands.shape[0]
        gk = g[:, model.skin.guide_index[strands]].reshape(w * b, model.k, model.n, 3)
        rot = item["rotations"].repeat_interleave(b, 0)
        trans = item["translations"].repeat_interleave(b, 0)
        pred = model.strands_forward(gk, strands.repeat(w), rot, trans)
        loss = mm2(pred, item["positions"][:, strands].reshape(w * b, model.n, 3))
        return loss, {"vertex_mm2": loss.detach()}

    @torch.no_grad()
    def predict(self, sample: dict) -> torch.Tensor:
        """Dense positions (T, S, N, 3) m world; the sample's groom and guides must be the trained ones."""
        model = self.trained()
        t, _, s, n = check_sample(sample, self.name)
        dev = model.skin.rest_dense.device
        why = _same_groom(model, sample["rest_positions"].to(dev), sample["guide_index"].to(dev))
        if why:
            raise NotApplicable(f"method 'upsampler': {why}; the upsampler applies to the groom it was trained on "
                              f"(use 'agnostic' for other grooms)")
        g = sample["guide_positions"].to(dev, torch.float32)
        rot, trans = sample["rotations"].to(g), sample["translations"].to(g)
        chunk = max(1, (1 << 22) // max(s * n, 1))
        out = [model(g[i:i + chunk], rot[i:i + chunk], trans[i:i + chunk]) for i in range(0, t, chunk)]
        return torch.cat(out).to(sample["guide_positions"].device)
