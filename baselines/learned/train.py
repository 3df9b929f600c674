"""The training loop every learned method's ``fit`` runs (and ``scripts/train_interp.py``, under
DDP or not): windows streamed from the dataset, a validation loss, a plateau learning-rate
schedule, early stopping, atomic checkpoints and resumption.

Step ``k`` takes global batch ``k`` of ``batch`` windows (:func:`~baselines.learned.data.batch_windows`,
per-epoch permutations from ``seed``) and, in each window, a subset of ``strands`` strands drawn
from (seed, step, slot). Under DDP (``torch.distributed`` initialised) each rank takes its
contiguous share of the windows, its losses are divided by the global batch and the gradients
summed over the ranks, so a step is the same whatever the world size. The validation loss (the
training loss on fixed windows and strands of the valid split, or of sequences held out of the
train split) is taken every ``valid_every`` steps; the learning rate halves after
``lr_patience`` validations without a relative improvement of ``min_delta``, training stops
after ``patience`` of them, and the best model is kept.

The checkpoint (``checkpoint=`` path) is written atomically at every validation and at the end.
It holds the best model, the method's model configuration, a key (method, model configuration,
guides, data) and the training state: a run finds a checkpoint with the same key and resumes it
(or loads it when training finished by early stopping, or reached at least ``steps``).
"""
from __future__ import annotations

import copy
import math
import os
import warnings
from typing import Optional

import torch

from .data import (StepBatches, keep_sequences, check_item, dataset_fingerprint, digest, holdout, item_sequences,
                   strand_subset, to_device,
                   window_view)

__all__ = ["fit_method", "save_blob", "load_blob", "dist_info"]

FORMAT = "ams_torch.learned/1"


def dist_info():
    """(rank, world size) of the initialised torch.distributed group, else (0, 1)."""
    import torch.distributed as dist

    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


def _all_reduce(t: torch.Tensor, world: int) -> torch.Tensor:
    if world > 1:
        import torch.distributed as dist

        dist.all_reduce(t)
    return t


def save_blob(path: str, blob: dict) -> None:
    """torch.save ``blob`` to ``path`` atomically (temporary file + rename), parents created."""
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    tmp = f"{path}.tmp{os.getpid()}"
    torch.save(blob, tmp)
    os.replace(tmp, path)


def load_blob(path: str) -> dict:
    """A checkpoint written by :func:`save_blob` (on the CPU); ValueError when it is not one of a
    learned method."""
    blob = torch.load(path, map_location="cpu", weights_only=False)
    if not isinstance(blob, dict) or blob.get("format") != FORMAT:
        raise ValueError(f"{path} is not a checkpoint of a learned interpolator ({FORMAT})")
    return blob


def _base(ds):
    return ds.dataset if isinstance(ds, torch.utils.data.Subset) else ds


def _prepare(method, item: dict, ds, device) -> dict:
    check_item(item, method.name)
    if method.needs_scene:
        from baselines.scene import make_sample

        return make_sample(item, _base(ds), device)
    return to_device(item, device)


def _loader(view, sampler, workers: int, device):
    return torch.utils.data.DataLoader(view, batch_sampler=sampler, collate_fn=list, num_workers=workers,
                                       pin_memory=device.type == "cuda")


def _validation_ids(n: int, count: int):
    if count <= 0 or count >= n:
        return list(range(n))
    return sorted({int(round(i * (n - 1) / max(count - 1, 1))) for i in range(count)})


@torch.no_grad()
def _validate(method, model, view, ids, opt, device, rank, world):
    model.eval()
    tot = torch.zeros(2, dtype=torch.float64, device=device)
    stats_sum = {}
    for j, i in enumerate(ids):
        if j % world != rank:
            continue
        item = _prepare(method, view[i], view, device)
        strands = strand_subset(item["rest_positions"].shape[0], opt["valid_strands"], opt["seed"] * 7919 + i)
        loss, stats = method.window_loss(model, item, strands.to(device))
        tot[0] += float(loss)
        tot[1] += 1
        for k, v in stats.items():
            stats_sum[k] = stats_sum.get(k, 0.0) + float(v)
    keys = sorted(method.stat_names)
    extra = torch.tensor([stats_sum.get(k, 0.0) for k in keys], dtype=torch.float64, device=device)
    _all_reduce(tot, world)
    _all_reduce(extra, world)
    model.train()
    n = max(float(tot[1]), 1.0)
    return float(tot[0]) / n, {k: float(v) / n for k, v in zip(keys, extra.tolist())}


def _validation_windows(method, valid, first: dict, opt: dict):
    """(window view of ``valid``, the validation window ids that suit the method)."""
    vview = window_view(valid, method.window, method.window)
    ids = _validation_ids(len(vview), opt["valid_windows"])
    return vview, [i for i in ids if not method.unsuitable(vview[i], first)]


