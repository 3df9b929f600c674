"""Simulating one batch group of a recipe (one batched run), and saying which input was not finite."""
from __future__ import annotations

import time
from typing import Callable, Optional, Sequence

import numpy as np
import torch

from ams_torch.apps.recipe import Recipe

__all__ = ["simulate_group", "nonfinite_inputs", "guide_order", "guide_simulators"]

_DTYPES = {"float32": torch.float32, "float64": torch.float64}


# -- inputs that were never finite ------------------------------------------------------------
def nonfinite_inputs(rest, motions: Sequence[tuple], frames: int, dt: float, winds=(), params=None) -> Optional[str]:
    """Which simulation input holds NaN/Inf, or None: rest (S, N, 3) m, ``motions`` as
    (label, motion) evaluated at t = 0, dt, …, frames·dt s, Wind objects (or None), Params."""
    r = np.asarray(rest.detach().cpu() if hasattr(rest, "detach") else rest, dtype=np.float64)
    if not np.isfinite(r).all():
        return f"the groom's rest positions hold NaN/Inf (strand {int(np.flatnonzero(~np.isfinite(r).all((1, 2)))[0])})"
    for label, m in motions:
        if m is None:
            continue
        for k in range(frames + 1):
            try:
                p = m(k * dt, dtype=torch.float64)
            except ValueError as err:  # a Pose refuses NaN/Inf
                return f"{label}: the pose at t = {k * dt:.4g} s (frame {k}) holds NaN/Inf ({err})"
            if not all(bool(torch.isfinite(t).all()) for t in (p.rotation, p.translation, p.linear_velocity,
                                                              p.angular_velocity)):
                return f"{label}: the pose at t = {k * dt:.4g} s (frame {k}) holds NaN/Inf"
    for w in winds:
        if w is not None:
            bad = [k for k, v in vars(w).items() if isinstance(v, (int, float)) and not np.isfinite(v)]
            if bad or not np.isfinite(w.direction).all():
                return f"the wind is not finite ({', '.join(bad) or 'direction'})"
    if params is not None:
        bad = [k for k, v in params.to_dict().items() if isinstance(v, float) and not np.isfinite(v)]
        if bad:
            return f"[params] {', '.join(bad)} not finite"
    return None


def _diverged(err, what: str, bad: Optional[str]):
    """A SimulationDiverged that says where, and says when the input itself was not finite."""
    from ams_torch import SimulationDiverged

    frame = getattr(err, "frame", None)
    if bad:
        msg = (f"{what}: the scene input is not finite: {bad}; the simulation stopped"
               f"{'' if frame is None else f' at frame {frame}'}. This is not a stability problem (more substeps "
               f"will not help): fix the input")
    else:
        msg = f"{what}: {err}"
    out = SimulationDiverged(msg, frame=frame, strands=getattr(err, "strands", []))
    out.bad_input = bool(bad) or bool(getattr(err, "bad_input", False))
    return out


# -- guides simulated alone -------------------------------------------------------------------
def guide_order(run, count: int) -> np.ndarray:
    """(count,) int64: the farthest-point order of the simulated groom's roots
    (:func:`ams_torch.grooms.groom.fps_order`); its first G entries are the G-guide choice."""
    from ams_torch.grooms.groom import fps_order

    return fps_order(run.sim.model.rest_positions[:, 0].detach().cpu(), count).numpy().astype(np.int64)


def guide_simulators(run, order: np.ndarray, counts: Sequence[int]) -> dict:
    """``{G: Simulator}``: for each guide count G, a simulator of the strands ``order[:G]`` alone,
    with everything else of the dense run: params, dtype, device, backend, hair–hair settings
    (its grid fitted to the guides) and colliders (copies). The guides' rest shape, masses,
    stiffnesses and pinned counts are the dense groom's for the same strands (all per strand)."""
    from ams_torch.sim.simulator import Simulator

    sim = run.sim
    if any(isinstance(v, torch.Tensor) for v in vars(sim.params).values()):
        raise ValueError("guides simulated alone need scalar Params fields (a per-strand tensor would have to be "
                         "subset too)")
    rest = np.asarray(run.rest)
    return {int(g): Simulator(rest[order[:g]], sim.params, device=sim.device, dtype=sim.dtype, pose=sim.initial_pose,
                              hair_hair=sim.hair_hair, colliders=list(sim.model.colliders),
                              backend=sim.requested_backend)
            for g in counts}


# -- simulation of one batch group ------------------------------------------------------------
def _batched_wind(winds: Sequence, sim) -> Optional[Callable]:
    """One external-force callable for a scene batch whose sequences have their own wind (or none)."""
    if all(w is None or w.is_zero for w in winds):
        return None
    forces = [None if (w is None or w.is_zero) else w.bind(sim) for w in winds]

    def force(x: torch.Tensor, v: torch.Tensor, t: float) -> torch.Tensor:
        return torch.stack([torch.zeros_like(x[b]) if f is None else f(x[b], v[b], t) for b, f in enumerate(forces)])

    return force


