"""The presets' rule: Pareto fronts, which scenes vote, and the pick within each cost budget."""
from __future__ import annotations

import math

import ams_torch as at

from tradeoff.scenes import BASE, has_stage, setting_key

PRESET_NAMES = ("fast", "balanced", "accurate")
#: a reference resolves a scene's errors when its own difference to the checks is at most this
#: share of every error that can decide a preset
RESOLVE = 0.25


def pareto(points: list[tuple[float, float]]) -> list[int]:
    """Indices of the (cost, error) points no other point beats in both, by cost."""
    order = sorted(range(len(points)), key=lambda i: (points[i][0], points[i][1]))
    front, best = [], math.inf
    for i in order:
        if points[i][1] < best:
            front.append(i)
            best = points[i][1]
    return front


def geomean(values) -> float:
    values = [max(v, 1e-12) for v in values]
    return float(math.exp(sum(math.log(v) for v in values) / len(values)))


def pick(cands: list, cost, error, budget: float, tol: float):
    """The cheapest candidate whose error is within ``tol`` (relative) of the lowest error among
    the candidates costing at most ``budget``; the cheapest candidate when none fits."""
    within = [c for c in cands if cost(c) <= budget]
    if not within:
        return min(cands, key=cost)
    best = min(error(c) for c in within)
    return min((c for c in within if error(c) <= (1 + tol) * best), key=cost)


def ms(rec: dict | None, path: str = "native") -> float | None:
    """The minimum over the repeats of a record's ms/frame on a path (None if not timed)."""
    if rec is None or not rec.get(path):
        return None
    return rec[path]["ms_min"]


def index(records: list[dict]) -> dict:
    return {(r["scene"], setting_key(r["settings"])): r for r in records if r.get("rms_error_mm") is not None}


def find(records_or_index, scene: str, raw_has_grid: bool, **kw):
    """The record of the base setting with ``kw`` changed, in ``scene``."""
    by = records_or_index if isinstance(records_or_index, dict) else index(records_or_index)
    s = dict(BASE, grid=BASE["grid"] if raw_has_grid else None, off=[])
    s.update(kw)
    return by.get((scene, setting_key(s)))


def floor_mm(info: dict) -> float | None:
    """The reference's resolution: the largest RMS difference between it and its refinement checks
    (half its substeps, fewer particles). The check with the other choice of geometric stiffness is
    not counted: it changes the implicit step's matrix, so at half the substeps it measures that
    choice's own first-order time error, not how far the reference is from converged."""
    ref_gs = info.get("reference", {}).get("gs")
    vals = [c["rms_error_mm"] for c in info.get("checks", []) if c.get("rms_error_mm") is not None
            and (ref_gs is None or "settings" not in c or bool(c["settings"].get("gs")) == bool(ref_gs))]
    return max(vals) if vals else None


def decisive_errors(info: dict, records: list[dict], budgets: dict) -> list[float]:
    """RMS errors of the scene's joint-grid settings that cost at most the largest budget in
    this scene (the errors that can decide a preset)."""
    sc, hh = info["scene"], info["grid"]
    base = ms(find(records, sc, hh))
    top = max(budgets.values())
    return [r["rms_error_mm"] for r in records if r["scene"] == sc and "joint" in r["axes"]
            and r.get("rms_error_mm") is not None and base and ms(r) is not None and ms(r) <= top * base]


def votes(info: dict, records: list[dict], budgets: dict) -> bool:
    """Whether a scene takes part in choosing the presets: its first-choice reference did not
    diverge, and it resolves the errors: the reference's checks differ from it by at most
    ``RESOLVE`` × the smallest error that can decide a preset (:func:`decisive_errors`)."""
    if info.get("reference_failed"):
        return False
    floor, dec = floor_mm(info), decisive_errors(info, records, budgets)
    return floor is not None and bool(dec) and floor <= RESOLVE * min(dec)


