"""Dataset generation: simulate a recipe's sequences into sharded HDF5 files, resumably.

The job list of a recipe (:mod:`ams_torch.apps.recipe`) is its batch groups: group g simulates
sequences g·batch … (g+1)·batch − 1 as one batched run (one groom, B head motions). Shard i of
n takes the groups with g % n == i, so every sharding simulates the same groups the same way
and any shard on any machine produces the same data.

Crash safety. Each finished group is first written to its own file under
``OUT/.partial/<shard>/group-<g>.h5`` (written to a temporary name, renamed when complete);
when every group of the shard is there, they are copied into ``OUT/<name>-shard-<i>-of-<n>.h5``
(again temporary name, then rename) and the work folder is removed. A run that is killed keeps
its finished groups; the next run deletes any temporary file, skips the finished groups and
simulates the rest. Nothing partial is ever renamed into place.

Backends: :func:`generate` (this process, one or several shards one after the other) and
:func:`generate_ray` (shards as Ray tasks, one GPU each where the cluster has GPUs).
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
from typing import Callable, Dict, List, Optional, Sequence

import numpy as np
import torch

from ams_torch import __version__
from ams_torch.apps.data import FORMAT, FORMAT_VERSION, POSE_FIELDS, array_digest, sequence_checksum, sequence_name
from ams_torch.apps.recipe import Recipe, RecipeError

__all__ = ["shard_filename", "simulate_group", "generate_shard", "generate", "generate_ray", "start_local_ray",
           "parse_shard"]

_DTYPES = {"float32": torch.float32, "float64": torch.float64}


def shard_filename(recipe: Recipe, shard: int, num_shards: int) -> str:
    """``<name>-shard-00000-of-00004.h5``."""
    return f"{recipe.name}-shard-{shard:05d}-of-{num_shards:05d}.h5"


def parse_shard(text: str) -> tuple:
    """``"i/n"`` → (i, n), with a clear error."""
    try:
        i, n = (int(p) for p in str(text).split("/"))
    except ValueError:
        raise ValueError(f"--shard must look like i/n (e.g. 0/4); got {text!r}") from None
    if not (n >= 1 and 0 <= i < n):
        raise ValueError(f"--shard i/n needs 0 <= i < n; got {text!r}")
    return i, n


def _batched_wind(winds: Sequence, sim) -> Optional[Callable]:
    """One external-force callable for a scene batch whose sequences have their own wind (or none)."""
    if all(w is None or w.is_zero for w in winds):
        return None
    forces = [None if (w is None or w.is_zero) else w.bind(sim) for w in winds]

    def force(x: torch.Tensor, v: torch.Tensor, t: float) -> torch.Tensor:
        return torch.stack([torch.zeros_like(x[b]) if f is None else f(x[b], v[b], t) for b, f in enumerate(forces)])

    return force


def simulate_group(recipe: Recipe, group: int, device=None, on_frame: Optional[Callable] = None,
                   on_start: Optional[Callable] = None) -> dict:
    """Simulate batch group ``group`` of a recipe as one batched run.

    ``on_start(run, specs)`` is called once the simulator is built (run: the
    :class:`~ams_torch.apps.scene.BuiltScene`; specs: the B sequence specs). ``on_frame(k, state)`` is
    called after each frame k (state.x, state.v: (B, S, N, 3) m, m/s, world; state.pose: the B
    head poses). Returns ``{"run": BuiltScene, "specs": [sequence specs],
    "group": group spec, "ms_per_frame": float}``.
    """
    from ams_torch.apps.motion import make_motion
    from ams_torch.geometry.pose import Pose
    from ams_torch.apps.scene import build
    from ams_torch.stages.wind import Wind

    dtype = _DTYPES[recipe.dtype_name]
    device = torch.device(device) if device is not None else torch.device("cpu")
    scene = recipe.group_scene(group)
    run = build(scene, device=device, dtype=dtype)
    sim = run.sim
    specs = [recipe.sequence_spec(i) for i in recipe.group_sequences(group)]
    if on_start is not None:
        on_start(run, specs)
    motions = [make_motion(s["motion"]) for s in specs]
    winds = [Wind(**s["wind"]) if s["wind"] is not None else None for s in specs]
    poses_at = lambda t: Pose.stack([m(t, device=device, dtype=dtype) for m in motions])  # noqa: E731
    state = sim.initial_state(poses_at(0.0))
    force = _batched_wind(winds, sim)
    dt = sim.params.dt
    moving = any(m is not None for m in run.collider_motions)
    t0 = time.perf_counter()
    for k in range(recipe.frames):
        t = (k + 1) * dt
        cposes = [None if m is None else m(t, device=device, dtype=dtype) for m in run.collider_motions] \
            if moving else None
        state = sim.step(state, poses_at(t), external_force=force, collider_poses=cposes)
        if on_frame is not None:
            on_frame(k, state)
    ms = 1e3 * (time.perf_counter() - t0) / recipe.frames
    return {"run": run, "specs": specs, "group": recipe.group_spec(group), "ms_per_frame": ms}


class _SequenceWriter:
    """Writes one sequence group incrementally (frame by frame) and its checksums."""

    def __init__(self, h5, recipe: Recipe, spec: dict, strands: int, particles: int, guide_idx):
        st = recipe.store
        self.g = h5.create_group(sequence_name(spec["index"]))
        self.frames = recipe.frames
        self.prec = np.float16 if st["precision"] == "float16" else np.float32
        self.guides = guide_idx
        self.digests: Dict[str, tuple] = {}
        self.hashers: Dict[str, object] = {}
        filters = {} if st["compression"] == "none" else {
            "compression": st["compression"], "shuffle": True,
            **({"compression_opts": st["compression_level"]} if st["compression"] == "gzip" else {})}
        self.framed = {}
        if st["positions"]:
            self.framed["positions"] = (strands, particles, 3)
        if st["velocities"]:
            self.framed["velocities"] = (strands, particles, 3)
        if guide_idx is not None:
            self.framed["guide_positions"] = (len(guide_idx), particles, 3)
        for name, shape in self.framed.items():
            self.g.create_dataset(name, shape=(self.frames,) + shape, dtype=self.prec, chunks=(1,) + shape,
                                  fletcher32=True, **filters)
            self.hashers[name] = hashlib.sha256()
        self.poses = {k: np.zeros((self.frames, 3, 3) if k == "rotations" else (self.frames, 3), np.float32)
                      for k in POSE_FIELDS} if st["poses"] else {}

    def frame(self, k: int, x: np.ndarray, v: Optional[np.ndarray], pose: Dict[str, np.ndarray]) -> None:
        """x, v: (S, N, 3) float32 (m, m/s); pose: rotation (3, 3), translation (3,), velocities (3,)."""
        arrays = {"positions": x, "velocities": v, "guide_positions": None if self.guides is None else x[self.guides]}
        for name in self.framed:
            a = np.ascontiguousarray(arrays[name].astype(self.prec))
            self.g[name][k] = a
            self.hashers[name].update(a.tobytes())
        for name, buf in self.poses.items():
            buf[k] = pose[name]

    def static(self, name: str, array: np.ndarray) -> None:
        a = np.ascontiguousarray(array)
        self.g.create_dataset(name, data=a)
        self.digests[name] = (a.dtype.str, a.shape, array_digest([a]))
        self.g[name].attrs["sha256"] = self.digests[name][2]

    def finish(self, attrs: dict) -> None:
        for name, buf in self.poses.items():
            self.static(name, buf)
        for name, h in self.hashers.items():
            d = self.g[name]
            self.digests[name] = (d.dtype.str, d.shape, h.hexdigest())
            d.attrs["sha256"] = h.hexdigest()
        for k, val in attrs.items():
            self.g.attrs[k] = val
        self.g.attrs["checksum"] = sequence_checksum(self.digests)


def _json(v) -> str:
    return json.dumps(v, sort_keys=True, default=str)


def _write_group(recipe: Recipe, group: int, path: str, device=None) -> float:
    """Simulate batch group ``group`` and write its sequences to ``path`` atomically. Returns ms/frame."""
    tmp = f"{path}.tmp{os.getpid()}"
    try:
        ms = _write_group_file(recipe, group, tmp, device)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise
    os.replace(tmp, path)
    return ms


def _write_group_file(recipe: Recipe, group: int, tmp: str, device=None) -> float:
    import h5py

    from ams_torch.grooms.groom import fps_order

    writers: List[_SequenceWriter] = []
    guides = recipe.store["guides"]
    keep_v = recipe.store["velocities"]
    with h5py.File(tmp, "w") as h5:
        def on_start(run, specs):
            rest = run.sim.model.rest_positions
            gidx = fps_order(rest[:, 0].cpu(), guides).numpy() if guides else None
            writers.extend(_SequenceWriter(h5, recipe, spec, rest.shape[0], rest.shape[1], gidx) for spec in specs)

        def on_frame(k, state):
            x = state.x.detach().to("cpu", torch.float32).numpy()
            v = state.v.detach().to("cpu", torch.float32).numpy() if keep_v else None
            p = state.pose
            pose = {"rotations": p.rotation, "translations": p.translation, "linear_velocities": p.linear_velocity,
                    "angular_velocities": p.angular_velocity}
            pose = {n: t.detach().to("cpu", torch.float32).numpy() for n, t in pose.items()}
            for b, w in enumerate(writers):
                w.frame(k, x[b], None if v is None else v[b], {n: a[b] for n, a in pose.items()})

        out = simulate_group(recipe, group, device=device, on_frame=on_frame, on_start=on_start)
        run = out["run"]
        rest = run.sim.model.rest_positions.detach().cpu().float().numpy()
        groom = run.groom
        for w, spec in zip(writers, out["specs"]):
            w.static("rest_positions", rest)
            if groom is not None and groom.root_triangles is not None:
                w.static("root_triangles", groom.root_triangles.numpy().astype(np.int64))
                w.static("root_barycentrics", groom.root_barycentrics.numpy().astype(np.float32))
            if w.guides is not None:
                w.static("guide_indices", np.asarray(w.guides, dtype=np.int64))
            w.finish({"index": spec["index"], "group": group, "seed": spec["seed"], "frames": recipe.frames,
                      "dt": float(run.sim.params.dt), "strands": rest.shape[0], "particles": rest.shape[1],
                      "motion": _json(spec["motion"]), "wind": _json(spec["wind"]),
                      "groom": _json(out["group"]["groom"]), "params": _json(run.sim.params.to_dict()),
                      "scene": _json(run.scene), "library_version": __version__,
                      "units": "metres, seconds; world frame, +y up"})
        h5.attrs["recipe_hash"] = recipe.hash
        h5.attrs["group"] = group
        h5.attrs["complete"] = True
    return out["ms_per_frame"]


def _group_done(path: str, recipe: Recipe) -> bool:
    import h5py

    try:
        with h5py.File(path, "r") as f:
            if f.attrs.get("recipe_hash") != recipe.hash:
                raise RecipeError(f"{path} was written by a different recipe (hash {f.attrs.get('recipe_hash')}); "
                                  f"use a fresh --out folder")
            return bool(f.attrs.get("complete", False))
    except OSError:
        return False


def generate_shard(recipe: Recipe, out: str, shard: int = 0, num_shards: int = 1, device=None,
                   progress: bool = True, log: Callable[[str], None] = print) -> str:
    """Generate shard ``shard`` of ``num_shards`` into folder ``out`` (resuming a killed run).

    Returns the path of the shard file. An existing complete shard file of the same recipe is
    kept as it is; one of another recipe raises :class:`RecipeError`."""
    import h5py

    groups = recipe.shard_groups(shard, num_shards)
    os.makedirs(out, exist_ok=True)
    final = os.path.join(out, shard_filename(recipe, shard, num_shards))
    if os.path.exists(final):
        with h5py.File(final, "r") as f:
            if f.attrs.get("recipe_hash") != recipe.hash:
                raise RecipeError(f"{final} exists and was written by a different recipe; use a fresh --out folder")
        log(f"{final}: already complete")
        return final
    for name in os.listdir(out):  # an assembly that was cut short
        if name.startswith(os.path.basename(final) + ".tmp"):
            os.remove(os.path.join(out, name))
    work = os.path.join(out, ".partial", os.path.splitext(os.path.basename(final))[0])
    os.makedirs(work, exist_ok=True)
    for name in os.listdir(work):
        if ".tmp" in name:  # a write that was cut short: never kept
            os.remove(os.path.join(work, name))
    path_of = lambda g: os.path.join(work, f"group-{g:06d}.h5")  # noqa: E731
    done = [g for g in groups if os.path.exists(path_of(g)) and _group_done(path_of(g), recipe)]
    total = sum(len(recipe.group_sequences(g)) for g in groups)
    if done:
        log(f"resuming {os.path.basename(final)}: {len(done)} of {len(groups)} batch groups already done")
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=total, initial=sum(len(recipe.group_sequences(g)) for g in done), unit="seq",
                   desc=f"{recipe.name} shard {shard}/{num_shards}")
    try:
        for g in groups:
            if g in done:
                continue
            ms = _write_group(recipe, g, path_of(g), device)
            if bar is not None:
                bar.set_postfix_str(f"{ms:.0f} ms/frame for {len(recipe.group_sequences(g))} seq")
                bar.update(len(recipe.group_sequences(g)))
    finally:
        if bar is not None:
            bar.close()
    _assemble(recipe, [path_of(g) for g in groups], final, shard, num_shards)
    shutil.rmtree(work)
    try:
        os.rmdir(os.path.join(out, ".partial"))
    except OSError:
        pass  # other shards are still in progress there
    return final


def _assemble(recipe: Recipe, parts: List[str], final: str, shard: int, num_shards: int) -> None:
    """Copy the finished groups into the shard file (temporary name, then rename)."""
    tmp = f"{final}.tmp{os.getpid()}"
    try:
        _copy_groups(recipe, parts, tmp, shard, num_shards)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise
    os.replace(tmp, final)


def _copy_groups(recipe: Recipe, parts: List[str], tmp: str, shard: int, num_shards: int) -> None:
    import h5py

    indices = []
    with h5py.File(tmp, "w") as dst:
        for p in parts:
            with h5py.File(p, "r") as src:
                for name in sorted(k for k in src.keys() if k.startswith("seq_")):
                    src.copy(src[name], dst, name=name)
                    indices.append(int(src[name].attrs["index"]))
        a = dst.attrs
        a["format"] = FORMAT
        a["format_version"] = FORMAT_VERSION
        a["library_version"] = __version__
        a["torch_version"] = str(torch.__version__)
        a["recipe_name"] = recipe.name
        a["recipe"] = recipe.to_json()
        a["recipe_hash"] = recipe.hash
        a["store"] = _json(recipe.store)
        a["shard"] = shard
        a["num_shards"] = num_shards
        a["num_sequences"] = recipe.num_sequences
        a["batch"] = recipe.batch
        a["frames"] = recipe.frames
        a["sequences"] = np.asarray(sorted(indices), dtype=np.int64)


def generate(recipe: Recipe, out: str, shards: Optional[Sequence[int]] = None, num_shards: int = 1, device=None,
             progress: bool = True, log: Callable[[str], None] = print) -> List[str]:
    """Generate shards ``shards`` (default: all) of ``num_shards`` in this process, one after
    the other. Returns the shard file paths."""
    shards = list(range(num_shards)) if shards is None else list(shards)
    return [generate_shard(recipe, out, i, num_shards, device=device, progress=progress, log=log) for i in shards]


def _ray_shard(recipe: Recipe, out: str, shard: int, num_shards: int, device: str) -> str:
    torch.set_num_threads(max(1, int(os.environ.get("OMP_NUM_THREADS", "1"))))
    return generate_shard(recipe, out, shard, num_shards, device=device, progress=False, log=lambda s: None)


def _import_ray():
    try:
        import ray
    except ImportError:
        raise RuntimeError("the Ray backend needs Ray: pip install 'ams_torch[ray]'") from None
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


def generate_ray(recipe: Recipe, out: str, num_shards: int, address: Optional[str] = None, device: Optional[str] = None,
                 cpus_per_task: float = 1.0, progress: bool = True, log: Callable[[str], None] = print) -> List[str]:
    """Generate every shard of ``num_shards`` as Ray tasks (one GPU each when the cluster has
    GPUs and ``device`` is not ``"cpu"``). ``out`` must be a folder every node can write.

    With ``address=None`` a private local cluster is started bound to 127.0.0.1 only (no
    dashboard, no usage reporting) and shut down afterwards; otherwise ``ray.init(address)``
    joins an existing cluster (e.g. ``"auto"``)."""
    ray = _import_ray()
    started = False
    if not ray.is_initialized():
        if address is None:
            start_local_ray(num_cpus=max(1, int(cpus_per_task * num_shards)))
        else:
            os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
            ray.init(address=address, configure_logging=False, log_to_driver=False)
        started = True
    try:
        gpus = float(ray.cluster_resources().get("GPU", 0))
        use_gpu = gpus >= 1 and device != "cpu"
        task = ray.remote(num_cpus=cpus_per_task, num_gpus=1 if use_gpu else 0, max_retries=2)(_ray_shard)
        os.makedirs(out, exist_ok=True)
        refs = {task.remote(recipe, os.path.abspath(out), i, num_shards, "cuda" if use_gpu else "cpu"): i
                for i in range(num_shards)}
        log(f"ray: {num_shards} shard task(s) on {'GPUs' if use_gpu else 'CPUs'} "
            f"({ray.cluster_resources().get('CPU', 0):.0f} CPUs, {gpus:.0f} GPUs in the cluster)")
        bar = None
        if progress:
            from tqdm.auto import tqdm

            bar = tqdm(total=num_shards, unit="shard", desc=f"{recipe.name} (ray)")
        paths: Dict[int, str] = {}
        pending = list(refs)
        while pending:
            ready, pending = ray.wait(pending, num_returns=1)
            for r in ready:
                paths[refs[r]] = ray.get(r)
                if bar is not None:
                    bar.update(1)
        if bar is not None:
            bar.close()
        return [paths[i] for i in range(num_shards)]
    finally:
        if started:
            ray.shutdown()
