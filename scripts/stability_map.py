"""Stability envelope of AMS and plain mass-spring (MS) at the extremes.

A grid over stretch stiffness κ_L (paper units, particle mass 1: κ_L/m from 1e2 to 1e8 s⁻²), frame
length dt (1/1000 … 1/24 s, M = 1 substep), biphasic stiffness κ_I = κ_α (0 … 1e4; 0 is plain MS,
κ_I = κ_α = 0 without the sag-free offset) and peak head acceleration (0 … 50 g), each with the
inextensibility stage on (the library default) and off (the springs alone).

Groom and motion: the factories of ``tests/test_core.py::test_extremes_stay_finite_and_inextensible``,
``sphere_groom`` (``--strands`` strands × 16 particles, 0.25 m, seed 4) and ``Shake`` (ams_torch.apps.motion): a
sinusoidal translation (a, 0.3 a, 0) · sin(2π f t) at f = 2 Hz whose peak acceleration along x is
``accel_g`` · 9.81 m/s², for ``--duration`` s (two periods by default). Gravity and drag 1.5 s⁻¹ on.

A cell is **unstable** when any of its strands, in any frame:

- ``nan``: a position or velocity is NaN/Inf;
- ``energy``: the kinetic energy relative to the head grows: the peak relative kinetic energy per
  unit mass (½|v − v_head|², J/kg) in the second half of the run exceeds ``--growth`` (10) × the
  peak of the first half (with a floor of 5e-5 J/kg, i.e. 1 cm/s), or a relative speed exceeds
  1e3 m/s (the divergence guard's default);
- ``stretch``: an edge is longer or shorter than its rest length by more than 10 % at the end of
  a frame.

All κ_L × κ_I values run at once as groups of strands (per-strand stiffness tensors, (S, 1)), and
all accelerations as a batch of head poses; strands are independent here (no hair–hair, no
collisions), so a blow-up in one group does not touch the others.

Writes ``docs/stability.json`` (one record per cell), ``docs/stability.md`` and the maps
``docs/stability_ftl.png`` (inextensibility on), ``docs/stability_springs.png`` (off) and
``docs/stability_ams_vs_ms.png``.

    python scripts/stability_map.py            # default grid, ~5 min on 2 cores
    python scripts/stability_map.py --quick    # smoke run, < 1 min
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import ams_torch as at  # noqa: E402
from ams_torch._bench import machine_info, shown_args  # noqa: E402
from ams_torch.sim.inextensibility import max_stretch  # noqa: E402
from ams_torch.apps.motion import Shake  # noqa: E402
from ams_torch.testing import sphere_groom  # noqa: E402

G = 9.81
STATUSES = ("stable", "stretch", "energy", "nan")  # increasing severity
STATUS_COLORS = {"stable": "#4daf4a", "stretch": "#ffd92f", "energy": "#ff7f00", "nan": "#e41a1c"}
KE_FLOOR = 0.5 * 0.01 ** 2  # J/kg: 1 cm/s
MAX_SPEED = 1.0e3  # m/s


def stack_poses(poses_per_batch: list[list]) -> list:
    """[B][F] poses → [F] poses with a leading batch dim B."""
    out = []
    for frame in zip(*poses_per_batch):
        out.append(at.Pose(*(torch.stack([getattr(p, f) for p in frame]) for f in
                             ("rotation", "translation", "linear_velocity", "angular_velocity"))))
    return out


def motion(accels_g, frames: int, dt: float, frequency: float, dtype) -> list:
    """Head poses (F frames, batch len(accels_g)): translation (a, 0.3 a, 0) sin(2π f t) m with
    a = accel_g · g / (2π f)², so the peak acceleration along x is accel_g · g."""
    per = []
    for a_g in accels_g:
        amp = a_g * G / (2 * math.pi * frequency) ** 2
        per.append(Shake(amplitude=0.0, frequency=frequency, translation=(amp, 0.3 * amp, 0.0)).poses(frames, dt, dtype=dtype))
    return stack_poses(per)


def run_block(kls, kbs, dt: float, inextensibility: bool, args, accels=None, ftl_damping=None) -> list[dict]:
    """Simulate every (κ_L, κ_bi) of ``kls`` × ``kbs`` at one dt for all accelerations
    (``accels``, g; default ``args.accels``).

    κ_bi = 0 must be alone in ``kbs`` (plain MS, no sag-free offset). ``ftl_damping``: override of
    ``Params.ftl_damping`` (default: the library's 0.9). Returns one record per (κ_L, κ_bi,
    acceleration) with ``status``, ``max_stretch``, ``ke_growth`` (ratio), ``peak_ke_j_per_kg`` and
    the frame of the first non-finite state."""
    accels = list(args.accels if accels is None else accels)
    dtype = torch.float64 if args.dtype == "float64" else torch.float32
    base = sphere_groom(args.strands, args.particles, seed=4, dtype=torch.float64)
    groups = [(kl, kb) for kl in kls for kb in kbs]
    s0 = base.shape[0]
    rest = base.repeat(len(groups), 1, 1)
    kl_t = torch.tensor([g[0] for g in groups for _ in range(s0)], dtype=dtype)[:, None]
    kb_t = torch.tensor([g[1] for g in groups for _ in range(s0)], dtype=dtype)[:, None]
    ms = all(kb == 0 for kb in kbs)
    if not ms and any(kb == 0 for kb in kbs):
        raise ValueError("κ_bi = 0 (MS) must run in its own block")
    params = at.Params.paper(stretch_stiffness=kl_t, integrity_stiffness=0.0 if ms else kb_t,
                             angular_stiffness=0.0 if ms else kb_t, sag_free=not ms, dt=dt, substeps=1,
                             inextensibility=inextensibility, check_every=0,
                             **({} if ftl_damping is None else {"ftl_damping": ftl_damping}))
    sim = at.Simulator(rest, params, dtype=dtype)
    frames = max(6, int(round(args.duration / dt)))
    poses = motion(accels, frames, dt, args.frequency, dtype)
    b = len(accels)
    ident = at.Pose(*(torch.stack([getattr(at.Pose.identity(dtype=dtype), f)] * b) for f in
                      ("rotation", "translation", "linear_velocity", "angular_velocity")))
    state = sim.initial_state(ident)
    edge = sim.model.edge_rest_length
    shape = (b, rest.shape[0])
    bad_nan = torch.zeros(shape, dtype=torch.bool)
    first_fail = torch.full(shape, -1, dtype=torch.long)
    stretch = torch.zeros(shape, dtype=torch.float64)
    ke1 = torch.zeros(shape, dtype=torch.float64)
    ke2 = torch.zeros(shape, dtype=torch.float64)
    fast = torch.zeros(shape, dtype=torch.bool)
    half = frames // 2
    for k, pose in enumerate(poses):
        state = sim.step(state, pose)
        x, v = state.x, state.v
        finite = torch.isfinite(x).all(-1).all(-1) & torch.isfinite(v).all(-1).all(-1)
        newly = ~finite & ~bad_nan
        first_fail = torch.where(newly & (first_fail < 0), torch.full_like(first_fail, k + 1), first_fail)
        bad_nan |= ~finite
        st = torch.nan_to_num(max_stretch(x, edge).double(), nan=math.inf)
        stretch = torch.maximum(stretch, st)
        rel = torch.nan_to_num(v - state.pose.velocity_at(x), nan=0.0, posinf=0.0, neginf=0.0).double()
        speed2 = (rel * rel).sum(-1)
        ke = 0.5 * speed2.mean(-1)
        fast |= speed2.amax(-1) > MAX_SPEED ** 2
        if k < half:
            ke1 = torch.maximum(ke1, ke)
        else:
            ke2 = torch.maximum(ke2, ke)
        if bool(bad_nan.all()):
            break
    growth = ke2 / ke1.clamp_min(KE_FLOOR)
    energy = fast | (growth > args.growth)
    over = stretch > args.max_stretch
    records = []
    for gi, (kl, kb) in enumerate(groups):
        sl = slice(gi * s0, (gi + 1) * s0)
        for ai, a_g in enumerate(accels):
            if bool(bad_nan[ai, sl].any()):
                status = "nan"
            elif bool(energy[ai, sl].any()):
                status = "energy"
            elif bool(over[ai, sl].any()):
                status = "stretch"
            else:
                status = "stable"
            ff = first_fail[ai, sl]
            records.append({
                "model": "MS" if ms else "AMS", "inextensibility": inextensibility,
                "stretch_stiffness": kl, "biphasic_stiffness": kb, "dt": dt, "accel_g": a_g,
                "frames": frames, "status": status, "ftl_damping": params.ftl_damping,
                "max_stretch": float(f"{float(stretch[ai, sl].max()):.4g}") if math.isfinite(float(stretch[ai, sl].max())) else None,
                "ke_growth": float(f"{float(growth[ai, sl].max()):.4g}") if math.isfinite(float(growth[ai, sl].max())) else None,
                "peak_ke_j_per_kg": float(f"{float(torch.maximum(ke1, ke2)[ai, sl].max()):.4g}"),
                "first_nan_frame": int(ff[ff > 0].min()) if bool((ff > 0).any()) else None,
            })
    return records


# ---------------------------------------------------------------------------------- outputs
def _cell(records, **kw):
    for r in records:
        if all(r[k] == v for k, v in kw.items()):
            return r
    return None


def _dt_label(dt: float) -> str:
    return f"1/{round(1 / dt)}"


def _map_axes(ax, args, xlabel: bool) -> None:
    """Ticks of a (κ_L/m, dt) stability map: decades of κ_L on y, the dts on x."""
    ax.set_yticks(range(len(args.stiffness)))
    ax.set_yticklabels([f"{kl:.0e}".replace("e+0", "e") if (math.log10(kl) % 1) == 0 else ""
                        for kl in args.stiffness], fontsize=6)
    ax.set_xticks(range(len(args.dts)))
    ax.set_xticklabels([_dt_label(dt) for dt in args.dts], fontsize=6, rotation=90)
    if xlabel:
        ax.set_xlabel("dt (s), M = 1", fontsize=7)


def plot_maps(records, args, inextensibility: bool, path: Path) -> None:
    """Rows: accelerations; columns: biphasic stiffness (0 = MS); each panel κ_L (y) × dt (x)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap
    from matplotlib.patches import Patch

    cmap = ListedColormap([STATUS_COLORS[s] for s in STATUSES])
    kbs = [0.0] + list(args.biphasic)
    fig, axes = plt.subplots(len(args.accels), len(kbs), figsize=(1.75 * len(kbs) + 0.8, 1.55 * len(args.accels) + 1.0),
                             sharex=True, sharey=True, squeeze=False)
    for i, a_g in enumerate(args.accels):
        for j, kb in enumerate(kbs):
            ax = axes[i][j]
            img = np.zeros((len(args.stiffness), len(args.dts)))
            for yi, kl in enumerate(args.stiffness):
                for xi, dt in enumerate(args.dts):
                    r = _cell(records, inextensibility=inextensibility, stretch_stiffness=kl, biphasic_stiffness=kb,
                              dt=dt, accel_g=a_g)
                    img[yi, xi] = STATUSES.index(r["status"]) if r else np.nan
            ax.imshow(img, cmap=cmap, vmin=-0.5, vmax=len(STATUSES) - 0.5, origin="lower", aspect="auto",
                      interpolation="nearest")
            if i == 0:
                ax.set_title("MS (κ_I = κ_α = 0)" if kb == 0 else f"AMS κ_I = κ_α = {kb:g}", fontsize=8)
            if j == 0:
                ax.set_ylabel(f"{a_g:g} g\nκ_L/m (s⁻²)", fontsize=8)
            _map_axes(ax, args, xlabel=i == len(args.accels) - 1)
    fig.legend(handles=[Patch(color=STATUS_COLORS[s], label=s) for s in STATUSES], loc="lower center",
               ncol=len(STATUSES), fontsize=8, frameon=False)
    fig.suptitle(f"Stability, inextensibility {'on (library default)' if inextensibility else 'off (springs alone)'}; "
                 "rows: peak head acceleration", fontsize=9)
    fig.tight_layout(rect=(0, 0.04, 1, 0.97))
    fig.savefig(path, dpi=80)
    plt.close(fig)