def _make_key(method, meta_key, guides, data) -> str:
    return digest({"method": method.name, "config": method.model_options(), "meta": meta_key,
                   "guides": [int(g) for g in guides], "data": data})


def _suited_training(method, train, view, first, opt):
    """(view, first) restricted to the sequences of the largest group that suits the method
    (``unsuitable``): the sequences with the most common number of particles per strand, or for a
    method bound to one groom, that groom's (said in a warning when some are left out). One window
    per sequence is read."""
    if not hasattr(view, "sequences"):
        return view, first
    reps = {}  # sequence index -> its first window
    for i, (q, _) in enumerate(view.items):
        reps.setdefault(int(view.sequences[q][2]), i)
    items = {seq: view[i] for seq, i in reps.items()}
    groups = {seq: [o for o in items if not method.unsuitable(items[o], items[seq])] for seq in items}
    best = max(groups, key=lambda q: (len(groups[q]), -q))
    if len(groups[best]) == len(items):
        return view, first
    other = next(o for o in items if o not in groups[best])
    warnings.warn(f"{method.name}: the train split holds {len(items)} sequences that one model cannot all take "
                  f"(sequence {other}: {method.unsuitable(items[other], items[best])}); training on the "
                  f"{len(groups[best])} like sequence {best}, the largest such group; it predicts only those",
                  stacklevel=4)
    view = window_view(train, method.window, opt["stride"], keep=groups[best])
    return view, view[0]


