"""The measurements of one scene: reference and its checks, the sweeps, the time reference,
native timing of every setting, and (phase 2) the presets with energy probes and both paths."""
from __future__ import annotations

import os
import time

import numpy as np

from tradeoff.choose import PRESET_NAMES, preset_setting
from tradeoff.energy import EnergyProbe
from tradeoff.scenes import (BASE, OTHER_CONTACT, base_setting, errors_mm, has_stage, make_run, run_setting,
                             scene_stages, setting_key, setting_label)
from tradeoff.timing import Case, time_cases


def sweep_settings(raw: dict, args) -> list[dict]:
    """Each axis swept alone around the base, the substeps again with the other contact mode
    (``OTHER_CONTACT``; scenes with colliders), then the joint M × N grid (geometric stiffness off
    and on). Each setting carries ``axes``: the sweeps it belongs to."""
    hh = has_stage(raw, "hair_hair")
    base = base_setting(raw)
    cands = [(dict(base, substeps=m), "substeps") for m in args.substeps]
    if has_stage(raw, "collisions"):
        cands += [(dict(base, substeps=m, contact=OTHER_CONTACT), "substeps_contact") for m in args.substeps]
    cands += [(dict(base, particles=n), "particles") for n in args.particles]
    cands += [(dict(base, dtype=d), "dtype") for d in args.dtypes]
    cands += [(dict(base, grid=g), "grid") for g in (args.grids if hh else ())]
    cands += [(dict(base, off=[st]), "stages") for st in scene_stages(raw)] + [(dict(base), "stages")]
    jm, jn = args.joint[raw["name"]]
    for gs in (False, True):
        for m in jm:
            for n in jn:
                cands.append((dict(base, substeps=m, particles=n, gs=gs), "joint"))
    out: dict = {}
    for s, axis in cands:
        rec = out.setdefault(setting_key(s), dict(s, axes=[]))
        if axis not in rec["axes"]:
            rec["axes"].append(axis)
    return list(out.values())


def reference_setting(raw: dict, args, **kw) -> dict:
    s = {"substeps": args.ref_substeps[raw["name"]], "particles": args.ref_particles[raw["name"]],
         "dtype": "float64", "grid": args.ref_grid if has_stage(raw, "hair_hair") else None, "gs": BASE["gs"],
         "off": [],
         "params": {"stiffness_cap": args.ref_cap}}
    s.update(kw)
    return s


def summary(rec: dict) -> str:
    if rec.get("rms_error_mm") is None:
        return f"{setting_label(rec['settings']):44s} diverged: {(rec.get('diverged') or '')[:80]}"
    return (f"{setting_label(rec['settings']):44s} RMS {rec['rms_error_mm']:8.3f} mm  max {rec['max_error_mm']:8.2f} mm"
            f"  shape {rec['shape_error_mm']:7.3f} mm  ({rec['wall_s']:.1f} s)")


def make_record(name: str, raw: dict, s: dict, axes: list, res: dict, ref_pts, subset) -> dict:
    rec = {"scene": name, "settings": {k: v for k, v in s.items() if k != "axes"}, "axes": list(axes),
           "frames": raw["frames"], "strands": int(raw["groom"].get("strands", 1)),
           "error_strands": None if subset is None else int(len(subset)), "diverged": res["diverged"],
           "wall_s": round(res["wall_s"], 2)}
    if res["pts"] is None:
        rec.update(rms_error_mm=None, max_error_mm=None, shape_error_mm=None, max_stretch=None)
        return rec
    rec.update(**{k: float(f"{v:.5g}") for k, v in errors_mm(res["pts"], ref_pts).items()},
               max_stretch=float(f"{res['stretch']:.4g}"))
    return rec


def state_at(raw: dict, setting: dict, k0: int):
    """The state of a setting on the full groom after ``k0`` frames (native)."""
    r = dict(raw, frames=k0)
    return run_setting(r, setting, keep_at=k0)["state"]


