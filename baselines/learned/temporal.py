"""``temporal``: a causal recurrent residual on top of skinning.

Per strand and frame t the inputs are the neighbourhood inputs of ``agnostic``
(:meth:`~baselines.learned.features.GroomBinding.inputs`) plus the recent motion, all in the head
frame: each of its K guides' displacement since the previous frame, the head's translation since
the previous frame in head axes, and its rotation increment (the axial vector of
R_{t−1}ᵀ R_t, as a displacement at 10 cm) (lengths / ``motion_scale``). An encoder MLP feeds a
GRU cell whose state (one per strand) carries the history; an MLP on [encoding, state] gives the
residual:

    h_t = GRU(enc(inputs_t), h_{t−1}),   x_t = skin_t + mask · head([enc_t, h_t]) · scale

The first frame of a stream (or of a training window) has no previous frame: its motion is zero
and h_0 = 0. Training windows are ``window`` frames; the first ``burn_in`` of them only warm the
state (no loss). The loss is the mean squared vertex error plus ``velocity_weight`` × the mean
squared error of the frame-to-frame motion (head frame, mm²). ``predict`` is the causal stream ``reset`` + ``step`` run over the sample, so
both give the same numbers. The model is groom-agnostic like ``agnostic`` (same N).
"""
from __future__ import annotations

import torch
from torch import nn

from baselines.protocol import MethodError, NotApplicable

from .base import LearnedInterpolator, StrandMLP, mm2, register_method
from .data import check_sample
from .features import BindingCache, GroomBinding, to_head, to_world, world_up

__all__ = ["Temporal", "TemporalNet", "motion_inputs"]

CHUNK_FLOATS = 1 << 24
LEVER = 0.1  # m: a rotation increment enters as the displacement at this distance


def _axial(q: torch.Tensor) -> torch.Tensor:
    """Axial vector ½ (Q − Qᵀ)ˇ of (..., 3, 3) → (..., 3) (sin θ · axis for a rotation)."""
    return 0.5 * torch.stack((q[..., 2, 1] - q[..., 1, 2], q[..., 0, 2] - q[..., 2, 0],
                              q[..., 1, 0] - q[..., 0, 1]), -1)


def motion_inputs(binding: GroomBinding, gh: torch.Tensor, gh_prev: torch.Tensor, rot: torch.Tensor,
                  rot_prev: torch.Tensor, trans: torch.Tensor, trans_prev: torch.Tensor, strands: torch.Tensor,
                  motion_scale: float) -> torch.Tensor:
    """Motion inputs (F, B, 3KN + 6) of ``strands`` (B,): head-frame guides now and one frame
    before (F, G, N, 3) m, head rotations (F, 3, 3) and translations (F, 3) m now and before."""
    f, b = gh.shape[0], strands.shape[0]
    nbr = binding.skin.guide_index[strands]
    dg = (gh - gh_prev)[:, nbr].reshape(f, b, -1)
    dt = ((trans - trans_prev)[:, None, :] @ rot)[:, 0]  # head translation in head axes
    dr = _axial(rot_prev.transpose(-1, -2) @ rot) * LEVER
    head = torch.cat((dt, dr), -1)[:, None, :].expand(f, b, 6)
    return torch.cat((dg, head), -1) / motion_scale


