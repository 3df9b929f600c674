"""Why the roller coaster does not converge in substeps: convergence and sensitivity per suspect.

docs/tradeoff.md measured the roller coaster's RMS error against a same-N float64 time reference
(M = 64) falling with slope −0.19 in the substeps M (first order would be −1). This script
measures, in float64, the convergence in M of the roller-coaster scene and of variants that each
switch off or alter one suspect, against a time reference of the same variant (same N, same
strands, M_ref substeps), and the sensitivity of each variant to a 1e-12 m/s perturbation of the
initial velocities. See docs/roller_coaster.md for the results.

Variants (each a scene edit and/or the library's step with some of its stages replaced through the
stage table, :func:`ams_torch.sim.stepping.replace_stage`; the library files are not touched):

    base            the scene as it is (the variant stages with default options are checked
                    bit-identical to the library's)
    no_collisions   [stages].collisions = false
    hookean         [stages].nonhookean = false (Hookean integrity, no plastic yield)
    no_yield        non-Hookean curve kept, plastic update replaced by a no-op
    rounds0         collision_inextensibility = 0 (no length restore + push-out after contact)
    rounds4         collision_inextensibility = 4
    tol             contact test σ < −1e-6 m instead of σ < 0 (a particle pushed out to σ ≈ 0
                    is not re-classified by rounding)
    skin            push-out to σ = +1e-6 m instead of σ = 0 (hysteresis: the pushed-out particle
                    sits clearly outside)
    per_substep     inextensibility, collisions (with their rounds) and the plastic update after
                    every substep (with Δt' = Δt/M) instead of once per frame
    per_substep_ftl, per_substep_yield
                    only FTL, or only the plastic update, after every substep
    per_substep_contact
                    the contact response + push-out after every substep (Δt'), and the frame's
                    FTL + collision stage as in the library
    frictionless    collider friction μ = 0 (the scene's head has 0.5)
    smooth          collisions off and Hookean integrity (no non-smooth operator left but FTL)

Error: positions at the same material points (same N, so particle by particle), RMS over all
frames, strands and particles, in mm; the slope is the least-squares slope of log(RMS error)
against log(M) over M <= M_ref / 4.

    python scripts/roller_coaster_convergence.py                 # full study (~1 h on 2 shared cores)
    python scripts/roller_coaster_convergence.py --quick         # smoke run (< 2 min)
    python scripts/roller_coaster_convergence.py --variants base smooth --substeps 1 2 4
    python scripts/roller_coaster_convergence.py --render-only   # rewrite plots from the JSON

Runs are cached (``--cache``, default /tmp/roller_coaster_cache) so an interrupted study resumes.
"""
from __future__ import annotations

import argparse
import dataclasses
import functools
import hashlib
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
#: The library measured: this checkout, or a frozen copy of it (``AMS_TORCH_LIBRARY=/path`` holding
#: ``ams_torch/``, e.g. ``git archive HEAD ams_torch | tar -x -C /path``) so that a long study is not
#: disturbed by edits made in the working tree while it runs.
LIBRARY = Path(os.environ.get("AMS_TORCH_LIBRARY", str(REPO))).resolve()
sys.path.insert(0, str(LIBRARY))
# Variants with step options run the step with variant stages (torch definition, torch backend); the
# check compares it with the library's step on the torch backend too (bit for bit). Variants
# without step options (scene or Params edits only) run the library's own step on its default
# backend (the native kernels, float64 parity ~1e-14): ``--torch`` puts everything on torch.
if "--torch" in sys.argv:
    os.environ["AMS_TORCH_NATIVE"] = "0"

from ams_torch.apps.scene import build, load_scene  # noqa: E402
from ams_torch.sim.dynamics import frame_dynamics, substep_poses, substep_targets, _external  # noqa: E402
from ams_torch.sim.assembly import assemble_system  # noqa: E402
from ams_torch.sim.contact import substep_contact  # noqa: E402
from ams_torch.sim.inextensibility import follow_the_leader as library_ftl  # noqa: E402
from ams_torch.sim.forces import safe_normalize  # noqa: E402
from ams_torch.sim.stepping import (STAGES, SimulationDiverged, finish_stage, plastic_update,  # noqa: E402
                                    replace_stage, wrap_stage)
