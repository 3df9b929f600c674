"""The base of the learned methods: options, ``fit`` through the one training loop
(:func:`~baselines.learned.train.fit_method`), loading a checkpoint, and the factory that registers
a method under its built-in name.

A subclass sets ``name``, ``window`` (frames per training window), ``needs_scene`` (training
items need the colliders), ``stat_names`` (what its loss reports), ``MODEL_DEFAULTS`` (its own
options: they are part of the checkpoint key), ``TRAIN_OVERRIDES`` (its defaults of training
options) and implements:

- ``data_meta(item) -> dict``: what the model is built from, read from the first training item;
- ``meta_key(meta)``: a JSON-able digest of it (for the checkpoint key);
- ``make_model(meta) -> nn.Module``: the untrained model (its output starts at the skinning);
- ``window_loss(model, item, strands) -> (loss, stats)``: the mean loss (mm²) of one window
  (a training item on the device, with colliders when ``needs_scene``) over the strands (B,);
- ``predict(sample)``;
- optionally ``unsuitable(item, first) -> str``: why a validation window cannot score it.
"""
from __future__ import annotations

import os

import inspect
import math
from abc import abstractmethod
from typing import Dict

import torch
from torch import nn

from baselines.protocol import Interpolator, MethodError, register

from .train import fit_method, load_blob

__all__ = ["TRAIN_DEFAULTS", "LearnedInterpolator", "StrandMLP", "register_method", "mm2"]

#: training options every learned method takes (see :mod:`baselines.learned.train`)
TRAIN_DEFAULTS: Dict[str, object] = {
    "steps": 20000,         # most optimiser steps (a cap: early stopping ends sooner once validation stalls)
    "batch": 16,            # windows per step (global, over all DDP ranks)
    "strands": 128,         # strands drawn from each window (all when fewer)
    "lr": 1e-3,             # Adam learning rate at the start
    "lr_min": 1e-5,         # the plateau schedule halves the rate down to this
    "patience": 10,         # validations without improvement before stopping
    "lr_patience": 3,       # validations without improvement before halving the rate
    "min_delta": 2e-3,      # relative decrease of the validation loss that counts as improvement
    "valid_every": 100,     # steps between validations
    "valid_windows": 48,    # validation windows (evenly spread over the valid split)
    "valid_strands": 512,   # strands per validation window (fixed draw)
    "holdout": 0.2,         # share of the train sequences held out when no valid split is given
    "stride": 1,            # frames between the starts of training windows
    "seed": 0,
    "workers": 0,           # DataLoader worker processes
    "progress": True,
}

_POSITIVE_INT = ("steps", "batch", "patience", "lr_patience", "valid_every", "stride")
_NONNEG_INT = ("strands", "valid_windows", "valid_strands", "seed", "workers")


