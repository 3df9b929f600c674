"""Train a learned guide-to-dense method of the benchmark on the train split of an
``ams-torch generate`` dataset, validating on its valid split (or on train sequences held out
when the recipe has none). It runs the method's own ``fit`` (what ``ams-torch bench-interp
--train`` calls), so a model trained here is the benchmark's.

    python scripts/train_interp.py --method upsampler --data out/bench_mini --guides 64 --out out/up64
    python scripts/train_interp.py --method temporal --data out/bench_mini --guides 64 --out out/tmp64 \\
        --device cuda --steps 20000 --patience 20 --option state=128
    torchrun --nnodes=1 --nproc_per_node=2 --master_addr=127.0.0.1 --master_port=29512 \\
        scripts/train_interp.py ...         # DDP: gloo on CPU (loopback only), nccl on GPUs

Methods: ``upsampler``, ``agnostic``, ``collision``, ``temporal`` (``baselines.learned``), or any
``package.module:factory`` whose method has ``fit``. ``--out DIR`` (created) receives
``model.pt`` (the checkpoint: best model and training state, written atomically at every
validation), ``history.json`` (training loss per step, validation losses) and ``summary.json``.
A run on a DIR whose ``model.pt`` holds an unfinished training of the same method, options,
guides and data resumes it; ``--restart`` starts over. Windows are streamed from the dataset
(``--workers`` DataLoader processes); nothing is loaded whole.
"""
from __future__ import annotations

import argparse
import ast
import json
import os
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--method", required=True,
                   help="upsampler, agnostic, collision, temporal, or package.module:factory")
    p.add_argument("--data", required=True, help="an `ams-torch generate` dataset (folder or shard file)")
    p.add_argument("--guides", type=int, required=True, help="guide count G (one of the recipe's [store] guides)")
    p.add_argument("--out", required=True, help="output folder (created): model.pt, history.json, summary.json")
    p.add_argument("--device", default=None, help="cpu (default), cuda, cuda:1, ...; under torchrun: cuda uses "
                   "cuda:LOCAL_RANK")
    for name, typ in (("steps", int), ("patience", int), ("batch", int), ("strands", int), ("lr", float),
                      ("valid-every", int), ("seed", int), ("workers", int)):
        p.add_argument(f"--{name}", type=typ, default=None, help="training option (default: the method's)")
    p.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                   help="any other option of the method (e.g. hidden=256, window=24); repeatable")
    p.add_argument("--restart", action="store_true", help="ignore (and overwrite) an existing DIR/model.pt")
    p.add_argument("--threads", type=int, default=0, help="torch CPU threads per process (0: torch's default)")
    p.add_argument("--init-method", default="env://", help="torch.distributed init method under DDP")
    p.add_argument("--no-progress", action="store_true")
    return p.parse_args(argv)


def _value(text: str):
    try:
        return ast.literal_eval(text)
    except (ValueError, SyntaxError):
        return text


def method_options(args) -> dict:
    """The method options the command line sets (None: not given)."""
    opts = {k.replace("-", "_"): getattr(args, k.replace("-", "_")) for k in
            ("steps", "patience", "batch", "strands", "lr", "valid-every", "seed", "workers")}
    opts = {k: v for k, v in opts.items() if v is not None}
    for item in args.option:
        key, sep, val = item.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"--option {item!r}: give KEY=VALUE")
        opts[key.strip()] = _value(val.strip())
    if args.no_progress:
        opts["progress"] = False
    return opts


def open_split(data: str, split: str, guides: int):
    """The ``split`` of dataset ``data`` with ``guides`` guides per item, or None when the dataset
    has no sequence in that split."""
    from ams_torch.apps.data import HairSequenceDataset

    try:
        return HairSequenceDataset(data, split=split, guides=guides)
    except ValueError as err:
        if "no sequences found" in str(err):
            return None
        raise


def setup_distributed(init_method: str, device):
    """(rank, world, device) from torchrun's environment (one process: rank 0, world 1)."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    want = torch.device(device) if device else torch.device("cpu")
    if want.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"--device {device}: CUDA is not available")
    if world == 1:
        return rank, world, want
    import torch.distributed as dist

    os.environ.setdefault("MASTER_ADDR", "127.0.0.1")
    if want.type == "cuda":
        want = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
        torch.cuda.set_device(want)
    elif sys.platform.startswith("linux"):
        os.environ.setdefault("GLOO_SOCKET_IFNAME", "lo")  # gloo talks over loopback only
    dist.init_process_group("nccl" if want.type == "cuda" else "gloo", init_method=init_method, rank=rank,
                            world_size=world)
    return rank, world, want


def train(args) -> dict:
    """Run one training; returns {"method": the trained method, "result": fit's result, "out": DIR}."""
    from baselines.protocol import resolve_method

    if args.threads > 0:
        torch.set_num_threads(args.threads)
    out = Path(args.out)
    rank, world, device = setup_distributed(args.init_method, args.device)
    try:
        if rank == 0:
            out.mkdir(parents=True, exist_ok=True)
        ckpt = out / "model.pt"
        if args.restart and rank == 0 and ckpt.exists():
            ckpt.unlink()
        if world > 1:
            import torch.distributed as dist

            dist.barrier()
        opts = method_options(args)
        method = resolve_method(args.method, device=device, checkpoint=str(ckpt), **opts)
        accepted = getattr(method, "options", None)
        if accepted is not None:
            unknown = sorted(set(opts) - set(accepted))
            if unknown:
                raise ValueError(f"--method {args.method}: unknown option(s) {unknown}; it takes {sorted(accepted)}")
        train_set = open_split(args.data, "train", args.guides)
        if train_set is None:
            raise ValueError(f"{args.data}: no sequence in the train split")
        valid_set = open_split(args.data, "valid", args.guides)
        guides = train_set[0]["guide_index"]
        method.fit(train_set, guides, valid=valid_set)
        result = getattr(method, "result", None) or {}
        if rank == 0:
            history = result.get("history", getattr(method, "history", None))
            (out / "history.json").write_text(json.dumps(history))
            summary = {"method": args.method, "data": str(args.data), "guides": args.guides, "device": str(device),
                       "world_size": world, "options": getattr(method, "options", opts),
                       **{k: result.get(k) for k in ("best_valid", "best_step", "stopped", "steps")}}
            (out / "summary.json").write_text(json.dumps(summary, indent=1, default=str))
        return {"method": method, "result": result, "out": str(out)}
    finally:
        if world > 1:
            import torch.distributed as dist

            dist.destroy_process_group()


def main(argv=None) -> dict:
    return train(parse_args(argv))


if __name__ == "__main__":
    main()