def simulate_group(recipe: Recipe, group: int, device=None, on_frame: Optional[Callable] = None,
                   on_start: Optional[Callable] = None, on_guides: Optional[Callable] = None,
                   on_initial: Optional[Callable] = None) -> dict:
    """Simulate batch group ``group`` of a recipe as one batched run.

    ``on_start(run, specs)`` is called once the simulator is built (run: the
    :class:`~ams_torch.apps.scene.BuiltScene`; specs: the B sequence specs); ``on_initial(state)``
    with the state at t = 0. ``on_frame(k, state)`` is
    called after each frame k (state.x, state.v: (B, S, N, 3) m, m/s, world; state.pose: the B
    head poses). For each count G of ``recipe.alone_counts`` the G first strands of the guide
    order (:func:`guide_order`) are also simulated alone (:func:`guide_simulators`) in the same
    frame loop, under the same head poses, collider poses and wind; ``on_guides(k, {G: state})``
    is called after each frame with their states ((B, G, N, 3)). Returns ``{"run": BuiltScene,
    "specs": [sequence specs], "group": group spec, "ms_per_frame": float, "guide_indices":
    (G_max,) int64 or None, "guides_ms_per_frame": {G: float}}``. A divergence raises
    SimulationDiverged naming the group (and the guide count, for a guides-alone run), and saying
    so when the input itself was not finite.
    """
    from ams_torch.apps.motion import make_motion
    from ams_torch.apps.scene import build
    from ams_torch.geometry.pose import Pose
    from ams_torch import SimulationDiverged
    from ams_torch.stages.wind import Wind

    dtype = _DTYPES[recipe.dtype_name]
    device = torch.device(device) if device is not None else torch.device("cpu")
    run = build(recipe.group_scene(group), device=device, dtype=dtype)
    sim = run.sim
    specs = [recipe.sequence_spec(i) for i in recipe.group_sequences(group)]
    order = guide_order(run, max(recipe.guide_counts)) if recipe.guide_counts else None
    alone = guide_simulators(run, order, recipe.alone_counts) if recipe.alone_counts else {}
    if on_start is not None:
        on_start(run, specs)
    motions = [make_motion(s["motion"]) for s in specs]
    winds = [Wind(**s["wind"]) if s["wind"] is not None else None for s in specs]
    poses_at = lambda t: Pose.stack([m(t, device=device, dtype=dtype) for m in motions])  # noqa: E731
    force = _batched_wind(winds, sim)
    guide_force = {g: _batched_wind(winds, gs) for g, gs in alone.items()}
    dt = sim.params.dt
    moving = any(m is not None for m in run.collider_motions)
    t0 = time.perf_counter()
    guide_s = {g: 0.0 for g in alone}
    what = f"{recipe.where}: batch group {group} (sequences {[s['index'] for s in specs]})"
    try:
        pose0 = poses_at(0.0)
        state = sim.initial_state(pose0)
        guides = {g: gs.initial_state(pose0) for g, gs in alone.items()}
        if on_initial is not None:
            on_initial(state)
        for k in range(recipe.frames):
            t = (k + 1) * dt
            cposes = [None if m is None else m(t, device=device, dtype=dtype) for m in run.collider_motions] \
                if moving else None
            pose = poses_at(t)
            state = sim.step(state, pose, external_force=force, collider_poses=cposes)
            if on_frame is not None:
                on_frame(k, state)
            for g, gs in alone.items():
                what = f"{recipe.where}: batch group {group}, its {g} guides simulated alone"
                tg = time.perf_counter()
                guides[g] = gs.step(guides[g], pose, external_force=guide_force[g], collider_poses=cposes)
                guide_s[g] += time.perf_counter() - tg
            what = f"{recipe.where}: batch group {group} (sequences {[s['index'] for s in specs]})"
            if on_guides is not None and guides:
                on_guides(k, guides)
    except (SimulationDiverged, ValueError) as err:  # a NaN input: diverged, or refused by the step
        labelled = [(f"[motion] of sequence {s['index']}", m) for s, m in zip(specs, motions)]
        labelled += [(f"[colliders[{i}].motion]", m) for i, m in enumerate(run.collider_motions)]
        bad = nonfinite_inputs(run.rest, labelled, recipe.frames, dt, winds, sim.params)
        if isinstance(err, ValueError) and not bad:
            raise
        raise _diverged(err, what, bad) from None
    ms = 1e3 * (time.perf_counter() - t0) / recipe.frames
    return {"run": run, "specs": specs, "group": recipe.group_spec(group), "ms_per_frame": ms,
            "guide_indices": order, "guides_ms_per_frame": {g: 1e3 * v / recipe.frames for g, v in guide_s.items()}}