def mm2(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Mean squared distance of points a, b (..., 3) m, in mm²."""
    return ((a - b) * 1000.0).square().sum(-1).mean()


class StrandMLP(nn.Module):
    """inputs (..., D) → (..., out): ``layers`` hidden SiLU layers of width ``hidden``; the last
    layer starts at zero (so an untrained residual model is exactly its base)."""

    def __init__(self, dim: int, out: int, hidden: int, layers: int):
        super().__init__()
        mods, width = [], dim
        for _ in range(layers):
            mods += [nn.Linear(width, hidden), nn.SiLU()]
            width = hidden
        last = nn.Linear(width, out)
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)
        self.net = nn.Sequential(*mods, last)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


class LearnedInterpolator(Interpolator):
    """Common part of the learned methods (see the module docstring).

    Args (keyword): ``device`` (training and prediction), ``checkpoint`` (path: load it when it
    matches, else train and write it), the training options :data:`TRAIN_DEFAULTS` and the
    method's ``MODEL_DEFAULTS``.
    """

    learned = True
    window = 1
    needs_scene = False
    stat_names = ("vertex_mm2",)
    MODEL_DEFAULTS: Dict[str, object] = {}
    #: the method's own defaults of training options
    TRAIN_OVERRIDES: Dict[str, object] = {}

    @classmethod
    def defaults(cls) -> dict:
        """Every option of the method with its default (training, then model options)."""
        return {**TRAIN_DEFAULTS, **cls.TRAIN_OVERRIDES, **cls.MODEL_DEFAULTS}

    def __init__(self, device=None, checkpoint=None, **options):
        known = self.defaults()
        unknown = sorted(set(options) - set(known))
        if unknown:
            raise TypeError(f"{self.name}: unknown option(s) {unknown}; options: {sorted(known)}")
        self.options = {**known, **options}
        for k in _POSITIVE_INT + _NONNEG_INT:
            v = self.options[k]
            low = 1 if k in _POSITIVE_INT else 0
            if isinstance(v, bool) or not isinstance(v, int) or v < low:
                raise ValueError(f"{self.name}: option {k} must be an integer >= {low}; got {v!r}")
        for k in ("lr", "lr_min", "min_delta", "holdout"):
            v = self.options[k]
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"{self.name}: option {k} must be a number >= 0; got {v!r}")
        if not 0 < self.options["holdout"] < 1:
            raise ValueError(f"{self.name}: option holdout must be in (0, 1); got {self.options['holdout']!r}")
        self.device = torch.device(device) if device is not None else torch.device("cpu")
        self.checkpoint = None if checkpoint is None else str(checkpoint)
        self.model = None
        self.history = None
        self.result = None

    # -- options ------------------------------------------------------------------------
    def train_options(self) -> dict:
        return {k: self.options[k] for k in TRAIN_DEFAULTS}

    def model_options(self) -> dict:
        return {k: self.options[k] for k in self.MODEL_DEFAULTS}

    # -- fit / load ---------------------------------------------------------------------
    def fit(self, train, guides: torch.Tensor, *, valid=None) -> "LearnedInterpolator":
        """Train on ``train`` (validating on ``valid``, or on held-out train sequences), or load
        the ``checkpoint`` when it holds this training. Returns self."""
        self.result = fit_method(self, train, guides, valid)
        self.history = self.result["history"]
        return self

    def load(self, path: str) -> "LearnedInterpolator":
        """Load the best model of a checkpoint written by ``fit`` (no data needed). Returns self."""
        blob = load_blob(path)
        if blob["method"] != self.name:
            raise ValueError(f"{path} holds a {blob['method']!r} model, not {self.name!r}")
        self.options.update(blob["options"])
        model = self.make_model(blob["meta"])
        model.load_state_dict(blob["model"])
        self.model = model.to(self.device).eval()
        self.history = blob["history"]
        self.result = {k: blob.get(k) for k in ("best_step", "best_valid", "stopped", "steps", "key")}
        return self

    @property
    def model_id(self):
        """Which trained weights predict: ``"<checkpoint key[:16]>@<best step>/<steps trained>"``
        (None before fit/load). The benchmark stores it in each row and scores again the rows of
        another model (e.g. after training resumed under a larger step cap)."""
        r = self.result
        if not r or not r.get("key"):
            return None
        return f"{r['key'][:16]}@{r['best_step']}/{r['steps']}"

    def trained(self) -> nn.Module:
        """The model: fitted, loaded, or else loaded now from the ``checkpoint`` the method was made
        with when that file holds a finished training (the benchmark's protocol); a MethodError
        when there is none."""
        if self.model is None and self.checkpoint and os.path.exists(self.checkpoint):
            if load_blob(self.checkpoint).get("finished"):
                self.load(self.checkpoint)
        if self.model is None:
            raise MethodError(f"method {self.name!r} is not trained: call fit(train, guides) or load(checkpoint) "
                              f"first")
        return self.model

    # -- hooks ---------------------------------------------------------------------------
    def data_meta(self, item: dict) -> dict:
        n = item["rest_positions"].shape[1]
        return {"particles": int(n), "k": int(min(self.options.get("k", 4), item["guide_index"].numel()))}

    def meta_key(self, meta: dict):
        return meta

    def unsuitable(self, item: dict, first: dict) -> str:
        """Why a window cannot train or score this method trained on items like ``first`` ('' when
        it can). The models take a fixed number of particles per strand N: another N is unsuitable."""
        n, want = item["rest_positions"].shape[1], first["rest_positions"].shape[1]
        return "" if n == want else f"another number of particles per strand (N = {n}, not {want})"

    @abstractmethod
    def make_model(self, meta: dict) -> nn.Module:
        """The untrained model of ``meta`` (:meth:`data_meta`)."""

    @abstractmethod
    def window_loss(self, model: nn.Module, item: dict, strands: torch.Tensor):
        """(mean loss of the window in mm², {stat name: value}) over ``strands`` (B,) of ``item``."""


def register_method(cls):
    """Register ``cls`` under ``cls.name`` with a factory whose signature lists every option (so the
    benchmark passes only the options a method takes). Returns cls."""
    def factory(**options):
        return cls(**options)

    params = [inspect.Parameter(k, inspect.Parameter.KEYWORD_ONLY, default=v)
              for k, v in {"device": None, "checkpoint": None, **cls.defaults()}.items()]
    factory.__signature__ = inspect.Signature(params)
    factory.__name__ = factory.__qualname__ = cls.name.replace("-", "_")
    factory.__doc__ = f"The {cls.name!r} method: {cls.__name__}(**options)."
    register(cls.name)(factory)
    cls.factory = staticmethod(factory)
    return cls