from ams_torch.solver.op import solve_banded  # noqa: E402
from ams_torch.stages.collide import resolve_world_poses  # noqa: E402
from ams_torch.stages.collide.poses import flat_pose  # noqa: E402
from ams_torch.stages.collide.response import collider_response  # noqa: E402

SCENE = REPO / "datasets" / "scenes" / "roller_coaster.toml"
NEAR = 1e-9  # m: a contact decision taken with |σ| below this is "at rounding level" (diagnostic only)

# ----------------------------------------------------------------------------------- variants
#: name -> (scene edits, step options, description)
VARIANTS = {
    "base": ({}, {}, "the scene as it is"),
    "no_collisions": ({"stages": {"collisions": False}}, {}, "collisions off"),
    "hookean": ({"stages": {"nonhookean": False}}, {}, "Hookean integrity (no non-Hookean curve, no yield)"),
    "no_yield": ({}, {"plastic": False}, "non-Hookean curve, plastic update a no-op"),
    "rounds0": ({"params": {"collision_inextensibility": 0}}, {}, "no length restore after contact (rounds = 0)"),
    "rounds4": ({"params": {"collision_inextensibility": 4}}, {}, "4 rounds of length restore + push-out"),
    "tol": ({}, {"contact_tol": 1e-6}, "contact test σ < −1 µm"),
    "skin": ({}, {"skin": 1e-6}, "push out to σ = +1 µm"),
    "per_substep": ({}, {"per_substep": ("ftl", "stage", "yield")},
                    "FTL, the collision stage and the yield after every substep (Δt')"),
    "per_substep_ftl": ({}, {"per_substep": ("ftl",)}, "FTL after every substep (Δt'), the rest per frame"),
    "per_substep_yield": ({}, {"per_substep": ("yield",)}, "plastic update after every substep, the rest per frame"),
    "per_substep_contact": ({}, {"per_substep": ("contact",)},
                            "contact response + push-out after every substep (Δt'), the frame's stages kept"),
    "substep_contact": ({"params": {"contact": "substep"}}, {},
                        "the library's Params(contact=\"substep\"): the contact response after every substep"),
    "hookean_substep_contact": ({"stages": {"nonhookean": False}, "params": {"contact": "substep"}}, {},
                                "Hookean integrity, contact after every substep"),
    "no_yield_substep_contact": ({"params": {"contact": "substep"}}, {"plastic": False},
                                 "plastic update a no-op, contact after every substep"),
    "hookean_no_ftl": ({"stages": {"nonhookean": False}, "params": {"inextensibility": False}}, {},
                       "Hookean, no follow-the-leader (nor collision rounds), contact once per frame"),
    "no_ftl_nonhookean_substep_contact": ({"params": {"contact": "substep", "inextensibility": False}}, {},
                                          "the scene's non-Hookean integrity and yield, no follow-the-leader, contact "
                                          "after every substep"),
    "no_ftl_substep_contact": ({"stages": {"nonhookean": False},
                                "params": {"contact": "substep", "inextensibility": False}}, {},
                               "Hookean, no follow-the-leader (nor collision rounds), contact after every substep"),
    "frictionless": ({}, {"friction": 0.0}, "collider friction μ = 0 (library: 0.5)"),
    "no_frame_ftl": ({}, {"frame_ftl": False},
                     "no follow-the-leader after the substeps (the collision stage keeps its rounds)"),
    "no_ftl": ({"params": {"inextensibility": False}}, {}, "no follow-the-leader at all (nor collision rounds)"),
    "ftl_positions": ({}, {"ftl_velocity": "none"}, "follow-the-leader moves positions only (no velocity correction)"),
    "strain_limit10": ({}, {"ftl_limit": 0.1}, "follow-the-leader as a strain limiter: edges kept within ±10 %"),
    "strain_limit2": ({}, {"ftl_limit": 0.02}, "follow-the-leader as a strain limiter: edges kept within ±2 %"),
    "no_collisions_sl10": ({"stages": {"collisions": False}}, {"ftl_limit": 0.1},
                           "collisions off, follow-the-leader as a ±10 % strain limiter"),
    "sl10_contact": ({}, {"ftl_limit": 0.1, "per_substep": ("contact",)},
                     "±10 % strain limiter and the contact response + push-out after every substep"),
    "ftl_damping0": ({"params": {"ftl_damping": 0.0}}, {}, "ftl_damping = 0 (library: 0.9)"),
    "ftl_damping1": ({"params": {"ftl_damping": 1.0}}, {}, "ftl_damping = 1"),
    "smooth_no_ftl": ({"stages": {"collisions": False, "nonhookean": False}, "params": {"inextensibility": False}}, {},
                      "collisions off, Hookean, no follow-the-leader"),
    "smooth": ({"stages": {"collisions": False, "nonhookean": False}}, {}, "collisions off and Hookean"),
    "smooth_ftl_positions": ({"stages": {"collisions": False, "nonhookean": False}}, {"ftl_velocity": "none"},
                             "collisions off, Hookean, FTL moves positions only (no velocity correction)"),
    "smooth_ftl_damping0": ({"stages": {"collisions": False, "nonhookean": False}, "params": {"ftl_damping": 0.0}},
                            {}, "collisions off, Hookean, ftl_damping = 0 (plain FTL velocities)"),
}
DEFAULT_OPTS = {"plastic": True, "contact_tol": 0.0, "skin": 0.0, "friction": None, "per_substep": (),
                "frame_ftl": True, "ftl_velocity": "dftl", "ftl_limit": 0.0}


