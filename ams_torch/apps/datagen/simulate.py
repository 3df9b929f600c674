"""Simulating one batch group of a recipe (one batched run), and saying which input was not finite."""
from __future__ import annotations

import time
from typing import Callable, Optional, Sequence

import numpy as np
import torch

from ams_torch.apps.recipe import Recipe

__all__ = ["simulate_group", "nonfinite_inputs"]

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
                   on_start: Optional[Callable] = None) -> dict:
    """Simulate batch group ``group`` of a recipe as one batched run.

    ``on_start(run, specs)`` is called once the simulator is built (run: the
    :class:`~ams_torch.apps.scene.BuiltScene`; specs: the B sequence specs). ``on_frame(k, state)`` is
    called after each frame k (state.x, state.v: (B, S, N, 3) m, m/s, world; state.pose: the B
    head poses). Returns ``{"run": BuiltScene, "specs": [sequence specs],
    "group": group spec, "ms_per_frame": float}``. A divergence raises SimulationDiverged naming
    the group (and saying so when the input itself was not finite).
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
    if on_start is not None:
        on_start(run, specs)
    motions = [make_motion(s["motion"]) for s in specs]
    winds = [Wind(**s["wind"]) if s["wind"] is not None else None for s in specs]
    poses_at = lambda t: Pose.stack([m(t, device=device, dtype=dtype) for m in motions])  # noqa: E731
    force = _batched_wind(winds, sim)
    dt = sim.params.dt
    moving = any(m is not None for m in run.collider_motions)
    t0 = time.perf_counter()
    try:
        state = sim.initial_state(poses_at(0.0))
        for k in range(recipe.frames):
            t = (k + 1) * dt
            cposes = [None if m is None else m(t, device=device, dtype=dtype) for m in run.collider_motions] \
                if moving else None
            state = sim.step(state, poses_at(t), external_force=force, collider_poses=cposes)
            if on_frame is not None:
                on_frame(k, state)
    except (SimulationDiverged, ValueError) as err:  # a NaN input: diverged, or refused by the step
        labelled = [(f"[motion] of sequence {s['index']}", m) for s, m in zip(specs, motions)]
        labelled += [(f"[colliders[{i}].motion]", m) for i, m in enumerate(run.collider_motions)]
        bad = nonfinite_inputs(run.rest, labelled, recipe.frames, dt, winds, sim.params)
        if isinstance(err, ValueError) and not bad:
            raise
        raise _diverged(err, f"{recipe.where}: batch group {group} (sequences {[s['index'] for s in specs]})",
                        bad) from None
    ms = 1e3 * (time.perf_counter() - t0) / recipe.frames
    return {"run": run, "specs": specs, "group": recipe.group_spec(group), "ms_per_frame": ms}