class TemporalNet(nn.Module):
    """Encoder MLP → GRU cell → residual MLP (zero last layer). ``dim`` inputs, ``out`` = 3N."""

    def __init__(self, dim: int, out: int, hidden: int, state: int):
        super().__init__()
        self.encoder = nn.Sequential(nn.Linear(dim, hidden), nn.SiLU(), nn.Linear(hidden, state), nn.SiLU())
        self.cell = nn.GRUCell(state, state)
        self.head = StrandMLP(2 * state, out, hidden, 1)
        self.state_size = state

    def encode(self, x: torch.Tensor) -> torch.Tensor:
        return self.encoder(x)

    def advance(self, enc: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
        """GRU step: enc (B, state), h (B, state) → new h."""
        return self.cell(enc, h)

    def residual(self, enc: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
        return self.head(torch.cat((enc, h), -1))


class _Stream:
    """The state of one causal stream: the model's GRU state per strand and the previous frame."""

    def __init__(self, method: "Temporal", model: TemporalNet, sample: dict):
        _, _, s, n = method._check(sample, model)
        self.method, self.model = method, model
        self.dev = next(model.parameters()).device
        self.binding = method.binding({k: (v.to(self.dev) if isinstance(v, torch.Tensor) else v)
                                       for k, v in sample.items() if k in ("rest_positions", "guide_index",
                                                                           "num_pinned")})
        self.s, self.n = s, n
        self.h = torch.zeros(s, model.state_size, device=self.dev)
        self.prev = None
        per = model.encoder[0].in_features
        self.chunk = max(1, min(s, CHUNK_FLOATS // per))

    @torch.no_grad()
    def step(self, guides: torch.Tensor, rot: torch.Tensor, trans: torch.Tensor) -> torch.Tensor:
        """One frame: guides (G, N, 3) m world, rotation (3, 3), translation (3,) m → (S, N, 3) m world."""
        home = guides.device
        g = guides.to(self.dev, torch.float32)[None]
        r, t = rot.to(g)[None], trans.to(g)[None]
        gh = to_head(g, r, t)
        prev = self.prev if self.prev is not None else (gh, r, t)
        out = torch.empty(1, self.s, self.n, 3, device=self.dev)
        for s0 in range(0, self.s, self.chunk):
            st = torch.arange(s0, min(self.s, s0 + self.chunk), device=self.dev)
            x, sk = self.method.frame_inputs(self.binding, gh, prev[0], r, prev[1], t, prev[2], st)
            enc = self.model.encode(x[0])
            h = self.model.advance(enc, self.h[st])
            self.h[st] = h
            res = self.model.residual(enc, h)[None].view(1, -1, self.n, 3)
            out[:, s0:s0 + st.numel()] = sk + res * self.binding.scale * self.binding.mask[st]
        self.prev = (gh, r, t)
        return to_world(out, r, t)[0].to(home)


@register_method
class Temporal(LearnedInterpolator):
    """Causal GRU residual over the guides' recent motion (see the module docstring).

    Model options: ``k`` guides per strand, ``hidden`` width of the MLPs, ``state`` GRU state
    size, ``scale`` and ``motion_scale`` (m), ``window`` frames per training window of which
    the first ``burn_in`` carry no loss, ``velocity_weight`` of the motion term of the loss. Training options: :data:`~baselines.learned.base.TRAIN_DEFAULTS`.
    """

    name = "temporal"
    causal = True
    MODEL_DEFAULTS = {"k": 4, "hidden": 192, "state": 64, "scale": 0.05, "motion_scale": 0.01, "window": 16,
                      "burn_in": 4, "velocity_weight": 5.0}
    stat_names = ("velocity_mm2", "vertex_mm2")
    TRAIN_OVERRIDES = {"batch": 8, "strands": 64, "valid_windows": 24, "valid_strands": 256}

    def __init__(self, device=None, checkpoint=None, **options):
        super().__init__(device=device, checkpoint=checkpoint, **options)
        w, b = self.options["window"], self.options["burn_in"]
        if isinstance(w, bool) or not isinstance(w, int) or not isinstance(b, int) or not 0 <= b < w:
            raise ValueError(f"temporal: need integers 0 <= burn_in < window; got burn_in={b!r}, window={w!r}")
        self._bindings = BindingCache()
        self._stream = None

    @property
    def window(self) -> int:
        return int(self.options["window"])

    def make_model(self, meta: dict) -> TemporalNet:
        n, k = meta["particles"], meta["k"]
        dim = 3 * n * (k + 1) + k + GroomBinding.dynamic_dim(k, n) + 3 * k * n + 6
        return TemporalNet(dim, 3 * n, self.options["hidden"], self.options["state"])

    def binding(self, sample: dict) -> GroomBinding:
        return self._bindings.get(sample["rest_positions"], sample["guide_index"], sample["num_pinned"],
                                  self.options["k"], self.options["scale"])

    def frame_inputs(self, binding, gh, gh_prev, rot, rot_prev, trans, trans_prev, strands):
        """(inputs (F, B, D), skinned (F, B, N, 3) m head frame) of ``strands`` at F frames."""
        feats, sk, _ = binding.inputs(gh, world_up(rot), strands)
        mot = motion_inputs(binding, gh, gh_prev, rot, rot_prev, trans, trans_prev, strands,
                            self.options["motion_scale"])
        return torch.cat((feats, mot), -1), sk

    def window_loss(self, model, item, strands):
        b = self.binding(item)
        rot, trans = item["rotations"], item["translations"]
        gh = to_head(item["guide_positions"], rot, trans)
        shift = lambda x: torch.cat((x[:1], x[:-1]))  # noqa: E731  (the first frame is its own previous)
        x, sk = self.frame_inputs(b, gh, shift(gh), rot, shift(rot), trans, shift(trans), strands)
        enc = model.encode(x)  # (W, B, state)
        h = torch.zeros(strands.shape[0], model.state_size, device=x.device, dtype=x.dtype)
        hs = []
        for t in range(x.shape[0]):
            h = model.advance(enc[t], h)
            hs.append(h)
        w, nb, n = sk.shape[0], sk.shape[1], sk.shape[2]
        res = model.residual(enc, torch.stack(hs)).view(w, nb, n, 3) * b.scale * b.mask[strands]
        keep = slice(self.options["burn_in"], None)
        pred, ref = (sk + res)[keep], to_head(item["positions"][:, strands], rot, trans)[keep]
        loss = mm2(pred, ref)
        # frame-to-frame motion in the head frame against the reference's (mm² per frame²)
        vel = mm2(pred[1:] - pred[:-1], ref[1:] - ref[:-1]) if pred.shape[0] > 1 else loss.new_zeros(())
        total = loss + self.options["velocity_weight"] * vel
        return total, {"vertex_mm2": loss.detach(), "velocity_mm2": vel.detach()}

    def _check(self, sample: dict, model) -> tuple:
        t, g, s, n = check_sample(sample, self.name)
        want = model.head.net[-1].out_features // 3
        if n != want:
            raise NotApplicable(f"method 'temporal': the groom has N = {n} particles per strand; the model was "
                              f"trained with N = {want}")
        return t, g, s, n

    # -- causal streaming ------------------------------------------------------------------
    def reset(self, sample: dict) -> None:
        """Start a stream on ``sample`` (its groom and guides; its frames are not read)."""
        self._stream = _Stream(self, self.trained(), sample)

    def step(self, frame: dict) -> torch.Tensor:
        """One frame (``guide_positions`` (G, N, 3), ``rotation``, ``translation``) → (S, N, 3) m world."""
        if self._stream is None:
            raise MethodError("method 'temporal': call reset(sample) before step(frame)")
        return self._stream.step(frame["guide_positions"], frame["rotation"], frame["translation"])

    @torch.no_grad()
    def predict(self, sample: dict) -> torch.Tensor:
        """Dense positions (T, S, N, 3) m world: the causal stream over the sample's frames."""
        stream = _Stream(self, self.trained(), sample)
        g, r, t = sample["guide_positions"], sample["rotations"], sample["translations"]
        return torch.stack([stream.step(g[i], r[i], t[i]) for i in range(g.shape[0])])