# ------------------------------------------------------------------ variants of the library step
def collide_variant(x, v, dt, colliders, world_poses, free=None, *, tol=0.0, skin=0.0, friction=None,
                    stats=None):
    """:func:`ams_torch.stages.collide.response.collide` with the study knobs of its
    ``collider_response``: the contact test is σ < −tol (library: tol = 0) and the push-out goes
    to σ = +skin (library: 0). ``stats``:
    a dict counting the contact decisions taken (``tests``), the contacts (``inside``) and the
    decisions with |σ| < NEAR (``near``). ``friction``: replaces the colliders' μ (None: theirs).
    With tol = skin = 0 and friction None it is the library's arithmetic."""
    if len(colliders) == 0:
        return x, v
    shape, batch = x.shape, x.shape[:-3]
    s_count, n_count = shape[-3], shape[-2]
    xf = x.reshape(-1, s_count * n_count, 3)
    vf = v.reshape(-1, s_count * n_count, 3)
    free_k = None
    if free is not None:
        free_k = torch.as_tensor(free, device=x.device).bool().expand(s_count, n_count).reshape(s_count * n_count)
    for col, pose in zip(colliders, world_poses):
        xf, vf, sigma, inside = collider_response(col, flat_pose(pose, batch, x), xf, vf, dt, free_k, tol=tol,
                                                  skin=skin, friction=friction)
        if stats is not None:
            f = free_k if free_k is not None else torch.ones_like(inside[0])
            stats["tests"] += int(f.sum()) * xf.shape[0]
            stats["inside"] += int(inside.sum())
            stats["near"] += int((((sigma + tol).abs() < NEAR) & f).sum())
    return xf.reshape(shape), vf.reshape(shape)


def collisions_variant(model, config, x, v, head_pose, collider_poses, dt, opts, stats):
    """A copy of :func:`ams_torch.sim.stepping.collisions` with the frame length ``dt`` given (the
    per-substep variant passes Δt') and :func:`collide_variant`."""
    cols = list(model.colliders)
    poses = resolve_world_poses(cols, head_pose, list(collider_poses) or None)
    free = ~model.pinned
    kw = dict(tol=opts["contact_tol"], skin=opts["skin"], friction=opts["friction"], stats=stats)
    x, v = collide_variant(x, v, dt, cols, poses, free=free, **kw)
    if config.inextensibility:
        for _ in range(config.collision_rounds):
            x, v = variant_inextensibility(model, config, x, v, head_pose, dt, opts)
            x, v = collide_variant(x, v, 0.0, cols, poses, free=free, **kw)
    return x, v


