"""The Ray backend: one task per batch group, progress in batch groups, clean interruption."""
from __future__ import annotations

import contextlib
import os
from typing import Callable, List, Optional

import torch

from ams_torch.apps.datagen.shards import (check_output, check_sharding, finish_shard, log_plan, output_lock,
                                           prepare_shard)
from ams_torch.apps.datagen.writer import write_group
from ams_torch.apps.recipe import Recipe

__all__ = ["generate_ray", "start_local_ray"]


# -- Ray: one task per batch group --------------------------------------------------------------
def _ray_group(recipe: Recipe, path: str, group: int, device: str) -> float:
    torch.set_num_threads(max(1, int(os.environ.get("OMP_NUM_THREADS", "1"))))
    return write_group(recipe, group, path, device)


def _import_ray():
    try:
        import ray
    except ImportError:
        raise ImportError("the Ray backend needs Ray: pip install 'ams_torch[ray]'") from None
    return ray


def start_local_ray(num_cpus: int = 1, num_gpus: Optional[int] = None):
    """Start a private single-node Ray cluster on this machine, bound to loopback only: node
    address 127.0.0.1 (every Ray server listens there; Ray is told not to swap it for the
    machine's routable address), no dashboard, no usage reporting. Stop it with ``ray.shutdown()``."""
    os.environ["RAY_USAGE_STATS_ENABLED"] = "0"
    os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"  # read when ray is first imported
    ray = _import_ray()
    try:  # ray imported before this call: the constant was read already
        from ray._private import ray_constants

        ray_constants.ENABLE_RAY_CLUSTER = False
    except (ImportError, AttributeError):
        pass
    ray.init(_node_ip_address="127.0.0.1", include_dashboard=False, configure_logging=False, log_to_driver=False,
             num_cpus=num_cpus, num_gpus=num_gpus)
    node = ray.util.get_node_ip_address()
    if node != "127.0.0.1":
        ray.shutdown()
        raise RuntimeError(f"Ray started on {node}, not on loopback; refusing to run (this Ray version "
                           f"ignores the loopback settings)")
    return ray


def _run_ray(ray, recipe: Recipe, todo: list, total: int, done: int, address, device, cpus_per_task: float,
             progress: bool, log, on_group) -> None:
    """Run one task per (plan, group) of ``todo``; progress counts batch groups. On any exit
    (KeyboardInterrupt included) pending tasks are cancelled and a cluster started here is shut down."""
    started, pending, bar = False, [], None
    try:
        if not ray.is_initialized():
            started = True
            if address is None:
                start_local_ray(num_cpus=max(1, min(len(todo), os.cpu_count() or 1)))
            else:
                os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
                ray.init(address=address, configure_logging=False, log_to_driver=False)
        gpus = float(ray.cluster_resources().get("GPU", 0))
        use_gpu = gpus >= 1 and device != "cpu"
        task = ray.remote(num_cpus=cpus_per_task, num_gpus=1 if use_gpu else 0, max_retries=2)(_ray_group)
        pending = [task.remote(recipe, plan["path_of"](g), g, device or ("cuda" if use_gpu else "cpu"))
                   for plan, g in todo]
        log(f"ray: {len(todo)} batch-group task(s) on {'GPUs' if use_gpu else 'CPUs'} "
            f"({ray.cluster_resources().get('CPU', 0):.0f} CPUs, {gpus:.0f} GPUs in the cluster)")
        if progress:
            from tqdm.auto import tqdm

            bar = tqdm(total=total, initial=done, unit="group", desc=f"{recipe.name} (ray)")
        while pending:
            ready, pending = ray.wait(pending, num_returns=1)
            ray.get(ready[0])
            done += 1
            if bar is not None:
                bar.update(1)
            if on_group is not None:
                on_group(done, total)
    finally:
        for ref in pending:
            with contextlib.suppress(Exception):  # a task that finished meanwhile cannot be cancelled
                ray.cancel(ref, force=True)
        if bar is not None:
            bar.close()
        if started:
            ray.shutdown()


def generate_ray(recipe: Recipe, out: str, num_shards: int, address: Optional[str] = None, device: Optional[str] = None,
                 cpus_per_task: float = 1.0, progress: bool = True, log: Callable[[str], None] = print,
                 wait: bool = False, on_group: Optional[Callable[[int, int], None]] = None) -> List[str]:
    """Generate every shard of ``num_shards`` with one Ray task per batch group (one GPU each
    when the cluster has GPUs and ``device`` is not ``"cpu"``); the driver holds the folder's
    lock, prints ``resuming: K of N batch groups already done`` when resuming, counts finished
    groups (``on_group(done, total)`` after each) and assembles the shard files. ``out`` must be
    a folder every node can write.

    With ``address=None`` a private local cluster is started bound to 127.0.0.1 only (no
    dashboard, no usage reporting) and shut down afterwards, also when the driver is
    interrupted; otherwise ``ray.init(address)`` joins an existing cluster (e.g. ``"auto"``)."""
    check_sharding(recipe, num_shards)
    ray = _import_ray()
    out = os.path.abspath(out)
    with output_lock(out, wait, log):
        check_output(recipe, out, num_shards)
        plans = [prepare_shard(recipe, out, i, num_shards) for i in range(num_shards)]
        todo = [(p, g) for p in plans if not p["complete"] for g in p["groups"] if g not in p["done"]]
        total = sum(len(p["groups"]) for p in plans)
        if len(todo) < total:
            log(f"resuming: {total - len(todo)} of {total} batch groups already done")
        log_plan(recipe, log)
        if todo:
            _run_ray(ray, recipe, todo, total, total - len(todo), address, device, cpus_per_task, progress, log,
                     on_group)
        return [p["final"] if p["complete"] else finish_shard(recipe, p) for p in plans]
