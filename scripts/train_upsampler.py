"""Train the guide upsampler (baselines/upsampler.py) on a dataset: a file of
``baselines.data.generate_dataset`` or an ``ams-torch generate`` dataset (a folder or a shard
file) whose sequences share one groom and whose recipe stores enough guides (``[store] guides``).

    python scripts/train_upsampler.py --data out/baselines/data.h5 --guides 128 --out out/up128.pt
    python scripts/train_upsampler.py --data out/upsampler_tiny --split train --guides 16 --out out/up16.pt
    torchrun --nnodes=1 --nproc_per_node=2 --master_addr=127.0.0.1 --master_port=29512 \
        scripts/train_upsampler.py ...        # DDP: gloo on CPU (loopback only), nccl on GPUs

Samples are (frame, strand) pairs. Their order is a fixed global permutation per epoch (from
``--seed``), cut into global batches of ``--batch``; under DDP each rank takes its contiguous
share of every global batch, so the loss curve does not depend on the world size. The loss is
the mean squared vertex error in mm². Checkpoints are written atomically every
``--checkpoint-every`` steps and at the end; ``--resume`` continues from ``--out``.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from baselines.data import HairDataset  # noqa: E402
from baselines.upsampler import GuideUpsampler, load_checkpoint, save_checkpoint  # noqa: E402


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", required=True, help="HDF5 file of baselines.data.generate_dataset, or an "
                   "`ams-torch generate` dataset (folder or shard file)")
    p.add_argument("--split", choices=("train", "valid", "test"), help="generated datasets: train on this split only")
    p.add_argument("--out", required=True, help="checkpoint path (.pt)")
    p.add_argument("--guides", type=int, default=128, help="number of guides (FPS order of the file)")
    p.add_argument("--k", type=int, default=4, help="guides per dense strand")
    p.add_argument("--hidden", type=int, default=192)
    p.add_argument("--layers", type=int, default=3)
    p.add_argument("--steps", type=int, default=300)
    p.add_argument("--batch", type=int, default=2048, help="global batch, in (frame, strand) samples")
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--sequences", default=None, help="comma-separated sequence names (seq_000003) or, for "
                   "generated datasets, indices (default: all)")
    p.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    p.add_argument("--checkpoint-every", type=int, default=100)
    p.add_argument("--resume", action="store_true", help="continue from --out if it exists")
    p.add_argument("--history", default=None, help="write the per-step loss list here (JSON, rank 0)")
    p.add_argument("--init-method", default="env://", help="torch.distributed init method under DDP")
    p.add_argument("--threads", type=int, default=1,
                   help="torch CPU threads per process (0: torch's default; 1 is fastest on a shared CPU)")
    p.add_argument("--no-progress", action="store_true")
    return p.parse_args(argv)


def batch_items(step: int, batch: int, total: int, seed: int) -> torch.Tensor:
    """Sample indices of global batch ``step``: a stream of per-epoch permutations of range(total)."""
    start = step * batch
    out, pos = [], start
    while pos < start + batch:
        epoch, off = divmod(pos, total)
        perm = torch.randperm(total, generator=torch.Generator().manual_seed(seed * 100003 + epoch))
        take = min(total - off, start + batch - pos)
        out.append(perm[off:off + take])
        pos += take
    return torch.cat(out)


def _setup_distributed(init_method: str):
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    if world == 1:
        return rank, world, torch.device("cpu")
    import torch.distributed as dist

    os.environ.setdefault("MASTER_ADDR", "127.0.0.1")
    cuda = torch.cuda.is_available()
    if not cuda and sys.platform.startswith("linux"):
        os.environ.setdefault("GLOO_SOCKET_IFNAME", "lo")  # gloo talks over loopback only
    backend = "nccl" if cuda else "gloo"
    device = torch.device("cpu")
    if cuda:
        device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
        torch.cuda.set_device(device)
    dist.init_process_group(backend, init_method=init_method, rank=rank, world_size=world)
    return rank, world, device


class _StrandsModule(torch.nn.Module):
    """Makes the upsampler's ``strands_forward`` a module's forward, so DDP can wrap it."""

    def __init__(self, model: GuideUpsampler):
        super().__init__()
        self.model = model

    def forward(self, guides_k, strands, rotation, translation):
        return self.model.strands_forward(guides_k, strands, rotation, translation)


def train(args) -> dict:
    """Run training; returns {"history": [loss per step, mm²], "steps": int, "out": path}."""
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    rank, world, device = _setup_distributed(args.init_method)
    dtype = getattr(torch, args.dtype)
    if args.batch % world:
        raise ValueError(f"--batch {args.batch} must be divisible by the world size {world}")
    seqs = None if args.sequences is None else args.sequences.split(",")
    ds = HairDataset(args.data, sequences=seqs, split=args.split)
    if not 1 <= args.guides <= len(ds.fps_order):
        raise ValueError(f"--guides {args.guides}: the dataset {args.data} offers {len(ds.fps_order)} guide strands "
                         f"(an `ams-torch generate` dataset: its recipe's [store] guides)")
    x, rot, trans = ds.frames()
    x, rot, trans = x.to(device, dtype), rot.to(device, dtype), trans.to(device, dtype)
    nframes, s = x.shape[0], x.shape[1]
    gidx = ds.fps_order[:args.guides]
    guides_all = x[:, gidx.to(device)]  # (T, G, N, 3)

    torch.manual_seed(args.seed)
    start_step, history = 0, []
    if args.resume and os.path.exists(args.out):
        model, blob = load_checkpoint(args.out)
        model = model.to(device, dtype)
        start_step, history = int(blob["step"]), list(blob["history"])
    else:
        model = GuideUpsampler(ds.rest.to(dtype), ds.rest[gidx].to(dtype), k=args.k, hidden=args.hidden,
                               layers=args.layers).to(device, dtype)
        blob = None
    opt = torch.optim.Adam(model.parameters(), lr=args.lr)
    if blob is not None and blob.get("optimizer") is not None:
        opt.load_state_dict(blob["optimizer"])
    net = _StrandsModule(model)
    if world > 1:
        from torch.nn.parallel import DistributedDataParallel as DDP
        net = DDP(net, device_ids=[device.index] if device.type == "cuda" else None)
    gi = model.skin.guide_index
    local = args.batch // world

    bar = range(start_step, args.steps)
    if rank == 0 and not args.no_progress:
        from tqdm.auto import tqdm
        bar = tqdm(bar, desc=f"upsampler G={args.guides}", initial=start_step, total=args.steps)
    for step in bar:
        items = batch_items(step, args.batch, nframes * s, args.seed)[rank * local:(rank + 1) * local].to(device)
        f, strand = items // s, items % s
        gk = guides_all[f[:, None], gi[strand]]  # (B, K, N, 3)
        pred = net(gk, strand, rot[f], trans[f])
        loss = ((pred - x[f, strand]) * 1000.0).square().sum(-1).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        logged = loss.detach().clone()
        if world > 1:
            import torch.distributed as dist
            dist.all_reduce(logged)
            logged /= world
        history.append(float(logged))
        if rank == 0 and hasattr(bar, "set_postfix"):
            bar.set_postfix(loss_mm2=f"{history[-1]:.4g}")
        if rank == 0 and ((step + 1) % args.checkpoint_every == 0 or step + 1 == args.steps):
            save_checkpoint(args.out, model, opt, step=step + 1, history=history, guides=gidx)
    if rank == 0 and args.steps <= start_step:
        save_checkpoint(args.out, model, opt, step=start_step, history=history, guides=gidx)
    if rank == 0 and args.history:
        Path(args.history).write_text(json.dumps(history))
    if world > 1:
        import torch.distributed as dist
        dist.barrier()
        dist.destroy_process_group()
    return {"history": history, "steps": max(args.steps, start_step), "out": args.out, "model": model}


def main(argv=None) -> dict:
    return train(parse_args(argv))


if __name__ == "__main__":
    main()