def dynamics_per_substep(model, coeffs, config, state, pose0, pose1, hermite, control, opts, stats):
    """:func:`ams_torch.sim.dynamics.frame_dynamics` with once-per-frame operators moved into the
    substep loop. ``opts["per_substep"]`` names them: ``"ftl"`` (follow-the-leader with Δt'),
    ``"stage"`` (the whole collision stage with Δt': response, then its rounds of FTL + push-out),
    ``"yield"`` (the plastic update), each then no longer run at the frame's end, and ``"contact"``
    (the contact response + push-out with Δt' after every substep, the frame's collision stage
    kept). Operators not named run once per frame as in the library (FTL, then the stage).
    Substep poses are the step's interpolated ones (with their interpolated velocities).
    Returns (x, v, ghost_rest)."""
    ops = set(opts["per_substep"])
    dt = config.dt
    m_sub = config.substeps
    h = dt / m_sub
    x, v, ghost_rest, sag_offset = state.x, state.v, state.ghost_rest, state.sag_offset
    time_ = state.time if control.time is None else control.time
    pinned = model.pinned[..., None]
    poses = substep_poses(pose0, pose1, hermite, m_sub, dt)
    y_a = poses[0].to_world(ghost_rest)
    nonhookean = config.nonhookean
    offset = poses[0].rotate(sag_offset) if nonhookean else None
    cols = list(model.colliders)
    for s in range(m_sub):
        pb = poses[s + 1]
        y_b, w, target, pin_v = substep_targets(model, x, ghost_rest, y_a, pb, h)
        f_ext = _external(control.external_force, x, v, time_ + s * h)
        blocks, rhs = assemble_system(model, coeffs, config, x, v, y_a, w, pin_v, h, f_ext, offset)
        v = solve_banded(blocks, rhs, check=False)
        x = torch.where(pinned, target, x + h * v)
        pv = pose1 if s + 1 == m_sub else pb  # interpolated poses carry (interpolated) velocities
        if config.inextensibility and "ftl" in ops:
            x, v = variant_inextensibility(model, config, x, v, pv, h, opts)
        if config.colliders and "stage" in ops:
            x, v = collisions_variant(model, config, x, v, pv, control.collider_poses, h, opts, stats)
        if config.colliders and "contact" in ops:
            wp = resolve_world_poses(cols, pv, list(control.collider_poses) or None)
            x, v = collide_variant(x, v, h, cols, wp, free=~model.pinned, tol=opts["contact_tol"], skin=opts["skin"],
                                   friction=opts["friction"], stats=stats)
        if nonhookean and opts["plastic"] and "yield" in ops:
            before = ghost_rest
            ghost_rest = plastic_update(model, coeffs, x, ghost_rest, sag_offset, pv)
            stats["yield"] += int((ghost_rest != before).any(-1).sum())
            y_b = pb.to_world(ghost_rest)
        y_a = y_b
        if nonhookean:
            offset = pb.rotate(sag_offset)
    if config.inextensibility and "ftl" not in ops:
        x, v = variant_inextensibility(model, config, x, v, pose1, dt, opts)
    if config.colliders and "stage" not in ops:
        x, v = collisions_variant(model, config, x, v, pose1, control.collider_poses, dt, opts, stats)
    return x, v, ghost_rest


def variant_stages(opts: dict, stats: dict) -> tuple:
    """The library's stages (:data:`ams_torch.sim.stepping.STAGES`) with the variant's dynamics,
    collisions, finish and yield (torch definition; hair–hair as in the library). With the default
    options it is the library's arithmetic on the torch backend (checked bit for bit)."""
    ops = set(opts["per_substep"])

    def dynamics(f):
        config = f.config
        if ops:  # the per-substep dynamics run the collision stage too
            x, v, ghost_rest = dynamics_per_substep(f.model, f.coeffs, config, f.state, f.state.pose, f.pose1,
                                                    f.hermite, f.control, opts, stats)
            return f.replace(x=x, v=v, ghost_rest=ghost_rest, speed=None)
        contact = None  # the library's Params(contact="substep"), as its dynamics stage passes it
        if config.contact == "substep" and config.colliders:
            contact = functools.partial(substep_contact, f.model, config, collider_poses=f.control.collider_poses)
        state = f.state
        time_ = state.time if f.control.time is None else f.control.time
        x, v = frame_dynamics(f.model, f.coeffs, dataclasses.replace(config, inextensibility=False), state.x,
                              state.v, state.ghost_rest, state.sag_offset, state.pose, f.pose1, f.hermite, time_,
                              f.control.external_force, contact=contact)
        if config.inextensibility and opts["frame_ftl"]:  # the frame's FTL, at the last substep pose
            last = substep_poses(state.pose, f.pose1, f.hermite, config.substeps, config.dt)[-1]
            x, v = variant_inextensibility(f.model, config, x, v, last, config.dt, opts)
        return f.replace(x=x, v=v, speed=None)

    def collide(f):
        if ops:
            return f
        x, v = collisions_variant(f.model, f.config, f.x, f.v, f.pose1, f.control.collider_poses, f.config.dt, opts,
                                  stats)
        return f.replace(x=x, v=v)

    def counted(run):
        def plastic(f):
            if not opts["plastic"] or "yield" in ops:
                return f
            out = run(f)
            stats["yield"] += int((out.ghost_rest != f.ghost_rest).any(-1).sum())
            return out
        return plastic

    stages = replace_stage(STAGES, "dynamics", dynamics)
    stages = replace_stage(stages, "collisions", collide)
    stages = replace_stage(stages, "finish", lambda f: finish_stage(f.replace(native=False)))
    return wrap_stage(stages, "yield", counted)