COMPARE = ("both stable", "AMS only", "MS only", "neither")
COMPARE_COLORS = ("#4daf4a", "#377eb8", "#984ea3", "#e41a1c")


def compare_cells(records, args, inextensibility: bool, kb: float) -> dict:
    """{(κ_L, dt, accel): category} comparing AMS at κ_I = κ_α = kb with MS."""
    out = {}
    for kl in args.stiffness:
        for dt in args.dts:
            for a_g in args.accels:
                key = dict(inextensibility=inextensibility, stretch_stiffness=kl, dt=dt, accel_g=a_g)
                ams = _cell(records, biphasic_stiffness=kb, **key)
                ms = _cell(records, biphasic_stiffness=0.0, **key)
                if ams is None or ms is None:
                    continue
                a, m = ams["status"] == "stable", ms["status"] == "stable"
                out[(kl, dt, a_g)] = COMPARE[0] if a and m else COMPARE[1] if a else COMPARE[2] if m else COMPARE[3]
    return out


def plot_compare(records, args, path: Path) -> None:
    """AMS (paper default κ_I = κ_α = 1e2) against MS, per acceleration, inextensibility on / off."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap
    from matplotlib.patches import Patch

    cmap = ListedColormap(COMPARE_COLORS)
    fig, axes = plt.subplots(2, len(args.accels), figsize=(1.9 * len(args.accels) + 0.8, 5.4), sharex=True,
                             sharey=True, squeeze=False)
    for i, inext in enumerate((True, False)):
        cells = compare_cells(records, args, inext, args.compare_kb)
        for j, a_g in enumerate(args.accels):
            ax = axes[i][j]
            img = np.full((len(args.stiffness), len(args.dts)), np.nan)
            for yi, kl in enumerate(args.stiffness):
                for xi, dt in enumerate(args.dts):
                    c = cells.get((kl, dt, a_g))
                    if c is not None:
                        img[yi, xi] = COMPARE.index(c)
            ax.imshow(img, cmap=cmap, vmin=-0.5, vmax=3.5, origin="lower", aspect="auto", interpolation="nearest")
            if i == 0:
                ax.set_title(f"{a_g:g} g", fontsize=9)
            if j == 0:
                ax.set_ylabel(f"inextensibility {'on' if inext else 'off'}\nκ_L/m (s⁻²)", fontsize=8)
            _map_axes(ax, args, xlabel=i == 1)
    fig.legend(handles=[Patch(color=c, label=l) for c, l in zip(COMPARE_COLORS, COMPARE)], loc="lower center",
               ncol=4, fontsize=8, frameon=False)
    fig.suptitle(f"AMS (κ_I = κ_α = {args.compare_kb:g}) against plain MS", fontsize=9)
    fig.tight_layout(rect=(0, 0.05, 1, 0.96))
    fig.savefig(path, dpi=80)
    plt.close(fig)


def _range_text(values, fmt) -> str:
    """Comma-separated ``fmt(v)`` of the values."""
    return ", ".join(fmt(v) for v in values)


def _kl_text(kl: float) -> str:
    """κ_L/m as ``1e6`` or ``3.2e5``."""
    e = math.log10(kl)
    if abs(e - round(e)) < 1e-9:
        return f"1e{round(e)}"
    return f"{kl / 10 ** math.floor(e):.2g}e{math.floor(e)}"


def region_lines(cells: dict, category: str, args) -> list[str]:
    """Compact text of the (κ_L, dt, accel) cells in ``category``: per acceleration, per κ_L the dts."""
    lines = []
    for a_g in args.accels:
        per_kl = []
        for kl in args.stiffness:
            dts = [dt for dt in args.dts if cells.get((kl, dt, a_g)) == category]
            if dts:
                per_kl.append(f"κ_L/m = {_kl_text(kl)} at dt = {_range_text(dts, _dt_label)}")
        if per_kl:
            lines.append(f"  - {a_g:g} g: " + "; ".join(per_kl))
    return lines


def unstable_lines(records, args, inext: bool, kb: float) -> list[str]:
    """Markdown lines listing, per acceleration and κ_L, the dts (and criteria) of unstable cells."""
    lines = []
    for a_g in args.accels:
        per_kl = []
        for kl in args.stiffness:
            bad = [(dt, r["status"]) for dt in args.dts
                   if (r := _cell(records, inextensibility=inext, stretch_stiffness=kl, biphasic_stiffness=kb,
                                  dt=dt, accel_g=a_g)) is not None and r["status"] != "stable"]
            if bad:
                per_kl.append(f"κ_L/m = {_kl_text(kl)}: " + ", ".join(f"{_dt_label(dt)} ({st})" for dt, st in bad))
        lines.append(f"  - {a_g:g} g: " + ("; ".join(per_kl) if per_kl else "stable at every κ_L and dt"))
    return lines


def stable_region(records, args, inext: bool, kb: float, a_g: float) -> str:
    """Text of the stable (κ_L, dt) cells at one acceleration: ``all``, ``none``, ``κ_L/m ≥ X`` (the
    same threshold at every dt), per-dt thresholds, or a count when the set has no threshold shape."""
    stable = {(kl, dt) for kl in args.stiffness for dt in args.dts
              if (r := _cell(records, inextensibility=inext, stretch_stiffness=kl, biphasic_stiffness=kb, dt=dt,
                             accel_g=a_g)) is not None and r["status"] == "stable"}
    total = len(args.stiffness) * len(args.dts)
    if not stable:
        return "none"
    if len(stable) == total:
        return "all"
    thresholds = {}
    for dt in args.dts:
        ks = [kl for kl in args.stiffness if (kl, dt) in stable]
        if not ks:
            thresholds[dt] = None
            continue
        lo = min(ks)
        if any((kl, dt) not in stable for kl in args.stiffness if kl >= lo):
            return f"{len(stable)} of {total} cells"
        thresholds[dt] = lo
    if len(set(thresholds.values())) == 1:
        return f"κ_L/m ≥ {_kl_text(next(iter(thresholds.values())))}"
    return "; ".join(f"{_dt_label(dt)}: " + ("none" if t is None else f"≥ {_kl_text(t)}") for dt, t in thresholds.items())


def _cell_text(r) -> str:
    """``MS, κ_L/m = 1e7, dt = 1/1000, 0 g`` for one cell record."""
    model = "MS" if r["model"] == "MS" else "AMS κ_I = κ_α = {:g}".format(r["biphasic_stiffness"])
    return f"{model}, κ_L/m = {_kl_text(r['stretch_stiffness'])}, dt = {_dt_label(r['dt'])}, {r['accel_g']:g} g"


def summary_lines(records, probes, args) -> list[str]:
    """The plain statements at the top of stability.md, computed from the cells."""
    out = []
    nan = [r for r in records if r["status"] == "nan"]
    out.append("**No cell produced a NaN/Inf**." if not nan else
               f"**{len(nan)} cells produced NaN/Inf**: " + "; ".join(_cell_text(r) for r in nan[:12]) + ".")
    on_bad = [r for r in records if r["inextensibility"] and r["status"] != "stable"]
    n_on = sum(r["inextensibility"] for r in records)
    if not on_bad:
        out.append(f"**With inextensibility on (the library default) every one of the {n_on} cells is stable**, "
                   "MS and AMS alike.")
    else:
        small = all(r["dt"] == min(args.dts) for r in on_bad)
        out.append(f"**With inextensibility on (the library default), {n_on - len(on_bad)} of {n_on} cells are "
                   f"stable.** The {len(on_bad)} unstable one(s): " + "; ".join(
                       f"{_cell_text(r)} ({r['status']}: kinetic energy ×{r['ke_growth']:g} from the first to the "
                       f"second half, to {r['peak_ke_j_per_kg']:g} J/kg, while the edges stay within "
                       f"{r['max_stretch']:.1e})" for r in on_bad) + "."
                   + (" They sit at the *smallest* dt, where the stiff stretch mode is resolved (ω·dt = "
                      + ", ".join(f"{math.sqrt(r['stretch_stiffness']) * r['dt']:.1f}" for r in on_bad)
                      + "): a strand at rest starts to oscillate by itself. That points to the splitting "
                      "(once-per-frame follow-the-leader with Müller's velocity correction after springs stiff enough "
                      "to be resolved) rather than to the implicit springs; the reruns below vary the correction."
                      if small else ""))
        for r in on_bad:
            ps = [p for p in probes if all(p[k] == r[k] for k in ("stretch_stiffness", "biphasic_stiffness", "dt",
                                                                    "accel_g", "model"))]
            if ps:
                def probe_text(p):
                    what = {0.0: "plain FTL velocities", 1.0: "full Müller correction"}.get(p["ftl_damping"], "")
                    # a strand falling its own length (0.25 m) gains g·L ≈ 2.5 J/kg: far above that it is not at rest
                    calm = p["peak_ke_j_per_kg"] <= 10 * G * 0.25
                    verdict = (f"{p['status']}, peak {p['peak_ke_j_per_kg']:.2g} J/kg" if calm or p["status"] != "stable"
                               else f"no growth, but {p['peak_ke_j_per_kg']:.3g} J/kg from the first frames on (`stable` "
                                    "by the criteria, yet the strand never comes to rest)")
                    return f"`ftl_damping = {p['ftl_damping']:g}` ({what}): {verdict}"
                out.append(f"  Rerun of {_cell_text(r)}: " + "; ".join(probe_text(p) for p in ps)
                           + f"; library default `ftl_damping = {r.get('ftl_damping', 0.9):g}`: {r['status']}, "
                           f"peak {r['peak_ke_j_per_kg']:.3g} J/kg.")
    for inext in (True, False):
        cells = compare_cells(records, args, inext, args.compare_kb)
        ams_only = [k for k, c in cells.items() if c == "AMS only"]
        neither = [k for k, c in cells.items() if c == "neither"]
        ms_only = [k for k, c in cells.items() if c == "MS only"]
        tag = "on" if inext else "off"
        out.append(f"**AMS (κ_I = κ_α = {args.compare_kb:g}) against MS, inextensibility {tag}**: AMS stable and MS "
                   f"not in {len(ams_only)} of {len(cells)} cells, neither stable in {len(neither)}, MS stable and "
                   f"AMS not in {len(ms_only)}.")
    off = [r for r in records if not r["inextensibility"]]
    by = {st: sum(r["status"] == st for r in off) for st in STATUSES}
    out.append(f"**Without inextensibility** the failures are stretch (> {args.max_stretch:.0%}): {by['stretch']} "
               f"cells, energy growth: {by['energy']}, NaN: {by['nan']}, of {len(off)}. MS stretches under its own "
               "weight unless κ_L is stiff (nothing else carries the weight), while AMS's sag-free integrity "
               "springs carry it, so at 0 g AMS is stable where MS is not. From a few g on, edges lengthen by more "
               "than 10 % in MS and AMS alike (the linearised step freezes each spring's direction at the start of "
               "the step, so fast-turning edges grow), unless κ_L and the biphasic stiffness are high and dt is "
               "small (see the frontier table). None of these is a blow-up.")
    ms_on = [r for r in records if r["inextensibility"] and r["model"] == "MS"]
    bad_kl = sorted({r["stretch_stiffness"] for r in ms_on if r["status"] != "stable"})
    out.append("**MS does not go unstable as κ_L grows** (the paper's Fig. 4 says it does): with inextensibility on, "
               f"MS is stable at every κ_L/m from {_kl_text(min(args.stiffness))} to {_kl_text(max(args.stiffness))} "
               + ("at every dt and acceleration." if not bad_kl else
                  "except " + ", ".join(_cell_text(r) for r in ms_on if r["status"] != "stable") + ".")
               + " Nowhere in the grid did the linearised backward-Euler springs blow up (no NaN, with or without "
               "inextensibility); what fails is accuracy (stretch without the projection) and, at the smallest "
               "steps, the projection's velocity correction.")
    return out


def write_markdown(path: Path, records, args, machine, wall_s, loads, command: str, probes=()) -> None:
    """docs/stability.md from the cells (see the module docstring for the criteria)."""
    kbs = [0.0] + list(args.biphasic)
    L = ["# Stability envelope: AMS against plain mass-spring", ""]
    L += ["Generated by `" + command + f"` in {wall_s / 60:.1f} min "
          f"on {machine['cpu']} ({machine['cpu_cores']} cores), torch {machine['torch']}, {machine['threads']} "
          f"intra-op thread(s), {args.dtype}. 1-minute load average: "
          + ", ".join(f"{k} {v}" for k, v in loads) + ". Raw cells: [`stability.json`](stability.json).", ""]
    L += ["## Summary", ""] + [("- " + x if not x.startswith("  ") else x) for x in summary_lines(records, probes, args)]
    L += ["", "![AMS against MS](stability_ams_vs_ms.png)", ""]
    L += ["## Set-up", "",
          f"- Paper units (SPEC §10): particle mass 1 kg, drag 1.5 s⁻¹, gravity on, bend and torsion springs at κ_L, "
          f"one substep (M = 1). Groom: `sphere_groom({args.strands}, {args.particles}, seed=4)` (0.25 m strands "
          "on a 0.1 m sphere, 2 pinned particles), the factory of `tests/test_core.py`.",
          f"- Grid: κ_L/m ∈ {{{_range_text(args.stiffness, _kl_text)}}} s⁻²; dt ∈ {{{_range_text(args.dts, _dt_label)}}} s; "
          f"κ_I = κ_α ∈ {{{_range_text(kbs, lambda v: f'{v:g}')}}} (0 is plain MS: no biphasic coupling, no sag-free "
          f"offset; > 0 is AMS with the sag-free offset); peak head acceleration ∈ {{{_range_text(args.accels, lambda v: f'{v:g}')}}} g; "
          "inextensibility (follow-the-leader after the substeps) on, as the library runs by default, and off, "
          "which leaves the linearised implicit springs alone.",
          f"- Motion: the head translates by (a, 0.3 a, 0) sin(2π f t) with f = {args.frequency:g} Hz and a = accel·g/(2πf)² "
          f"(so 50 g is a {50 * G / (2 * math.pi * args.frequency) ** 2:.2f} m amplitude at "
          f"{50 * G / (2 * math.pi * args.frequency):.0f} m/s peak speed), for {args.duration:g} s "
          f"({args.duration * args.frequency:g} periods).",
          f"- Unstable = `nan` (non-finite state), `energy` (peak relative kinetic energy in the second half above "
          f"{args.growth:g}× that of the first half, floor 1 cm/s, or a relative speed above 1e3 m/s) or `stretch` "
          f"(an edge off its rest length by more than {args.max_stretch:.0%} at the end of a frame). The worst "
          "strand of a cell decides.", ""]
    # counts
    L += ["## Counts", "", "| inextensibility | κ_I = κ_α | " + " | ".join(STATUSES) + " |",
          "|---|---|" + "---:|" * len(STATUSES)]
    for inext in (True, False):
        for kb in kbs:
            rs = [r for r in records if r["inextensibility"] == inext and r["biphasic_stiffness"] == kb]
            L.append(f"| {'on' if inext else 'off'} | {kb:g}{' (MS)' if kb == 0 else ''} | "
                     + " | ".join(str(sum(r["status"] == s for r in rs)) for s in STATUSES) + " |")
    L.append("")
    # stable regions
    L += ["## The stability frontier", "",
          "Stable (κ_L/m, dt) cells for each model and peak head acceleration (`all` = every cell of the grid).", ""]
    for inext in (True, False):
        L += [f"**Inextensibility {'on' if inext else 'off'}**", "",
              "| model | " + " | ".join(f"{a:g} g" for a in args.accels) + " |", "|---|" + "---|" * len(args.accels)]
        for kb in kbs:
            L.append(f"| {'MS' if kb == 0 else f'AMS κ_I = κ_α = {kb:g}'} | "
                     + " | ".join(stable_region(records, args, inext, kb, a) for a in args.accels) + " |")
        L.append("")
    # AMS vs MS
    L += ["## Where AMS is stable and MS is not, and where neither is", ""]
    for inext in (True, False):
        cells = compare_cells(records, args, inext, args.compare_kb)
        counts = {c: sum(v == c for v in cells.values()) for c in COMPARE}
        L.append(f"**Inextensibility {'on' if inext else 'off'}**, AMS at κ_I = κ_α = {args.compare_kb:g} against MS "
                 f"({len(cells)} cells of κ_L × dt × acceleration): " + ", ".join(f"{k}: {v}" for k, v in counts.items())
                 + ".")
        L.append("")
        for cat in ("AMS only", "MS only", "neither"):
            lines = region_lines(cells, cat, args)
            L.append(f"- {cat}: " + ("none" if not lines else ""))
            L += lines
        L.append("")
        any_ams = {}
        for kb in args.biphasic:
            for key, cat in compare_cells(records, args, inext, kb).items():
                if cat in ("AMS only", "both stable"):
                    any_ams.setdefault(key, []).append(kb)
        ms_bad = [k for k, c in cells.items() if c in ("AMS only", "neither")]
        rescued = [k for k in ms_bad if k in any_ams]
        L.append(f"  Over all AMS stiffnesses: {len(ms_bad)} cells where MS is unstable; some κ_I = κ_α > 0 is stable in "
                 f"{len(rescued)} of them.")
        L.append("")
    L += ["## Maps", "", "Inextensibility on (the library default):", "", "![stability, inextensibility on](stability_ftl.png)",
          "", "Inextensibility off (springs alone):", "", "![stability, inextensibility off](stability_springs.png)", ""]
    L += ["## Unstable cells, listed", ""]
    for inext in (True, False):
        for kb in kbs:
            L.append(f"- inextensibility {'on' if inext else 'off'}, "
                     f"{'MS' if kb == 0 else f'AMS κ_I = κ_α = {kb:g}'}:")
            L += unstable_lines(records, args, inext, kb)
    L.append("")
    path.write_text("\n".join(L))


CELL_COLUMNS = ("model", "inextensibility", "stretch_stiffness", "biphasic_stiffness", "dt", "accel_g", "frames",
                "status", "ftl_damping", "max_stretch", "ke_growth", "peak_ke_j_per_kg", "first_nan_frame")


def dump_cells(records: list, meta: dict) -> str:
    """stability.json: ``{"meta": {...}, "columns": [...], "rows": [[...], ...]}``, one row per cell
    (columns ``CELL_COLUMNS``; stiffness in s⁻² for unit mass, dt in s, acceleration in g, kinetic
    energy in J/kg, stretch relative)."""
    rows = ",\n".join(json.dumps([r.get(c) for c in CELL_COLUMNS]) for r in records)
    return ('{"meta": ' + json.dumps(meta) + ',\n"columns": ' + json.dumps(list(CELL_COLUMNS))
            + ',\n"rows": [\n' + rows + "\n]}\n")


def load_cells(path: Path) -> dict:
    """Read stability.json back: ``{"meta": {...}, "records": [dict per cell]}``."""
    data = json.loads(path.read_text())
    if "records" in data:
        return data
    return {"meta": data["meta"], "records": [dict(zip(data["columns"], row)) for row in data["rows"]]}


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="smoke run: a coarse grid, 0.2 s; output under out/stability_quick")
    p.add_argument("--strands", type=int, default=8, help="strands per cell (16 particles each)")
    p.add_argument("--particles", type=int, default=16)
    p.add_argument("--duration", type=float, help="seconds simulated per cell (default 1.0; --quick 0.25)")
    p.add_argument("--frequency", type=float, default=2.0, help="head shake frequency, Hz")
    p.add_argument("--growth", type=float, default=10.0, help="kinetic-energy growth factor counted as unstable")
    p.add_argument("--max-stretch", type=float, default=0.10, help="relative edge-length error counted as unstable")
    p.add_argument("--dtype", default="float32", choices=("float32", "float64"))
    p.add_argument("--threads", type=int, default=1, help="torch intra-op threads (default 1; 0: torch's default)")
    p.add_argument("--out", type=Path, help="output folder (default docs/; --quick: out/stability_quick)")
    p.add_argument("--render-only", action="store_true",
                   help="rewrite stability.md and the maps from an existing stability.json in --out (no simulation)")
    args = p.parse_args(argv)
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    q = args.quick
    args.stiffness = [10.0 ** e for e in ((2, 4, 6, 8) if q else np.arange(2.0, 8.01, 0.5))]
    args.dts = [1 / 1000, 1 / 60, 1 / 24] if q else [1 / 1000, 1 / 500, 1 / 240, 1 / 120, 1 / 60, 1 / 30, 1 / 24]
    args.biphasic = [1e2, 1e4] if q else [1.0, 1e1, 1e2, 1e3, 1e4]
    args.accels = [0.0, 10.0, 50.0] if q else [0.0, 2.0, 10.0, 20.0, 50.0]
    args.duration = args.duration or (0.25 if q else 1.0)
    args.compare_kb = 1e2
    out = args.out or (REPO / "out" / "stability_quick" if q else REPO / "docs")
    out.mkdir(parents=True, exist_ok=True)
    if args.render_only:
        data = load_cells(out / "stability.json")
        meta, grid = data["meta"], data["meta"]["grid"]
        args.stiffness, args.dts, args.accels = grid["stretch_stiffness"], grid["dt"], grid["accel_g"]
        args.biphasic = [kb for kb in grid["biphasic_stiffness"] if kb != 0]
        args.duration, args.frequency = grid["duration_s"], grid["frequency_hz"]
        args.strands, args.particles, args.dtype = grid["strands"], grid["particles"], grid["dtype"]
        args.growth = grid.get("growth", args.growth)
        args.max_stretch = grid.get("max_stretch", args.max_stretch)
        _write(out, data["records"], args, meta["machine"], meta["wall_s"], [tuple(x) for x in meta["load_avg_1min"]],
               meta["command"], meta.get("probes", []))
        print(f"rewrote {out / 'stability.md'} and the maps from {out / 'stability.json'}")
        return
    machine = machine_info()
    loads = [("at the start", machine["load_avg_1min_at_start"])]
    t0 = time.perf_counter()
    records = []
    for inext in (True, False):
        for dt in args.dts:
            for kbs in ([0.0], list(args.biphasic)):
                t = time.perf_counter()
                recs = run_block(args.stiffness, kbs, dt, inext, args)
                records += recs
                bad = sum(r["status"] != "stable" for r in recs)
                print(f"[{time.perf_counter() - t0:7.1f} s] inextensibility={'on' if inext else 'off'} dt={_dt_label(dt)} "
                      f"{'MS' if kbs == [0.0] else 'AMS'}: {len(recs)} cells, {bad} unstable ({time.perf_counter() - t:.1f} s)",
                      flush=True)
        loads.append((f"after inextensibility {'on' if inext else 'off'}", round(os.getloadavg()[0], 2)))
    # probe: every unstable cell with inextensibility on, rerun with the FTL velocity correction
    # factor at its ends (0: plain FTL velocities, 1: full Müller correction)
    probes = []
    for r in [r for r in records if r["inextensibility"] and r["status"] != "stable"]:
        for damp in (0.0, 1.0):
            pr = run_block([r["stretch_stiffness"]], [r["biphasic_stiffness"]], r["dt"], True, args,
                           accels=[r["accel_g"]], ftl_damping=damp)[0]
            probes.append(pr)
            print(f"[probe] {pr['model']} κ_L/m={_kl_text(pr['stretch_stiffness'])} κ_bi={pr['biphasic_stiffness']:g} "
                  f"dt={_dt_label(pr['dt'])} {pr['accel_g']:g} g ftl_damping={damp:g}: {pr['status']} "
                  f"(KE growth {pr['ke_growth']}, peak {pr['peak_ke_j_per_kg']} J/kg)", flush=True)
    wall = time.perf_counter() - t0
    loads.append(("at the end", round(os.getloadavg()[0], 2)))
    meta = {"command": f"python scripts/stability_map.py {shown_args(hide=('--note',))}".strip(), "wall_s": round(wall, 1),
            "machine": machine, "load_avg_1min": loads,
            "grid": {"stretch_stiffness": args.stiffness, "dt": args.dts, "biphasic_stiffness": [0.0] + args.biphasic,
                     "accel_g": args.accels, "duration_s": args.duration, "frequency_hz": args.frequency,
                     "strands": args.strands, "particles": args.particles, "dtype": args.dtype,
                     "growth": args.growth, "max_stretch": args.max_stretch}, "probes": probes}
    (out / "stability.json").write_text(dump_cells(records, meta))
    _write(out, records, args, machine, wall, loads, meta["command"], probes)
    print(f"wrote {out / 'stability.md'}, stability.json and the maps in {wall / 60:.1f} min")


def _write(out: Path, records, args, machine, wall, loads, command: str, probes=()) -> None:
    plot_maps(records, args, True, out / "stability_ftl.png")
    plot_maps(records, args, False, out / "stability_springs.png")
    plot_compare(records, args, out / "stability_ams_vs_ms.png")
    write_markdown(out / "stability.md", records, args, machine, wall, loads, command, probes)


if __name__ == "__main__":
    main()
