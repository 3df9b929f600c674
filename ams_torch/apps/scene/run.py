"""Running a built scene frame by frame: positions, poses and per-stage timings."""
from __future__ import annotations

import contextlib
import time
from typing import Optional

import numpy as np
import torch

from ams_torch.apps.scene.build import BuiltScene, trim_strands

__all__ = ["simulate"]


def simulate(run: BuiltScene, frames: Optional[int] = None, progress: bool = False, on_frame=None,
             record=None, keep: bool = True) -> dict:
    """Run a built scene. Returns a dict: ``positions`` (F, S, N, 3) float32 numpy (world, m; only
    with ``keep``, else frames go to ``record`` alone and at most one frame is held in memory),
    ``rotations`` (F, 3, 3), ``translations`` (F, 3) m, ``ms_per_frame`` {stage: ms} (``solve``:
    the AMS integration incl. inextensibility; ``hair_hair``, ``collisions``, ``wind``; means over
    frames 2..F when F > 1; ``trim``: its one-off cost), ``first_frame_ms`` (the first frame's
    wall time: it loads the native kernels) and the final ``state``. ``on_frame(k, state)`` is called after each frame;
    ``record(k, arrays)`` with the frame's ``positions`` (S, N, 3) float32, ``rotations``, ``translations``
    (and ``collider_rotations``, ``collider_translations`` with colliders), e.g. to stream them to a file."""

    sim = run.sim
    scene = run.scene
    frames = int(frames or scene["frames"])
    dt = sim.params.dt
    state = sim.initial_state()
    timings = {"solve": 0.0}
    sync = (lambda: torch.cuda.synchronize()) if sim.device.type == "cuda" else (lambda: None)  # noqa: E731
    staged = (["hair_hair"] if sim.hair_hair_grid is not None else []) + (["collisions"] if sim.colliders else [])
    for name in staged:
        timings[name] = 0.0

    @contextlib.contextmanager
    def timer(name):
        """Wall time of one stage of the step (device synchronised), under its profiler label."""
        sync()
        t = time.perf_counter()
        with torch.profiler.record_function(f"ams_torch.{name}"):
            yield
        sync()
        if name in timings:
            timings[name] += time.perf_counter() - t

    wind = None
    if run.wind is not None and not run.wind.is_zero:
        timings["wind"] = 0.0
        raw = run.wind.bind(sim)

        def wind(x, v, t):
            t0 = time.perf_counter()
            out = raw(x, v, t)
            timings["wind"] += time.perf_counter() - t0
            return out

    trim = scene.get("trim")
    xs, rots, trans, crots, ctrans = [], [], [], [], []
    specs = scene["colliders"] if sim.colliders else []
    scene_motions = run.collider_motions[len(run.collider_motions) - len(specs):]
    it = range(frames)
    if progress:
        from tqdm.auto import tqdm

        it = tqdm(it, desc=f"simulating {scene['name']}", unit="frame")
    wall = 0.0
    first_ms, first = 0.0, (0.0, {})
    for k in it:
        if trim is not None and k + 1 == trim["frame"]:
            t0 = time.perf_counter()
            state, sim = _apply_trim(run, state, trim)
            if wind is not None:
                raw = run.wind.bind(sim)
            timings["trim"] = time.perf_counter() - t0
        t_end = (k + 1) * dt
        pose = run.motion(t_end, device=sim.device, dtype=sim.dtype)
        cposes = None
        if any(m is not None for m in run.collider_motions):
            cposes = [None if m is None else m(t_end, device=sim.device, dtype=sim.dtype) for m in run.collider_motions]
        sync()
        t0 = time.perf_counter()
        with torch.profiler.record_function("ams_torch.step"):
            state = sim.step(state, pose, external_force=wind, collider_poses=cposes, timer=timer)
        sync()
        wall += time.perf_counter() - t0
        x = state.x.detach().to("cpu", torch.float32).numpy()
        if keep:
            xs.append(x)
        rots.append(state.pose.rotation.detach().cpu().numpy())
        trans.append(state.pose.translation.detach().cpu().numpy())
        if specs:
            cr, ct = _collider_world_poses(specs, scene_motions, t_end, state.pose)
            crots.append(cr)
            ctrans.append(ct)
        if record is not None:
            record(k, {"positions": x, "rotations": rots[-1], "translations": trans[-1],
                       **({"collider_rotations": crots[-1], "collider_translations": ctrans[-1]} if specs else {})})
        if on_frame is not None:
            on_frame(k, state)
        if k == 0:  # the first frame loads the native kernels and warms caches: reported apart
            first_ms, first = 1e3 * wall, (wall, dict(timings))
    staged = sum(v for k, v in timings.items() if k not in ("solve", "trim"))
    timings["solve"] = wall - staged
    timed = frames
    if frames > 1:  # steady-state means over frames 2..F
        first_staged = sum(v for k, v in first[1].items() if k not in ("solve", "trim"))
        first[1]["solve"] = first[0] - first_staged
        timings = {k: v - (first[1].get(k, 0.0) if k != "trim" else 0.0) for k, v in timings.items()}
        wall, timed = wall - first[0], frames - 1
    ms = {k: 1e3 * v / (timed if k != "trim" else 1) for k, v in timings.items()}
    ms["total"] = 1e3 * wall / timed
    run.sim = sim
    out = {"rotations": np.stack(rots), "translations": np.stack(trans),
           "ms_per_frame": ms, "first_frame_ms": first_ms, "state": state}
    if keep:
        out["positions"] = np.stack(xs)
    if specs:
        out["collider_rotations"], out["collider_translations"] = np.stack(crots), np.stack(ctrans)
    return out


def _collider_world_poses(specs, motions, t: float, head_pose) -> tuple:
    """World rotations (C, 3, 3) and translations (C, 3) m of the scene's colliders at time t
    (their motion's pose, relative to the head when ``follow_head``), for drawing."""
    rots, trans = [], []
    hr = head_pose.rotation.detach().cpu().double().numpy()
    ht = head_pose.translation.detach().cpu().double().numpy()
    for spec, m in zip(specs, motions):
        if m is not None:
            p = m(t, dtype=torch.float64)
            r, tr = p.rotation.numpy(), p.translation.numpy()
        else:
            r, tr = np.eye(3), np.zeros(3)
        if spec.get("follow_head", False):
            r, tr = hr @ r, hr @ tr + ht
        rots.append(r)
        trans.append(tr)
    return np.stack(rots), np.stack(trans)


def _apply_trim(run: BuiltScene, state, trim: dict):
    """Cut the groom by the scene's plane and rebuild the simulator around the shorter strands."""
    from ams_torch.sim.simulator import Simulator

    old = run.sim
    rest, x, v, frac = trim_strands(old.model.rest_positions, state.x, state.v, state.pose,
                                    trim["point"], trim["normal"])
    sim = Simulator(rest, old.params, device=old.device, dtype=old.dtype, pose=state.pose,
                    hair_hair=old.hair_hair, colliders=old.colliders or None)
    new = sim.initial_state(state.pose)
    run.sim = sim
    return new.replace(x=x, v=v, time=state.time, frame=state.frame), sim