def variant_inextensibility(model, config, x, v, pose, dt, opts):
    """:func:`ams_torch.sim.dynamics.inextensibility` with the variant's follow-the-leader:
    ``opts["ftl_limit"]`` (a strain limiter: edges kept within ± the limit; 0: exact lengths) and
    ``opts["ftl_velocity"]`` ("none": positions projected, velocities left as they were)."""
    rest = model.rest_positions
    fallback = safe_normalize(pose.rotate((rest[:, 1:, :] - rest[:, :-1, :]).expand(
        x.shape[:-3] + (rest.shape[0], rest.shape[1] - 1, 3))))[0]
    if opts["ftl_limit"]:
        x2, v2 = library_ftl(x, v, model.edge_rest_length, model.pinned, dt, config.ftl_damping, fallback,
                             limit=opts["ftl_limit"])
    else:
        x2, v2 = library_ftl(x, v, model.edge_rest_length, model.pinned, dt, config.ftl_damping, fallback)
    return (x2, v) if opts["ftl_velocity"] == "none" else (x2, v2)


# ------------------------------------------------------------------------------------- runs
def build_variant(name: str, substeps: int, frames: int, strands: int, particles: int):
    edits, _, _ = VARIANTS[name]
    scene = load_scene(str(SCENE), {"frames": frames, "scale": strands / 600.0})
    scene["substeps"] = int(substeps)
    scene["groom"]["particles"] = int(particles)
    for section, changes in edits.items():
        scene[section].update(changes)
    return build(scene, dtype=torch.float64)


def simulate_variant(name: str, substeps: int, frames: int, strands: int, particles: int, perturb: float = 0.0,
                     library=False, force_copy: bool = False) -> dict:
    """One run. ``perturb``: m/s added to the initial velocity of every free particle (fixed random
    directions). A variant with step options runs the variant stages (torch backend), one without
    the library's own step (default backend; the contact counts of ``stats`` come from the variant
    only). ``library``: the library's step even so (``"torch"``: on the torch backend, the check);
    ``force_copy``: the variant stages even without options (the check). Returns ``x`` (F, S, N, 3) float64 m,
    ``stats`` and ``wall_s``."""
    run = build_variant(name, substeps, frames, strands, particles)
    sim = run.sim
    copy = (bool(VARIANTS[name][1]) or force_copy) and not library
    opts = dict(DEFAULT_OPTS, **VARIANTS[name][1]) if copy else None
    if copy or library == "torch":  # the copy is the torch definition: compare it on the torch backend
        sim.config = dataclasses.replace(sim.config, backend="torch")
    stats = {"tests": 0, "inside": 0, "near": 0, "yield": 0}
    state = sim.initial_state()
    if perturb:
        g = torch.Generator().manual_seed(1234)
        d = torch.randn(state.v.shape, generator=g, dtype=torch.float64)
        d = d / d.norm(dim=-1, keepdim=True) * (~sim.model.pinned)[..., None]
        state = dataclasses.replace(state, v=state.v + perturb * d)
    dt = sim.params.dt
    xs = []
    t0 = time.perf_counter()
    diverged = None
    if opts is not None:
        sim.stages = variant_stages(opts, stats)
    for k in range(frames):
        pose = run.motion((k + 1) * dt, dtype=torch.float64)
        try:
            state = sim.step(state, pose)
        except SimulationDiverged as err:  # the rest of the run is NaN
            diverged = f"frame {err.frame}: {str(err)[:200]}"
            xs += [torch.full_like(state.x, float("nan"))] * (frames - k)
            break
        xs.append(state.x.detach().clone())
        for k2 in ("inside", "near", "yield"):
            stats.setdefault(f"{k2}_per_frame", []).append(stats[k2])
    return {"x": torch.stack(xs), "stats": stats, "wall_s": time.perf_counter() - t0, "diverged": diverged}


