"""What interpolation costs next to dense simulation, on one device: ms/frame of the dense run,
of the guides simulated alone, and of each method's prediction, at the dense strand counts the
benchmark names (10k and 100k by default).

The scene is the dataset's own (its first sequence's: head, colliders, hair–hair grid, params,
motion) with the groom regrown at S strands (a preset groom keeps its preset; a file groom is
replaced by the ``straight`` preset, said in the row). Timings are wall clock after one warm-up
frame, device synchronised, over ``frames`` frames.
"""
from __future__ import annotations

import copy
import json
import time
from pathlib import Path
from typing import Callable, Dict, List, Optional, Sequence

import torch

from baselines.protocol import check_prediction, resolve_method, safe_name

__all__ = ["measure", "guide_simulator"]


def guide_simulator(sim, index: torch.Tensor):
    """A simulator of the strands ``index`` of ``sim`` alone: the same params, stages, colliders,
    device and dtype (what a pipeline that simulates only guides runs)."""
    from ams_torch import Simulator

    rest = sim.model.rest_positions[index.to(sim.device)]
    return Simulator(rest, sim.params, device=sim.device, dtype=sim.dtype, pose=sim.initial_pose,
                     hair_hair=sim.hair_hair, colliders=sim.colliders or None)


def _scene(dataset: Path, strands: int) -> tuple:
    from ams_torch.apps.data.format import list_files, open_dataset

    with open_dataset(list_files(str(dataset))[0]) as f:
        g = f[next(k for k in f.keys() if k.startswith("seq_"))]
        scene = json.loads(g.attrs["scene"])
    scene = copy.deepcopy(scene)
    note = ""
    groom = scene["groom"]
    if "preset" not in groom:
        note = f"groom {groom.get('file', groom.get('kind'))!r} replaced by the straight preset"
        scene["groom"] = {"preset": "straight", "particles": groom.get("particles") or 32, "seed": 0,
                          "compare_ms": False, "compare_offset": groom.get("compare_offset", [0, 0, 0])}
    scene["groom"]["strands"] = int(strands)
    scene["scale"] = 1.0
    return scene, note


def _run(sim, run, frames: int, device) -> tuple:
    """Simulate frames + 1 frames; returns (ms per frame over the last ``frames``, states' x, head poses)."""
    sync = (lambda: torch.cuda.synchronize(device)) if torch.device(device).type == "cuda" else (lambda: None)  # noqa: E731
    state = sim.initial_state()
    dt = sim.params.dt
    xs, poses = [], []
    t0 = 0.0
    for k in range(frames + 1):
        if k == 1:
            sync()
            t0 = time.perf_counter()
        t = (k + 1) * dt
        cposes = [None if m is None else m(t, device=sim.device, dtype=sim.dtype) for m in run.collider_motions] \
            if any(m is not None for m in run.collider_motions) else None
        state = sim.step(state, run.motion(t, device=sim.device, dtype=sim.dtype), collider_poses=cposes)
        xs.append(state.x)
        poses.append((state.pose, cposes))
    sync()
    return (time.perf_counter() - t0) * 1e3 / frames, xs[1:], poses[1:]


def _sample(sim, guide_sim, index, xs, poses, dt) -> dict:
    from ams_torch.geometry.pose import Pose
    from ams_torch.stages.collide import resolve_world_poses

    cols = sim.colliders
    world = [resolve_world_poses(cols, p, c) for p, c in poses]
    head = next((i for i, c in enumerate(cols) if getattr(c, "follow_head", False)), -1)
    return {"guide_positions": torch.stack(xs), "rotations": torch.stack([p.rotation for p, _ in poses]),
            "translations": torch.stack([p.translation for p, _ in poses]),
            "rest_positions": sim.model.rest_positions, "guide_index": index.to(sim.device),
            "num_pinned": sim.model.num_pinned, "colliders": cols, "head_collider": head,
            "collider_poses": [Pose(torch.stack([w[i].rotation for w in world]),
                                    torch.stack([w[i].translation for w in world]), check=False)
                               for i in range(len(cols))],
            "dt": dt, "sequence": -1, "start": 0}


def _method_ms(spec: str, sample: dict, device, options: dict, checkpoint: Optional[Path]) -> tuple:
    """(ms per frame, None) or (None, why not) of ``spec``'s prediction on ``sample``."""
    sync = (lambda: torch.cuda.synchronize(device)) if torch.device(device).type == "cuda" else (lambda: None)  # noqa: E731
    context = {"device": torch.device(device)}
    if checkpoint is not None and checkpoint.exists():
        context["checkpoint"] = str(checkpoint)
    try:
        method = resolve_method(spec, context, **options)  # a learned method loads its checkpoint
        with torch.no_grad():
            method.predict(sample)  # warm-up (bindings, caches)
            sync()
            t0 = time.perf_counter()
            out = method.predict(sample)
            sync()
        check_prediction(spec, out, sample)
    except Exception as err:  # noqa: BLE001 - a method that cannot run on another groom is reported, not fatal
        return None, f"{type(err).__name__}: {' '.join(str(err).split())[:200]}"
    return (time.perf_counter() - t0) * 1e3 / sample["guide_positions"].shape[0], None


def measure(dataset: Path, methods: Sequence[str], guides: Sequence[int], sizes: Sequence[int], *, device="cpu",
            frames: int = 3, options: Optional[Dict[str, dict]] = None, log: Callable[[str], None] = print,
            models: Optional[Path] = None) -> List[dict]:
    """Rows ``{"strands", "guides", "method", "dense_ms", "guides_ms", "method_ms", "total_ms",
    "speedup", "note"}`` (ms per frame; speedup = dense / (guides + method); ``method_ms`` None with
    the reason in ``note`` when the method cannot predict this groom, e.g. it is trained on one
    groom's rest shape)."""
    from ams_torch.apps.scene import build
    from ams_torch.grooms.groom import fps_order

    options = options or {}
    rows = []
    for s in sizes:
        scene, note = _scene(dataset, s)
        run = build(scene, device=device)
        sim = run.sim
        dense_ms, _, _ = _run(sim, run, frames, device)
        log(f"cost: dense {s} strands: {dense_ms:.1f} ms/frame")
        roots = sim.model.rest_positions[:, 0].detach().cpu()
        for g in guides:
            index = fps_order(roots, int(g))
            gsim = guide_simulator(sim, index)
            guides_ms, xs, poses = _run(gsim, run, frames, device)
            sample = _sample(sim, gsim, index, xs, poses, sim.params.dt)
            for spec in methods:
                # a learned method's trained models (one per dataset): the first that applies to this
                # groom (its particles per strand), timing being what is measured here
                found = sorted(models.glob(f"*/{safe_name(spec)}-G{g}.pt")) if models is not None else []
                for ckpt in found or [None]:
                    ms, why = _method_ms(spec, sample, device, options.get(spec, {}), ckpt)
                    if ms is not None or not (why or "").startswith("NotApplicable"):
                        break
                total = None if ms is None else guides_ms + ms
                rows.append({"strands": int(s), "particles": int(sim.model.num_particles), "guides": int(g),
                             "method": spec, "dense_ms": dense_ms, "guides_ms": guides_ms, "method_ms": ms,
                             "total_ms": total, "speedup": None if total is None else dense_ms / total,
                             "device": str(device), "frames": frames,
                             "note": "; ".join(x for x in (note, why) if x)})
                log(f"cost: S={s} G={g} {spec}: guides {guides_ms:.1f} + method "
                    f"{'n/a' if ms is None else f'{ms:.1f}'} ms/frame")
            del gsim
        del run, sim
    return rows
