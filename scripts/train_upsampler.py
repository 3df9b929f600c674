"""Deprecated: use ``scripts/train_interp.py --method upsampler``. Kept as a thin alias for
``scripts/evaluate_baselines.py`` and the files of ``baselines.data.generate_dataset``: it trains
the ``upsampler`` method (its own ``fit``: validation on held-out sequences, plateau schedule,
early stopping) on what :class:`baselines.data.HairDataset` reads (such a file, or a one-groom
``ams-torch generate`` dataset), with the dense run's guide copies (the first ``--guides`` of the
file's guide order) as the guide input and 2 pinned particles per strand.

    python scripts/train_upsampler.py --data out/baselines/data.h5 --guides 128 --out out/up128.pt
    torchrun --nnodes=1 --nproc_per_node=2 --master_addr=127.0.0.1 --master_port=29512 \
        scripts/train_upsampler.py ...        # DDP: gloo on CPU (loopback only), nccl on GPUs
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))  # train_interp

from baselines.data import HairDataset  # noqa: E402
from baselines.learned import Upsampler  # noqa: E402


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", required=True, help="HDF5 file of baselines.data.generate_dataset, or a one-groom "
                   "`ams-torch generate` dataset")
    p.add_argument("--split", choices=("train", "valid", "test"), help="generated datasets: train on this split only")
    p.add_argument("--out", required=True, help="checkpoint path (.pt)")
    p.add_argument("--guides", type=int, default=128)
    p.add_argument("--k", type=int, default=4)
    p.add_argument("--hidden", type=int, default=192)
    p.add_argument("--layers", type=int, default=3)
    p.add_argument("--steps", type=int, default=4000, help="most steps (early stopping may end sooner)")
    p.add_argument("--batch", type=int, default=2048, help="(frame, strand) samples per step")
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads (0: torch's default)")
    p.add_argument("--device", default=None, help="cpu (default) or cuda")
    p.add_argument("--init-method", default="env://", help="torch.distributed init method under DDP")
    p.add_argument("--no-progress", action="store_true")
    return p.parse_args(argv)


class LegacyItems(torch.utils.data.Dataset):
    """One-frame benchmark items (see baselines/protocol.py) of a :class:`HairDataset`."""

    def __init__(self, ds: HairDataset, guides: int):
        if not 1 <= guides <= len(ds.fps_order):
            raise ValueError(f"--guides {guides}: the dataset offers {len(ds.fps_order)} guide strands (an "
                             f"`ams-torch generate` dataset: its recipe's [store] guides)")
        self.ds, self.gi = ds, ds.fps_order[:guides].clone()
        self.pinned = torch.full((ds.rest.shape[0],), 2, dtype=torch.long)

    def __len__(self):
        return len(self.ds)

    def item_sequences(self):
        return [q for q, _ in self.ds.items]

    def __getitem__(self, i):
        it = self.ds[i]
        x = it["positions"].float()
        return {"positions": x, "guide_positions": x[:, self.gi], "guide_index": self.gi,
                "rest_positions": self.ds.rest.float(), "num_pinned": self.pinned, "rotations": it["rotation"].float(),
                "translations": it["translation"].float(), "sequence": it["sequence"], "start": it["start"]}


def main(argv=None) -> dict:
    """Train; returns {"history": training loss per step (mm²), "model": the GuideUpsampler,
    "steps", "method"}."""
    from train_interp import setup_distributed

    args = parse_args(argv)
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    _, world, device = setup_distributed(args.init_method, args.device)
    try:
        items = LegacyItems(HairDataset(args.data, split=args.split), args.guides)
        strands = min(128, items.ds.rest.shape[0])
        batch = max(world, args.batch // strands // world * world)
        method = Upsampler(device=device, checkpoint=args.out, k=args.k, hidden=args.hidden, layers=args.layers,
                           steps=args.steps, batch=batch, strands=strands, lr=args.lr, seed=args.seed,
                           progress=not args.no_progress)
        method.fit(items, items.gi)
    finally:
        if world > 1:
            import torch.distributed as dist

            dist.destroy_process_group()
    return {"history": method.history["train"], "model": method.model, "steps": method.result["steps"],
            "method": method}


if __name__ == "__main__":
    main()