def cached(cache: Path, key: dict, fn):
    """Run ``fn()`` unless ``key`` is cached; returns its dict (``x`` as a tensor)."""
    h = hashlib.sha1(json.dumps(key, sort_keys=True).encode()).hexdigest()[:16]
    path = cache / f"{h}.pt"
    if path.exists():
        return torch.load(path)
    out = fn()
    cache.mkdir(parents=True, exist_ok=True)
    torch.save(out, path)
    return out


def rms_mm(a: torch.Tensor, b: torch.Tensor, dims=None) -> torch.Tensor:
    d2 = (a - b).pow(2).sum(-1)
    return (d2.mean() if dims is None else d2.mean(dims)).sqrt() * 1e3


def slope(ms, errs) -> float:
    return float(np.polyfit(np.log(ms), np.log(errs), 1)[0])


# ------------------------------------------------------------------------------------ study
def study(args, log) -> dict:
    cache = Path(args.cache)
    base_key = {"frames": args.frames, "strands": args.strands, "particles": args.particles,
                "library": f"{LIBRARY}@{library_commit()}"}
    out = {"args": {k: v for k, v in vars(args).items() if k not in ("render_only",)}, "variants": {}}
    if args.check:
        a = simulate_variant("base", 2, min(args.frames, 12), args.strands, args.particles, force_copy=True)
        b = simulate_variant("base", 2, min(args.frames, 12), args.strands, args.particles, library="torch")
        same = bool(torch.equal(a["x"], b["x"]))
        out["copy_bit_identical"] = same
        log(f"check: the variant stages (default options) are bit-identical to the library's step over "
            f"{a['x'].shape[0]} frames: {same}")
        if not same:
            raise SystemExit("the variant stages differ from the library; fix variant_stages first")
    for name in args.variants:
        t0 = time.perf_counter()
        runs = {}
        for m in sorted(set(args.substeps) | {args.ref_substeps}):
            key = dict(base_key, variant=name, substeps=m, perturb=0.0)
            runs[m] = cached(cache, key, functools.partial(simulate_variant, name, m, args.frames, args.strands,
                                                           args.particles))
            log(f"[{name}] M={m}: {runs[m]['wall_s']:.0f} s, contacts "
                f"{ {k: v for k, v in runs[m]['stats'].items() if not k.endswith('_frame')} }"
                + (f", DIVERGED at {runs[m]['diverged']}" if runs[m].get("diverged") else ""))
        ref = runs[args.ref_substeps]["x"]
        ms = sorted(args.substeps)
        errs = [float(rms_mm(runs[m]["x"], ref)) for m in ms]
        per_frame = {m: rms_mm(runs[m]["x"], ref, dims=(-1, -2)).tolist() for m in ms}
        fit = [(m, e) for m, e in zip(ms, errs) if m <= args.ref_substeps / 4 and np.isfinite(e) and e > 0]
        rec = {"description": VARIANTS[name][2], "substeps": ms, "rms_error_mm": errs,
               "final_rms_error_mm": [float(rms_mm(runs[m]["x"][-1], ref[-1])) for m in ms],
               "per_frame_rms_error_mm": per_frame, "ref_substeps": args.ref_substeps,
               "slope": slope(*zip(*fit)) if len(fit) >= 2 else None, "fit_substeps": [f[0] for f in fit],
               "diverged": {m: runs[m].get("diverged") for m in runs if runs[m].get("diverged")},
               "stats": {m: {k: v for k, v in runs[m]["stats"].items() if not k.endswith("_frame")} for m in runs}, "wall_s": {m: runs[m]["wall_s"] for m in runs}}
        # first-order halving check on the early part (frames before the first large error)
        # sensitivity: the same run with a 1e-12 m/s perturbation of the initial velocities
        sens = []
        pairs = [(m, args.perturb) for m in args.sens_substeps]
        if name in args.perturb_extra_variants:
            pairs += [(max(args.sens_substeps), p) for p in args.perturb_extra]
        for m, size in pairs:
            key = dict(base_key, variant=name, substeps=m, perturb=size)
            pert = cached(cache, key, functools.partial(simulate_variant, name, m, args.frames, args.strands,
                                                        args.particles, size))
            if m not in runs:
                key0 = dict(base_key, variant=name, substeps=m, perturb=0.0)
                runs[m] = cached(cache, key0, functools.partial(simulate_variant, name, m, args.frames, args.strands,
                                                                args.particles))
            d = (pert["x"] - runs[m]["x"]).norm(dim=-1)  # (F, S, N) m
            dmax = d.amax((-1, -2))
            first = {}
            for thr in (1e-9, 1e-6, 1e-3):
                idx = torch.nonzero(dmax > thr)
                first[f"{thr:g}"] = int(idx[0, 0]) + 1 if len(idx) else None
            ld = torch.log10(dmax.clamp_min(1e-300))
            jump = torch.diff(ld)  # the largest one-frame growth of log10(max difference)
            k = int(torch.argmax(jump))
            sens.append({"substeps": m, "perturb": size, "max_diff_m": dmax.tolist(),
                         "rms_diff_mm": float(rms_mm(pert["x"], runs[m]["x"])),
                         "final_max_diff_m": float(dmax[-1]), "peak_max_diff_m": float(dmax.max()),
                         "first_frame_above": first, "largest_jump_decades": float(jump[k]),
                         "largest_jump_frame": k + 2,
                         "strands_above_1mm_at_end": int((d[-1].amax(-1) > 1e-3).sum())})
            log(f"[{name}] sensitivity M={m}, {size:g} m/s: final max diff {dmax[-1]:.3g} m (peak {dmax.max():.3g}), "
                f"RMS {sens[-1]['rms_diff_mm']:.3g} mm, first frames above 1e-9/1e-6/1e-3 m: {first}, "
                f"largest jump {jump[k]:.1f} decades at frame {k + 2}")
        rec["sensitivity"] = sens
        rec["study_wall_s"] = time.perf_counter() - t0
        out["variants"][name] = rec
        log(f"[{name}] RMS error (mm) vs M={args.ref_substeps}: "
            + ", ".join(f"M={m}: {e:.3g}" for m, e in zip(ms, errs))
            + (f"; slope {rec['slope']:.2f} over M={rec['fit_substeps']}" if rec["slope"] is not None else ""))
    return out


