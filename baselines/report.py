"""The benchmark's leaderboard (markdown) and plots, from its ``results.json``.

``python -m baselines.report DIR`` redraws ``DIR/leaderboard.md`` and ``DIR/*.png`` from
``DIR/results.json`` without rerunning anything.
"""
from __future__ import annotations

import math
import sys
from collections import defaultdict
from pathlib import Path
from typing import Dict, List, Sequence

from baselines.metrics import aggregate

__all__ = ["write", "summarise", "leaderboard", "REFERENCE_ROWS"]

#: rows that describe the data, not a method
REFERENCE_ROWS = ("(dense reference)", "(guide input vs dense copies)")

#: leaderboard columns: (key, header, format)
COLUMNS = [("mean_mm", "mean (mm)", "{:.2f}"), ("p95_mm", "p95 (mm)", "{:.2f}"), ("max_mm", "max (mm)", "{:.1f}"),
           ("worst_mean_mm", "worst seq. mean (mm)", "{:.2f}"), ("tip_mm", "tip (mm)", "{:.2f}"),
           ("chamfer_mm", "Chamfer (mm)", "{:.2f}"), ("velocity_mm_s", "velocity (mm/s)", "{:.0f}"),
           ("acceleration_mm_s2", "accel. (m/s²)", "{:.1f}"), ("curvature_err", "curvature (1/m)", "{:.2f}"),
           ("strand_length_mm", "length (mm)", "{:.2f}"), ("head_inside_share", "in head", "{:.3%}"),
           ("head_depth_max_mm", "head depth max (mm)", "{:.1f}"), ("colliders_inside_share", "in colliders", "{:.3%}"),
           ("colliders_depth_max_mm", "collider depth max (mm)", "{:.1f}"),
           ("ms_per_frame_method", "method ms/frame", "{:.1f}")]


def _fmt(key: str, fmt: str, v) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "–"
    if key == "acceleration_mm_s2":
        v = v / 1000.0  # shown in m/s²
    return fmt.format(v)


def summarise(rows: Sequence[dict], by: Sequence[str]) -> Dict[tuple, dict]:
    """Aggregate per-sequence rows (:func:`baselines.metrics.aggregate`) grouped by the keys ``by``;
    the method's ms/frame is averaged too."""
    groups: Dict[tuple, List[dict]] = defaultdict(list)
    skipped: Dict[tuple, int] = defaultdict(int)
    for r in rows:
        if "not_applicable" in r:  # the method does not apply to that sequence (said in the row)
            skipped[tuple(r[k] for k in by)] += 1
        else:
            groups[tuple(r[k] for k in by)].append(r)
    out = {}
    for k in skipped:
        if k not in groups:
            out[k] = {"sequences": 0, "not_applicable": skipped[k]}
    for k, rs in groups.items():
        agg = aggregate(rs)
        agg["not_applicable"] = skipped.get(k, 0)
        ms = [r["ms_per_frame_method"] for r in rs if r.get("ms_per_frame_method") is not None]
        agg["ms_per_frame_method"] = sum(ms) / len(ms) if ms else None
        out[k] = agg
    return out