def run_reference(name: str, raw: dict, args, subset, log) -> tuple:
    """The reference (float64) and its checks (half the substeps; fewer particles; half the
    substeps with the other choice of geometric stiffness). Returns (info, reference positions at
    material points)."""
    ref_set, failed = reference_setting(raw, args), []
    while True:
        ref = run_setting(raw, ref_set, subset)
        if ref["pts"] is not None:
            break
        failed.append({"settings": dict(ref_set), "diverged": ref["diverged"]})
        log(f"[{name}] reference {setting_label(ref_set)} diverged: {ref['diverged'][:120]}")
        if ref_set["substeps"] <= 4:
            raise RuntimeError(f"{name}: every reference diverged: {failed}")
        ref_set = dict(ref_set, substeps=ref_set["substeps"] // 2)
    log(f"[{name}] reference {setting_label(ref_set)}: {ref['wall_s']:.0f} s")
    info = {"scene": name, "reference_failed": failed, "frames": raw["frames"], "grid": has_stage(raw, "hair_hair"),
            "strands": int(raw["groom"].get("strands", 1)), "reference": ref_set, "reference_wall_s": ref["wall_s"],
            "error_strands": None if subset is None else int(len(subset)), "checks": []}
    m = ref_set["substeps"]
    checks = [("half the substeps", dict(ref_set, substeps=m // 2)),
              ("fewer particles", dict(ref_set, particles=args.ref_check_particles[name])),
              ("half the substeps, " + ("SPEC form" if ref_set["gs"] else "geometric stiffness"),
               dict(ref_set, substeps=m // 2, gs=not ref_set["gs"]))]
    for what, chk_set in checks[:args.ref_checks]:
        chk = run_setting(raw, chk_set, subset)
        e = errors_mm(chk["pts"], ref["pts"]) if chk["pts"] is not None else {}
        info["checks"].append({"what": what, "settings": chk_set, **e, "wall_s": chk["wall_s"],
                               "diverged": chk["diverged"]})
        log(f"[{name}] reference check {setting_label(chk_set)}: RMS {e.get('rms_error_mm', float('nan')):.3g} mm "
            f"({chk['wall_s']:.0f} s)")
    return info, ref["pts"]


def run_scene(name: str, raw: dict, args, subset, log) -> tuple:
    """Phase 1 of a scene: reference and checks, every setting of the sweeps (errors), the time
    reference, and native timing of every setting (interleaved). Returns (records, info, ref)."""
    t0 = time.perf_counter()
    info, ref_pts = run_reference(name, raw, args, subset, log)
    k0, window = args.window[name]
    records, kept, states = [], {}, {}
    for s in sweep_settings(raw, args):
        axes = s.pop("axes")
        res = run_setting(raw, s, subset, keep_at=None if subset is not None else k0)
        rec = make_record(name, raw, s, axes, res, ref_pts, subset)
        if ("substeps" in axes or "substeps_contact" in axes) and res["pts"] is not None:
            kept[len(records)] = (res["pts"], s.get("contact", BASE["contact"]))
        if res["pts"] is not None:
            states[setting_key(s)] = res["state"]
        records.append(rec)
        log(f"[{name}] {summary(rec)}")
    info["error_runs_wall_s"] = round(time.perf_counter() - t0, 1)
    # time discretisation alone: the substeps sweep against a float64 run at the same N with many substeps
    # (one per contact mode: the other mode's sweep against a time reference of that mode)
    m_time = args.time_ref_substeps.get(name)
    for contact in ((BASE["contact"], OTHER_CONTACT) if m_time else ()):
        mine = {i: x for i, (x, c) in kept.items() if c == contact}
        if not mine:
            continue
        t_set = base_setting(raw, substeps=m_time, dtype="float64", contact=contact)
        t_ref = run_setting(raw, t_set, subset)
        info["time_reference" if contact == BASE["contact"] else "time_reference_contact"] = t_set
        for i, x in (mine.items() if t_ref["pts"] is not None else ()):
            e = errors_mm(x, t_ref["pts"])
            records[i]["time_rms_error_mm"] = float(f"{e['rms_error_mm']:.5g}")
        log(f"[{name}] time reference {setting_label(t_set)}: " + ", ".join(
            f"M={records[i]['settings']['substeps']}: {records[i].get('time_rms_error_mm', float('nan')):.3g} mm"
            for i in mine))
    # native timing of every setting, interleaved
    t1 = time.perf_counter()
    cases = []
    for i, rec in enumerate(records):
        if rec["rms_error_mm"] is None:
            continue
        s = rec["settings"]
        state = states.get(setting_key(s)) if subset is None else state_at(raw, s, k0)
        run = make_run(raw, s, "native")
        cases.append(Case(i, run, run.sim, state, k0, window))
    for i, res in time_cases(cases, args.repeats, log).items():
        records[i]["native"] = res
    info["timing_wall_s"] = round(time.perf_counter() - t1, 1)
    info["wall_s"] = round(time.perf_counter() - t0, 1)
    info["load_avg_1min_at_end"] = round(os.getloadavg()[0], 2)
    return records, info, ref_pts


def run_presets(name: str, raw: dict, args, presets: dict, records: list, ref_pts, subset, log) -> dict:
    """Phase 2 of a scene: the base setting and each preset, geometric stiffness off and on: the
    error (a record, added when the sweeps did not have it), the energy probe (states of the run
    with it off, probed both ways), and the ms/frame of both paths, all cases interleaved."""
    t0 = time.perf_counter()
    k0, window = args.window[name]
    by = {setting_key(r["settings"]): r for r in records if r["scene"] == name}
    targets = [("base", base_setting(raw))] + [(p, preset_setting(presets[p], raw)) for p in PRESET_NAMES]
    targets.append(("base-inextensibility", base_setting(raw, off=["inextensibility"])))  # energy only, not timed
    cases, rows = [], []
    for tag, s0 in targets:
        for gs in (False, True):
            s = dict(s0, gs=gs)
            rec = by.get(setting_key(s))
            if rec is None or (not gs and "energy" not in rec):
                probe = EnergyProbe(make_run(raw, s, "native", subset).sim) if not gs else None
                res = run_setting(raw, s, subset, probes=[probe] if probe else [])
                if rec is None:
                    rec = make_record(name, raw, s, ["preset"], res, ref_pts, subset)
                    records.append(rec)
                    by[setting_key(s)] = rec
                    log(f"[{name}] {tag}{' GS' if gs else ''}: {summary(rec)}")
                if probe is not None:
                    rec["energy"] = probe.summary()
                    log(f"[{name}] {tag} energy probe: {rec['energy']}")
            if tag in PRESET_NAMES and "preset" not in rec["axes"]:
                rec["axes"].append("preset")
            if tag in PRESET_NAMES and not gs:
                rec.setdefault("presets", [])
                if tag not in rec["presets"]:
                    rec["presets"].append(tag)
            if tag in PRESET_NAMES and gs:
                rec.setdefault("presets_gs", [])
                if tag not in rec["presets_gs"]:
                    rec["presets_gs"].append(tag)
            if rec["rms_error_mm"] is None or tag == "base-inextensibility":
                continue
            state = state_at(raw, s, k0)
            for path in ("native", "torch"):
                run = make_run(raw, s, path)
                cases.append(Case((setting_key(s), path), run, run.sim, state, k0, window))
            rows.append(rec)
    timed = time_cases(cases, args.repeats, log)
    for rec in rows:
        rec["paths"] = {path: timed[(setting_key(rec["settings"]), path)] for path in ("native", "torch")}
    return {"wall_s": round(time.perf_counter() - t0, 1), "load_avg_1min_at_end": round(os.getloadavg()[0], 2)}


def convergence_slopes(records: list[dict], infos: list[dict], axis: str = "substeps") -> dict:
    """Per scene, the substeps sweep (base N, float32; ``axis="substeps_contact"``: with the other
    contact mode, ``OTHER_CONTACT``): RMS error against the reference and against the same-N float64 time
    reference (of the same contact mode), and the least-squares slope of log(error) against
    log(M) for the latter over M ≤ M_time / 4. First order (backward Euler) gives −1."""
    out = {}
    for info in infos:
        sc = info["scene"]
        rs = sorted((r for r in records if r["scene"] == sc and axis in r["axes"] and r.get("rms_error_mm")),
                    key=lambda r: r["settings"]["substeps"])
        if len(rs) < 2:
            continue
        d = {"substeps": [r["settings"]["substeps"] for r in rs], "rms_error_mm": [r["rms_error_mm"] for r in rs],
             "time_rms_error_mm": [r.get("time_rms_error_mm") for r in rs], "slope": None, "fit_substeps": []}
        m_time = info.get("time_reference" if axis == "substeps" else "time_reference_contact", {}).get("substeps")
        fit = [(m, e) for m, e in zip(d["substeps"], d["time_rms_error_mm"]) if e and m_time and m <= m_time / 4]
        if len(fit) >= 2:
            d["slope"] = float(np.polyfit(np.log([f[0] for f in fit]), np.log([f[1] for f in fit]), 1)[0])
            d["fit_substeps"] = [f[0] for f in fit]
            d["time_reference_substeps"] = m_time
        out[sc] = d
    return out


__all__ = ["sweep_settings", "run_scene", "run_presets", "convergence_slopes", "reference_setting", "BASE"]
