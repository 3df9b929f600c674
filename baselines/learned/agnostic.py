"""``agnostic``: a groom-agnostic residual on top of skinning.

Each strand's inputs come from its own neighbourhood (:class:`~baselines.learned.features.GroomBinding`):
its rest shape relative to its root, its K nearest guides' rest shapes relative to its own rest
shape (which holds the root offsets), the skinning weights, the guides' and the skinned strand's
displacements from rest in the head frame, and the world up axis in the head frame. No input is a
per-groom table, so one trained model applies to any groom with the same particles per strand N
(any strand count S, any guides):

    x_i = skin_i + mask_i · MLP(inputs_i) · scale        (head frame; mask 0 on the pinned prefix)

The last layer starts at zero: an untrained model is the skinning. The binding of each groom is
built once from the sample (``rest_positions``, ``guide_index``, ``num_pinned``) and cached.
"""
from __future__ import annotations

from typing import Optional

import torch

from baselines.protocol import MethodError, NotApplicable

from .base import LearnedInterpolator, StrandMLP, mm2, register_method
from .data import check_sample
from .features import BindingCache, GroomBinding, pose_tensors, to_head, to_world, world_up

__all__ = ["Agnostic", "NeighbourhoodMethod"]

#: floats of inputs per chunk of (frames × strands) at prediction
CHUNK_FLOATS = 1 << 24


class NeighbourhoodMethod(LearnedInterpolator):
    """A per-frame residual MLP over neighbourhood inputs (base of ``agnostic`` and ``collision``).

    Subclasses add inputs with :meth:`extra_dim` / :meth:`extra_inputs` and terms to the loss
    with :meth:`extra_loss`."""

    MODEL_DEFAULTS = {"k": 4, "hidden": 256, "layers": 3, "scale": 0.05}

    def __init__(self, device=None, checkpoint=None, **options):
        super().__init__(device=device, checkpoint=checkpoint, **options)
        self._bindings = BindingCache()

    def extra_dim(self, meta: dict) -> int:
        return 0

    def extra_inputs(self, skinned_world, rot, scene) -> Optional[torch.Tensor]:
        return None

    def extra_loss(self, pred_world, binding, strands, scene):
        return None

    def input_dim(self, meta: dict) -> int:
        n, k = meta["particles"], meta["k"]
        return 3 * n * (k + 1) + k + GroomBinding.dynamic_dim(k, n) + self.extra_dim(meta)

    def make_model(self, meta: dict) -> StrandMLP:
        o = self.options
        return StrandMLP(self.input_dim(meta), 3 * meta["particles"], o["hidden"], o["layers"])

    def binding(self, sample: dict) -> GroomBinding:
        return self._bindings.get(sample["rest_positions"], sample["guide_index"], sample["num_pinned"],
                                  self.options["k"], self.options["scale"])

    def scene(self, sample: dict, frames: slice):
        """(colliders, [(rotation (F, 3, 3), translation (F, 3))]) of the frames, or None."""
        if not self.needs_scene:
            return None
        t = sample["guide_positions"].shape[0]
        poses = pose_tensors(sample.get("collider_poses", []), t)
        return sample.get("colliders", []), [(r[frames], tr[frames]) for r, tr in poses]

    def forward_frames(self, model, binding: GroomBinding, guides_head, rot, trans, strands, scene):
        """Head-frame prediction (F, B, N, 3) m of ``strands`` (B,) from head-frame guides
        (F, G, N, 3) and the head pose (F, 3, 3), (F, 3)."""
        feats, sk, _ = binding.inputs(guides_head, world_up(rot), strands)
        extra = self.extra_inputs(to_world(sk, rot, trans) if scene is not None else None, rot, scene)
        if extra is not None:
            feats = torch.cat((feats, extra), -1)
        f, b, n, _ = sk.shape
        res = model(feats).view(f, b, n, 3) * binding.scale * binding.mask[strands]
        return sk + res

    def window_loss(self, model, item, strands):
        b = self.binding(item)
        rot, trans = item["rotations"], item["translations"]
        scene = self.scene(item, slice(None))
        pred = self.forward_frames(model, b, to_head(item["guide_positions"], rot, trans), rot, trans, strands,
                                   scene)
        data = mm2(pred, to_head(item["positions"][:, strands], rot, trans))
        extra = self.extra_loss(to_world(pred, rot, trans), b, strands, scene)
        if extra is None:
            return data, {"vertex_mm2": data.detach()}
        term, stats = extra
        return data + term, {"vertex_mm2": data.detach(), **stats}

    def _check(self, sample: dict, model) -> tuple:
        t, g, s, n = check_sample(sample, self.name)
        want = model.net[-1].out_features // 3
        if n != want:
            raise NotApplicable(f"method {self.name!r}: the groom has N = {n} particles per strand; the model was "
                              f"trained with N = {want}")
        return t, g, s, n

    @torch.no_grad()
    def predict(self, sample: dict) -> torch.Tensor:
        """Dense positions (T, S, N, 3) m world, for any groom with the trained N."""
        model = self.trained()
        t, _, s, n = self._check(sample, model)
        dev = next(model.parameters()).device
        home = sample["guide_positions"].device
        sample = {k: (v.to(dev) if isinstance(v, torch.Tensor) else v) for k, v in sample.items()}
        b = self.binding(sample)
        rot, trans = sample["rotations"].float(), sample["translations"].float()
        gh = to_head(sample["guide_positions"].float(), rot, trans)
        per = model.net[0].in_features
        strands_chunk = max(1, min(s, CHUNK_FLOATS // per))
        frames_chunk = max(1, CHUNK_FLOATS // (per * strands_chunk))
        out = torch.empty(t, s, n, 3, device=dev)
        for f0 in range(0, t, frames_chunk):
            fr = slice(f0, min(t, f0 + frames_chunk))
            scene = self.scene(sample, fr)
            for s0 in range(0, s, strands_chunk):
                st = torch.arange(s0, min(s, s0 + strands_chunk), device=dev)
                pred = self.forward_frames(model, b, gh[fr], rot[fr], trans[fr], st, scene)
                out[fr, s0:s0 + st.numel()] = to_world(pred, rot[fr], trans[fr])
        return out.to(home)


@register_method
class Agnostic(NeighbourhoodMethod):
    """Groom-agnostic residual MLP on neighbourhood inputs (see the module docstring).

    Model options: ``k`` guides per strand, ``hidden`` width, ``layers`` hidden layers, ``scale``
    length scale (m). Training options: :data:`~baselines.learned.base.TRAIN_DEFAULTS`.
    """

    name = "agnostic"