def choose_presets(records: list[dict], infos: list[dict], scenes: list[str], budgets: dict,
                   tol: float = 0.05) -> dict:
    """Pick ``fast`` / ``balanced`` / ``accurate``: errors from the voting ``scenes``, costs from
    every scene (a cost needs no reference).

    Each preset has a cost budget (× the native ms/frame of the base setting, the library
    default) and takes, on each axis, the cheapest option whose error is within ``tol`` of the
    lowest error that fits in the budget:

    1. substeps M and particles N jointly, over the joint grid measured in every scene (float32,
       every stage on, the base grid, the library's geometric stiffness): cost = the largest over all scenes
       of the native ms/frame relative to the scene's base (the preset must fit its budget in
       every scene; a small scene's frame is mostly fixed overhead on the native path, and a mean
       would let it hide the cost of a large one), error = the geometric mean over the voting
       scenes of the RMS error relative to the base's; only points of this Pareto front compete;
    2. the hair–hair grid (voting scenes with hair–hair; the grid sweep at the base setting;
       cost = the base frame with the hair–hair stage's native time at that grid);
    3. the dtype (the dtype sweep at the base setting);
    4. geometric stiffness, at the chosen (M, N): the library's default unless the other choice
       lowers the error (geometric mean over the voting scenes) by more than ``tol`` within the
       budget (timing noise alone must not switch it).
    """
    by = index(records)
    grid_of = {i["scene"]: i["grid"] for i in infos}
    timed = [i["scene"] for i in infos]
    base = {sc: find(by, sc, grid_of[sc]) for sc in timed}
    joint = None
    for sc in timed:
        keys = {(r["settings"]["substeps"], r["settings"]["particles"], BASE["gs"])
                for r in records if r["scene"] == sc and "joint" in r["axes"] and r.get("rms_error_mm") is not None
                and ms(r) is not None and bool(r["settings"].get("gs")) == BASE["gs"]}
        joint = keys if joint is None else joint & keys
    keys = sorted(joint or [])
    pts = []
    for m, n, gs in keys:
        rs = {sc: find(by, sc, grid_of[sc], substeps=m, particles=n, gs=gs) for sc in timed}
        pts.append((max(ms(rs[sc]) / ms(base[sc]) for sc in timed),
                    geomean([rs[sc]["rms_error_mm"] / base[sc]["rms_error_mm"] for sc in scenes])))
    front = pareto(pts)
    hh = [sc for sc in scenes if grid_of[sc]]
    dt_pairs = [(base[sc], find(by, sc, grid_of[sc], dtype="float64")) for sc in timed]
    dt_pairs = [(a, b) for a, b in dt_pairs if b is not None and ms(b) is not None]
    out = {}
    for name in PRESET_NAMES:
        b = budgets[name]
        i = pick(front, lambda j: pts[j][0], lambda j: pts[j][1], b, tol)
        m, n, gs = keys[i]
        grid = None
        if hh:
            sc = hh[0]
            grids = [r for r in records if r["scene"] == sc and "grid" in r["axes"] and r.get("rms_error_mm") is not None
                     and r.get("native")]
            b_ms = ms(base[sc])
            b_hh = base[sc]["native"]["stages_median"].get("hair_hair", 0.0)

            def grid_cost(r):
                return (b_ms - b_hh + r["native"]["stages_median"].get("hair_hair", 0.0)) / b_ms

            grid = pick(grids, grid_cost, lambda r: r["rms_error_mm"], b, tol)["settings"]["grid"]
        dtype = "float32"
        if dt_pairs:
            opts = [("float32", 1.0, 1.0),
                    ("float64", max(ms(r64) / ms(r32) for r32, r64 in dt_pairs),
                     geomean([r64["rms_error_mm"] / r32["rms_error_mm"] for r32, r64 in dt_pairs
                              if r32["scene"] in scenes]))]
            dtype = pick(opts, lambda o: o[1] * pts[i][0], lambda o: o[2], b, tol)[0]
        other = {sc: find(by, sc, grid_of[sc], substeps=m, particles=n, gs=not BASE["gs"]) for sc in timed}
        default = {sc: find(by, sc, grid_of[sc], substeps=m, particles=n) for sc in timed}
        if all(other[sc] is not None and ms(other[sc]) is not None for sc in timed):
            cost_other = max(ms(other[sc]) / ms(base[sc]) for sc in timed)
            err_other = geomean([other[sc]["rms_error_mm"] / default[sc]["rms_error_mm"] for sc in scenes])
            if err_other < 1 / (1 + tol) and cost_other <= b:
                gs = not BASE["gs"]
        out[name] = {"substeps": m, "particles": n, "gs": gs, "dtype": dtype, "grid": grid, "cost": pts[i][0],
                     "error": pts[i][1], "budget": b}
    out["_front"] = [{"substeps": keys[i][0], "particles": keys[i][1], "gs": keys[i][2], "cost": pts[i][0],
                      "error": pts[i][1]} for i in front]
    out["_points"] = [{"substeps": k[0], "particles": k[1], "gs": k[2], "cost": p[0], "error": p[1]}
                      for k, p in zip(keys, pts)]
    out["_scenes"] = list(scenes)
    return out


def library_presets() -> dict:
    """The library's presets as benchmark settings (``Params.preset`` and ``preset_settings``)."""
    out = {}
    for name in PRESET_NAMES:
        p, extra = at.Params.preset(name), at.Params.preset_settings(name)
        out[name] = {"substeps": p.substeps, "particles": extra["particles"], "dtype": extra["dtype"],
                     "grid": extra["hair_hair_resolution"], "gs": bool(p.geometric_stiffness)}
    return out


def preset_setting(preset: dict, raw: dict) -> dict:
    """The setting of a preset in a scene: the grid only where the scene has hair–hair."""
    return {"substeps": preset["substeps"], "particles": preset["particles"], "dtype": preset["dtype"],
            "grid": preset["grid"] if has_stage(raw, "hair_hair") else None, "gs": bool(preset.get("gs")), "off": []}