def fit_method(method, train, guides: torch.Tensor, valid=None) -> dict:
    """Train ``method`` (a :class:`~baselines.learned.base.LearnedInterpolator`) on the ``train``
    dataset, validating on ``valid`` (or on sequences held out of ``train``). Sets
    ``method.model`` to the best model and returns ``{"history", "best_step", "best_valid",
    "stopped", "steps", "key"}`` (key: the checkpoint key, a hex digest). See the module docstring."""
    opt = method.train_options()
    device = method.device
    rank, world = dist_info()
    if opt["batch"] % world:
        raise ValueError(f"{method.name}: batch = {opt['batch']} windows must be divisible by the world size {world}")
    data_key = {"train": dataset_fingerprint(train), "valid": None if valid is None else dataset_fingerprint(valid)}
    given, whole = valid, train
    if valid is None:
        train, valid = holdout(train, opt["holdout"])
    view = window_view(train, method.window, opt["stride"])
    if len(view) == 0:
        raise ValueError(f"{method.name}: no training window of {method.window} frames")
    first = view[0]
    check_item(first, method.name)
    gi = torch.as_tensor(guides).long().cpu()  # the guides of the first item (each groom has its own)
    if not torch.equal(first["guide_index"].long().cpu(), gi):
        raise ValueError(f"{method.name}: fit(guides=...) got {gi.tolist()[:8]}... but the items' guide_index is "
                         f"{first['guide_index'].tolist()[:8]}... (open the dataset with the same guides)")
    view, first = _suited_training(method, train, view, first, opt)
    gi = first["guide_index"].long().cpu()  # a groom-bound method: its groom's guides
    if first["positions"].shape[0] < method.window:
        raise ValueError(f"{method.name}: needs windows of {method.window} frames; the dataset's items have "
                         f"{first['positions'].shape[0]}")
    vview, vids = _validation_windows(method, valid, first, opt)
    if not vids and given is not None:
        warnings.warn(f"{method.name}: no window of the valid split suits the method (e.g. another groom); "
                      f"validating on sequences held out of the train split instead", stacklevel=3)
        # held out of the sequences the method trains on (one groom for a groom-bound method)
        train, valid = holdout(keep_sequences(whole, sorted(set(item_sequences(view)))), opt["holdout"])
        view = window_view(train, method.window, opt["stride"])
        first = view[0]
        vview, vids = _validation_windows(method, valid, first, opt)
    if not vids:
        raise ValueError(f"{method.name}: no validation window suits the method")
    meta = method.data_meta(first)
    key = _make_key(method, method.meta_key(meta), gi, data_key)
    path = method.checkpoint
    blob = None
    if path and os.path.exists(path):
        blob = load_blob(path)
        if blob.get("key") != key:
            warnings.warn(f"{path}: the checkpoint was trained with another method, model configuration, guides or "
                          f"data; training anew (it will be overwritten)", stacklevel=3)
            blob = None
    with torch.random.fork_rng(devices=[]):  # the initial weights come from the seed; the caller's RNG is left alone
        torch.manual_seed(opt["seed"])
        model = method.make_model(meta if blob is None else blob["meta"]).to(device)
    if blob is not None and blob["finished"] and (blob["stopped"] == "early" or blob["steps"] >= opt["steps"]):
        model.load_state_dict(blob["model"])
        method.model = model.eval()
        return {**{k: blob[k] for k in ("history", "best_step", "best_valid", "stopped", "steps")}, "key": key}
    params = [p for p in model.parameters() if p.requires_grad]
    optim = torch.optim.Adam(params, lr=opt["lr"])
    state = {"step": 0, "history": {"train": [], "valid": []}, "best_valid": math.inf, "best_step": 0, "bad": 0,
             "lr": opt["lr"]}
    best = copy.deepcopy(model.state_dict())
    if blob is not None:
        tr = blob["train"]
        model.load_state_dict(tr["model"])
        optim.load_state_dict(tr["optimizer"])
        state.update({k: tr[k] for k in ("step", "history", "best_valid", "best_step", "bad", "lr")})
        best = blob["model"]
    if world > 1:  # every rank starts from rank 0's weights
        import torch.distributed as dist

        for p in model.state_dict().values():
            dist.broadcast(p, 0)
    for g in optim.param_groups:
        g["lr"] = state["lr"]

    def checkpoint(finished: bool, stopped: Optional[str]):
        if rank != 0 or not path:
            return
        save_blob(path, {"format": FORMAT, "method": method.name, "key": key, "meta": meta,
                         "options": method.model_options(), "train_options": opt, "guides": gi,
                         "model": best, "finished": finished, "stopped": stopped, "steps": state["step"],
                         "history": state["history"], "best_step": state["best_step"],
                         "best_valid": state["best_valid"],
                         "train": {"model": model.state_dict(), "optimizer": optim.state_dict(),
                                   **{k: state[k] for k in ("step", "history", "best_valid", "best_step", "bad",
                                                            "lr")}}})

    def validate_now():
        v, stats = _validate(method, model, vview, vids, opt, device, rank, world)
        state["history"]["valid"].append({"step": state["step"], "loss": v, "lr": state["lr"], **stats})
        if v < state["best_valid"] * (1 - opt["min_delta"]):
            state.update(best_valid=v, best_step=state["step"], bad=0)
            return copy.deepcopy(model.state_dict()), False
        state["bad"] += 1
        if state["bad"] % opt["lr_patience"] == 0:
            state["lr"] = max(state["lr"] * 0.5, opt["lr_min"])
            for g in optim.param_groups:
                g["lr"] = state["lr"]
        return None, state["bad"] >= opt["patience"]

    if state["step"] == 0 and not state["history"]["valid"]:
        new, _ = validate_now()  # the untrained model (the method's starting point, e.g. skinning)
        best = new if new is not None else best
    stopped = "steps"
    bar = None
    if rank == 0 and opt["progress"]:
        from tqdm.auto import tqdm

        bar = tqdm(total=opt["steps"], initial=state["step"], desc=f"{method.name} G={gi.numel()}", unit="step")
    local = opt["batch"] // world
    sampler = StepBatches(len(view), opt["batch"], opt["seed"], state["step"], opt["steps"], rank, world)
    model.train()
    if state["step"] < opt["steps"]:
        for items in _loader(view, sampler, opt["workers"], device):
            step = state["step"]
            optim.zero_grad(set_to_none=True)
            total = torch.zeros((), dtype=torch.float64, device=device)
            for j, raw in enumerate(items):
                slot = rank * local + j
                item = _prepare(method, raw, view, device)
                strands = strand_subset(item["rest_positions"].shape[0], opt["strands"],
                                        (opt["seed"] * 1000003 + step) * 4099 + slot)
                loss, _ = method.window_loss(model, item, strands.to(device))
                (loss / opt["batch"]).backward()
                total += loss.detach().double()
            if world > 1:
                grads = [p.grad if p.grad is not None else torch.zeros_like(p) for p in params]
                flat = torch.cat([g.reshape(-1) for g in grads])
                _all_reduce(flat, world)
                off = 0
                for p, g in zip(params, grads):
                    p.grad = flat[off:off + g.numel()].view_as(g)
                    off += g.numel()
            optim.step()
            _all_reduce(total, world)
            state["history"]["train"].append(float(total) / opt["batch"])
            state["step"] = step + 1
            stop = False
            if state["step"] % opt["valid_every"] == 0 or state["step"] == opt["steps"]:
                new, stop = validate_now()
                best = new if new is not None else best
                checkpoint(False, None)
            if bar is not None:
                last = state["history"]["valid"][-1]["loss"]
                bar.update(1)
                bar.set_postfix(loss=f"{state['history']['train'][-1]:.4g}", valid=f"{last:.4g}",
                                best=f"{state['best_valid']:.4g}", lr=f"{state['lr']:.2g}")
            if stop:
                stopped = "early"
                break
    if bar is not None:
        bar.close()
    checkpoint(True, stopped)
    model.load_state_dict(best)
    if world > 1:
        import torch.distributed as dist

        dist.barrier()
    method.model = model.eval()
    return {"history": state["history"], "best_step": state["best_step"], "best_valid": state["best_valid"],
            "stopped": stopped, "steps": state["step"], "key": key}