# ----------------------------------------------------------------------------------- plots
def plot(res: dict, prefix: Path) -> list:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    vs = res["variants"]
    fig, ax = plt.subplots(figsize=(7, 5))
    for name, r in vs.items():
        ax.loglog(r["substeps"], r["rms_error_mm"], "o-", label=f"{name} ({r['slope']:.2f})" if r["slope"] is not None
                  else name)
    m = np.array(sorted({m for r in vs.values() for m in r["substeps"]}), dtype=float)
    if len(m):
        ax.loglog(m, 10 / m, "k--", lw=0.8, label="slope −1")
    ax.set_xlabel("substeps M")
    ax.set_ylabel("RMS error vs same-variant M_ref (mm)")
    ax.set_title("roller coaster: convergence in substeps (float64)")
    ax.legend(fontsize=7)
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    p = prefix.with_name(prefix.name + "_convergence.png")
    fig.savefig(p, dpi=110)
    plt.close(fig)
    paths.append(p)

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    for name, r in vs.items():
        for s in r["sensitivity"]:
            if s["perturb"] != res["args"]["perturb"] or s["substeps"] != max(res["args"]["sens_substeps"]):
                continue
            axes[0].semilogy(np.arange(1, len(s["max_diff_m"]) + 1), np.maximum(s["max_diff_m"], 1e-17),
                             label=f"{name} M={s['substeps']}")
    axes[0].set_xlabel("frame")
    axes[0].set_ylabel(f"max |Δx| (m) from a {res['args']['perturb']:g} m/s perturbation")
    axes[0].legend(fontsize=6)
    axes[0].grid(True, alpha=0.3)
    for name in ("base", "smooth", "no_collisions"):
        if name in vs:
            r = vs[name]
            for m, e in r["per_frame_rms_error_mm"].items():
                axes[1].semilogy(np.arange(1, len(e) + 1), np.maximum(e, 1e-12), label=f"{name} M={m}",
                                 ls="-" if name == "base" else "--")
    axes[1].set_xlabel("frame")
    axes[1].set_ylabel("RMS error per frame vs M_ref (mm)")
    axes[1].legend(fontsize=6, ncol=2)
    axes[1].grid(True, alpha=0.3)
    fig.tight_layout()
    p = prefix.with_name(prefix.name + "_sensitivity.png")
    fig.savefig(p, dpi=110)
    plt.close(fig)
    paths.append(p)
    return paths