def _table(entries: List[tuple]) -> List[str]:
    """entries: (label cells, aggregated metrics) → markdown lines."""
    head = ["guides", "method"] + [h for _, h, _ in COLUMNS] + ["sequences", "n/a"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for cells, m in entries:
        vals = [_fmt(k, f, m.get(k)) for k, _, f in COLUMNS]
        lines.append("| " + " | ".join(list(cells) + vals + [str(m.get("sequences", "")),
                                                             str(m.get("not_applicable", 0) or "")]) + " |")
    return lines


def leaderboard(results: dict) -> str:
    """The leaderboard page (markdown) of a results dict."""
    rows = results["rows"]
    run = results["runs"][-1] if results.get("runs") else {}
    out = ["# Interpolation benchmark: leaderboard", ""]
    out.append(f"Written by `ams-torch bench-interp` ({' '.join(run.get('command') or [])}). Raw rows: "
               f"`results.json` (one per method × guides × guide source × split × sequence).")
    out += ["", "## Provenance", ""]
    for k in ("commit", "tree_changed", "ams_torch", "torch", "python", "device", "cores", "threads", "load_average",
              "native", "date"):
        if k in run:
            out.append(f"- {k}: {run[k]}")
    for name, d in results.get("datasets", {}).items():
        out.append(f"- dataset `{name}` ({d.get('recipe')}): checksum `{d['checksum'][:16]}`, splits {d['splits']}, "
                   f"guides simulated alone {d['guides_alone']}, path `{d.get('path')}`")
    out += ["", "Errors are over every free (non-pinned) vertex of every frame of the held-out sequences. "
            "`worst seq. mean` is the worst sequence's mean error. Velocity and acceleration errors compare finite "
            "differences of the prediction with the reference's (a constant offset scores 0; flicker scores high). "
            "`in head` / `in colliders`: share of vertices deeper than 0.1 mm inside. "
            "`(dense reference)` is the dense simulation scored against itself (its own penetration); "
            "`(guide input vs dense copies)` is how far the guides simulated alone are from the dense run's copies "
            "of the same strands (the error that no interpolation can remove).", ""]
    methods = [m for m in dict.fromkeys(r["method"] for r in rows) if m not in REFERENCE_ROWS]
    order = list(REFERENCE_ROWS) + methods
    overall = summarise(rows, ("guide_source", "guides", "method"))
    out += ["## Overall (every dataset and held-out split)", ""]
    for src in sorted({k[0] for k in overall}):
        out += [f"### Guides: {'simulated alone' if src == 'alone' else 'the dense run copies'}", ""]
        entries = []
        for g in sorted({k[1] for k in overall if k[0] == src}):
            ranked = sorted((m for m in methods if (src, g, m) in overall),
                            key=lambda m: overall[(src, g, m)].get("mean_mm", math.inf))
            for m in [r for r in REFERENCE_ROWS if (src, g, r) in overall] + ranked:
                entries.append(((str(g), m), overall[(src, g, m)]))
        out += _table(entries) + [""]
    rows = [dict(r, subset=r["split"] + (f" (held out: {r['holdout']})" if r.get("holdout") else
                                         " (by the split's shares)" if r["split"] == "test" else ""))
            for r in rows]
    detail = summarise(rows, ("dataset", "subset", "guide_source", "guides", "method"))
    out += ["## Per dataset and split", "",
            "Test sequences are broken down by why they are held out: an unseen groom (`groom_seed`, `preset`), "
            "an unseen motion (`motion`), an unseen collider (`collider`), or only the split's random shares "
            "(seen kinds of groom, motion and collider, new draws).", ""]
    for ds, split, src in sorted({k[:3] for k in detail}):
        out += [f"### {ds} / {split} / guides {src}", ""]
        entries = [((str(g), m), detail[(ds, split, src, g, m)])
                   for g in sorted({k[3] for k in detail if k[:3] == (ds, split, src)})
                   for m in order if (ds, split, src, g, m) in detail]
        out += _table(entries) + [""]
    cost = results.get("cost") or []
    if cost:
        out += ["## Cost: guides + interpolation against dense simulation (ms/frame, same device)", "",
                f"The scene of dataset `{results.get('cost_dataset', '?')}` (head, colliders, hair–hair grid, "
                "params, motion of its first sequence) with the groom regrown at S strands.", "",
                "| strands | guides | method | dense | guides alone | method | guides + method | speed-up | note |",
                "|---|---|---|---|---|---|---|---|---|"]
        for c in cost:
            f = lambda v: "–" if v is None else f"{v:.1f}"  # noqa: E731
            sp = "–" if c["speedup"] is None else f"{c['speedup']:.2f}×"
            out.append(f"| {c['strands']} × {c['particles']} | {c['guides']} | {c['method']} | {f(c['dense_ms'])} | "
                       f"{f(c['guides_ms'])} | {f(c['method_ms'])} | {f(c['total_ms'])} | {sp} | {c['note']} |")
        out.append("")
    out += ["![error vs guides](error_vs_guides.png)", "", "![penetration](penetration.png)", ""]
    if cost:
        out += ["![cost](cost.png)", ""]
    return "\n".join(out)


def _plots(results: dict, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for r in results["rows"] if r["method"] not in REFERENCE_ROWS]
    if not rows:
        return
    overall = summarise(rows, ("guide_source", "method", "guides"))
    for key, label, fname, scale in (("mean_mm", "mean vertex error (mm)", "error_vs_guides.png", 1.0),
                                     ("head_inside_share", "vertices inside the head (%)", "penetration.png", 100.0)):
        fig, ax = plt.subplots(figsize=(6.4, 4.2))
        for (src, m) in sorted({k[:2] for k in overall}):
            gs = sorted(k[2] for k in overall if k[:2] == (src, m))
            ys = [overall[(src, m, g)].get(key, math.nan) * scale for g in gs]
            ax.plot(gs, ys, "o-" if src == "alone" else "s--", label=f"{m} ({src})")
        ax.set_xscale("log", base=2)
        ax.set_xlabel("guides")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(out / fname, dpi=110)
        plt.close(fig)
    cost = [c for c in results.get("cost") or [] if c["total_ms"] is not None]
    if cost:
        fig, ax = plt.subplots(figsize=(6.4, 4.2))
        sizes = sorted({c["strands"] for c in cost})
        dense = {c["strands"]: c["dense_ms"] for c in cost}
        ax.plot(sizes, [dense[s] for s in sizes], "k-o", label="dense simulation")
        for g, m in sorted({(c["guides"], c["method"]) for c in cost}):
            pts = sorted((c["strands"], c["total_ms"]) for c in cost if (c["guides"], c["method"]) == (g, m))
            ax.plot([p[0] for p in pts], [p[1] for p in pts], "o--", label=f"G={g} + {m}")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("dense strands")
        ax.set_ylabel("ms/frame")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(out / "cost.png", dpi=110)
        plt.close(fig)


def write(results: dict, out: Path) -> Path:
    """Write ``out/leaderboard.md`` and the plots; returns the leaderboard's path."""
    out = Path(out)
    page = out / "leaderboard.md"
    tmp = page.with_name(page.name + ".tmp")
    tmp.write_text(leaderboard(results))
    tmp.replace(page)
    _plots(results, out)
    return page


if __name__ == "__main__":
    import json

    folder = Path(sys.argv[1] if len(sys.argv) > 1 else ".")
    print(write(json.loads((folder / "results.json").read_text()), folder))