def _git_head() -> str:
    import subprocess

    try:
        return subprocess.run(["git", "-C", str(REPO), "rev-parse", "HEAD"], capture_output=True, text=True,
                              check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def library_commit() -> str:
    """The commit the measured library is (``AMS_TORCH_LIBRARY_COMMIT`` for a frozen copy), else this
    checkout's HEAD, marked ``+worktree`` (uncommitted edits may be in it)."""
    return os.environ.get("AMS_TORCH_LIBRARY_COMMIT") or _git_head() + "+worktree"


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    p.add_argument("--substeps", nargs="+", type=int, default=[1, 2, 4, 8, 16, 32])
    p.add_argument("--ref-substeps", type=int, default=128)
    p.add_argument("--sens-substeps", nargs="+", type=int, default=[4, 16])
    p.add_argument("--perturb", type=float, default=1e-12, help="m/s, at every --sens-substeps")
    p.add_argument("--perturb-extra", nargs="*", type=float, default=[1e-9, 1e-6],
                   help="further perturbation sizes (m/s), at the largest --sens-substeps only")
    p.add_argument("--perturb-extra-variants", nargs="*", default=["base", "smooth", "smooth_no_ftl", "no_collisions",
                                                                  "no_collisions_sl10", "strain_limit10"],
                   help="the variants that get the --perturb-extra runs")
    p.add_argument("--frames", type=int, default=100)
    p.add_argument("--strands", type=int, default=30)
    p.add_argument("--particles", type=int, default=32)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--cache", default="/tmp/roller_coaster_cache")
    p.add_argument("--out", default=str(REPO / "docs" / "roller_coaster.json"))
    p.add_argument("--no-check", dest="check", action="store_false")
    p.add_argument("--quick", action="store_true", help="smoke run: 12 frames, 6 strands, M ≤ 4 vs 16")
    p.add_argument("--render-only", action="store_true")
    p.add_argument("--torch", action="store_true", help="every run on the torch backend (AMS_TORCH_NATIVE=0)")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    out_path = Path(args.out)
    if args.render_only:
        res = json.loads(out_path.read_text())
    else:
        if args.quick:
            args.frames, args.strands, args.substeps, args.ref_substeps = 12, 6, [1, 2, 4], 16
        t0 = time.perf_counter()
        load0 = os.getloadavg()[0]
        res = study(args, lambda s: print(f"[{time.perf_counter() - t0:7.0f} s] {s}", flush=True))
        res["machine"] = {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count(),
                          "torch": torch.__version__, "threads": args.threads,
                          "load_avg_1min_start": round(load0, 2), "load_avg_1min_end": round(os.getloadavg()[0], 2)}
        res["wall_s"] = time.perf_counter() - t0
        res["library"] = {"path": str(LIBRARY), "commit": library_commit()}
        res["command"] = "python scripts/roller_coaster_convergence.py " + " ".join(argv or sys.argv[1:])
        out_path.write_text(json.dumps(res, indent=1))
    for path in plot(res, out_path.with_suffix("")):
        print("wrote", path)


if __name__ == "__main__":
    main()
