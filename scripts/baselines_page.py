"""docs/baselines.md from a bench-interp run: the leaderboard with the comparisons a reader asks
for (do the learned models beat skinning, and where; where does interpolation pay for itself in
ms), plus the run's results.json and plots under docs/baselines/.

    ams-torch bench-interp standard --methods rigid,nearest,skinning,skinning+pushout,upsampler,temporal,collision,agnostic \\
        --guides 64,256 --guide-source both --train --out out/bench_standard
    python scripts/baselines_page.py out/bench_standard            # → docs/baselines.md, docs/baselines/*
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path
from typing import Optional

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from baselines.report import REFERENCE_ROWS, leaderboard, summarise  # noqa: E402

LEARNED = ("upsampler", "temporal", "collision", "agnostic")


def _pct(a: float, b: float) -> str:
    return f"{100.0 * (a - b) / b:+.1f} %"


def _subset(r: dict) -> str:
    return r["split"] + (f" (held out: {r['holdout']})" if r.get("holdout") else
                         " (by the split's shares)" if r["split"] == "test" else "")


def best_simple(results: dict) -> str:
    """The method without training with the lowest mean error over every held-out sequence (guides
    alone, every G), or ''."""
    rows = [r for r in results["rows"] if r["guide_source"] == "alone" and r["method"] not in REFERENCE_ROWS
            and r["method"] not in LEARNED and r["method"] != "rigid"]
    per = summarise(rows, ("method",))
    ranked = sorted((a["mean_mm"], m) for (m,), a in per.items() if "mean_mm" in a and not a["not_applicable"])
    return ranked[0][1] if ranked else ""


def comparisons(results: dict, baseline: str = "skinning", only=None) -> list:
    """Sentences: each method against ``baseline`` (guides alone), paired on the sequences both
    scored (a learned model is not applicable to grooms of another particle count), overall per G
    and per dataset × held-out subset × G ("where")."""
    rows = [dict(r, subset=_subset(r)) for r in results["rows"] if r["guide_source"] == "alone"]
    seq = lambda r: (r["dataset"], r["split"], r["guides"], r["sequence"])  # noqa: E731
    base = {seq(r): r for r in rows if r["method"] == baseline and "mean_mm" in r}
    lines = []
    for m in [m for m in dict.fromkeys(r["method"] for r in rows) if m not in REFERENCE_ROWS and m != baseline
              and (only is None or m in only)]:
        mine = [r for r in rows if r["method"] == m]
        scored = [r for r in mine if "mean_mm" in r and seq(r) in base]
        paired = scored + [dict(base[seq(r)], method=baseline) for r in scored]
        overall = summarise(paired, ("guides", "method"))
        per = summarise(paired, ("dataset", "subset", "guides", "method"))
        na = len(mine) - len(scored)
        tot = [f"G={g}: {a['mean_mm']:.2f} vs {overall[(g, baseline)]['mean_mm']:.2f} mm "
               f"({_pct(a['mean_mm'], overall[(g, baseline)]['mean_mm'])}, {a['sequences']} sequences)"
               for (g, mm), a in sorted(overall.items()) if mm == m]
        wins, losses = [], []
        for (ds, sub, g, mm), a in sorted(per.items()):
            if mm == m:
                b = per[(ds, sub, g, baseline)]["mean_mm"]
                (wins if a["mean_mm"] < b else losses).append(f"{ds} {sub} G={g} ({_pct(a['mean_mm'], b)})")
        if tot:
            lines.append(f"- **{m}** against {baseline}{f' (on the {len(scored)} sequences it applies to; {na} not applicable)' if na else ''}: "
                         f"{'; '.join(tot)}. Better in {len(wins)} of {len(wins) + len(losses)} (dataset, subset, G) "
                         f"cells: {'; '.join(wins) or 'none'}. Not better: {'; '.join(losses) or 'none'}.")
        elif mine:
            lines.append(f"- **{m}**: not applicable to any held-out sequence.")
    return lines


def ranking(results: dict) -> list:
    """Per G: the methods that apply to every held-out sequence, best mean vertex error first
    (guides alone); learned methods that apply to some sequences only are named apart."""
    rows = [r for r in results["rows"] if r["guide_source"] == "alone" and r["method"] not in REFERENCE_ROWS]
    per = summarise(rows, ("guides", "method"))
    out = []
    for g in sorted({k[0] for k in per}):
        full = sorted(((m, a) for (gg, m), a in per.items() if gg == g and "mean_mm" in a and not a["not_applicable"]),
                      key=lambda t: t[1]["mean_mm"])
        part = [m for (gg, m), a in per.items() if gg == g and a.get("not_applicable")]
        if full:
            out.append(f"- G={g}: " + " < ".join(f"{m} {a['mean_mm']:.2f} mm" for m, a in full) +
                       (f" (every held-out sequence); applicable to some sequences only: {', '.join(part)} "
                        "(compared paired below)" if part else " (every held-out sequence)"))
    return out


def summary(results: dict) -> list:
    """The page's answers in a few lines: the best method without training per G, the learned models
    against it and against skinning (paired), and at which sizes which methods pay for themselves."""
    out = []
    rows = [r for r in results["rows"] if r["guide_source"] == "alone" and r["method"] not in REFERENCE_ROWS]
    per = summarise(rows, ("guides", "method"))
    best = best_simple(results)
    for g in sorted({k[0] for k in per}):
        if (g, best) in per and (g, "skinning") in per:
            out.append(f"- G={g}: `{best}` is the most accurate method without training, {per[(g, best)]['mean_mm']:.2f} mm "
                       f"mean vertex error against skinning's {per[(g, 'skinning')]['mean_mm']:.2f} mm over all "
                       f"{per[(g, best)]['sequences']} held-out sequences.")
    learned = [m for m in dict.fromkeys(r["method"] for r in rows) if m in LEARNED]
    if learned and best:
        seq = lambda r: (r["dataset"], r["split"], r["guides"], r["sequence"])  # noqa: E731
        idx = {(seq(r), r["method"]): r["mean_mm"] for r in rows if "mean_mm" in r}
        for m in learned:
            mine = [k for (k, mm) in idx if mm == m]
            if not mine:
                continue
            for base in ("skinning", best):
                pairs = [(idx[(k, m)], idx[(k, base)]) for k in mine if (k, base) in idx]
                wins = sum(a < b for a, b in pairs)
                out.append(f"- `{m}` is better than `{base}` on "
                           f"{wins} of {len(pairs)} sequences it applies to "
                           f"({sum(a for a, _ in pairs) / len(pairs):.2f} vs {sum(b for _, b in pairs) / len(pairs):.2f} mm).")
    sizes = sorted({c["strands"] for c in results.get("cost") or []})
    for sz in sizes:
        cs = [c for c in results["cost"] if c["strands"] == sz and c["total_ms"] is not None]
        if not cs:
            continue
        pay = [f"`{c['method']}` {c['speedup']:.1f}×" for c in sorted(cs, key=lambda c: -c["speedup"]) if c["speedup"] > 1]
        no = [f"`{c['method']}`" for c in cs if c["speedup"] <= 1]
        out.append(f"- S = {sz:,} (dense {cs[0]['dense_ms']:.0f} ms/frame on {cs[0]['device']}): pays for itself: "
                   f"{', '.join(pay) or 'none'}; does not: {', '.join(no) or 'none'}.")
    return out


def guide_gap(results: dict) -> list:
    """How far the guides simulated alone are from the dense run's copies (per dataset and G), and
    skinning's error with either input when both were scored."""
    rows = [r for r in results["rows"] if r["method"] == "(guide input vs dense copies)"]
    per = summarise(rows, ("dataset", "guides"))
    out = [f"- {ds}, G={g}: guides alone vs the dense run's copies {a['mean_mm']:.2f} mm mean, "
           f"{a['p95_mm']:.2f} mm p95" for (ds, g), a in sorted(per.items()) if "mean_mm" in a]
    sk = summarise([r for r in results["rows"] if r["method"] == "skinning"], ("guide_source", "guides"))
    for g in sorted({k[1] for k in sk}):
        if ("alone", g) in sk and ("dense", g) in sk:
            a, d = sk[("alone", g)]["mean_mm"], sk[("dense", g)]["mean_mm"]
            out.append(f"- skinning, G={g}: {a:.2f} mm from guides simulated alone, {d:.2f} mm from the dense run's "
                       f"copies ({_pct(a, d)}): the share of the error that is the guides' own, not interpolation")
    return out


def pays_off(results: dict) -> list:
    lines = []
    for c in results.get("cost") or []:
        if c["total_ms"] is None:
            lines.append(f"- S = {c['strands']}, G = {c['guides']}, {c['method']}: not measurable ({c['note']}).")
            continue
        verdict = "pays for itself" if c["speedup"] > 1 else "costs more than simulating every strand"
        lines.append(f"- S = {c['strands']}, G = {c['guides']}, {c['method']}: {c['total_ms']:.1f} ms/frame "
                     f"(guides {c['guides_ms']:.1f} + method {c['method_ms']:.1f}) against dense {c['dense_ms']:.1f}: "
                     f"{c['speedup']:.2f}×, {verdict}.")
    return lines


def _blobs(run: Path) -> list:
    """(checkpoint blob, path) of every readable learned model of a run."""
    from baselines.learned.train import load_blob

    out = []
    for f in sorted((run / "models").glob("*/*.pt")):
        try:
            out.append((load_blob(str(f)), f))
        except (ValueError, OSError, RuntimeError):
            continue
    return out


def budget(run: Optional[Path]) -> str:
    """How to read the learned rows: which methods' models all stopped early (validation stalled:
    trained to convergence) and which stopped at the run's step cap (a lower bound)."""
    if run is None:
        return ""
    early, capped = {}, {}
    for b, _ in _blobs(run):
        (early if b["stopped"] == "early" else capped).setdefault(b["method"], 0)
        (early if b["stopped"] == "early" else capped)[b["method"]] += 1
    conv = sorted(m for m in early if m not in capped)
    cap = sorted(capped)
    parts = []
    if conv:
        parts.append(f"{', '.join(f'`{m}`' for m in conv)}: every model stopped early, its validation loss stalled "
                     f"(trained to convergence)")
    if cap:
        parts.append(f"{', '.join(f'`{m}`' for m in cap)}: stopped at the run's step cap (a compute budget: not "
                     f"converged, so their rows are a lower bound on what the method can do)")
    return "; ".join(parts) + "."


def training(run: Path) -> list:
    """A table of the learned models of a run (``run/models/<dataset>/<method>-G<g>.pt``): steps run
    and the cap, the best validation step and loss (mm², the untrained model's for scale), and
    whether training stopped early (validation stalled) or at the step cap (not converged)."""

    rows = []
    for b, f in _blobs(run):
        valid = b["history"].get("valid") or []
        start = valid[0]["loss"] if valid else float("nan")
        cap = b["train_options"]["steps"]
        how = "early (validation stalled)" if b["stopped"] == "early" else (
            "at the step cap: not converged" if b["best_step"] >= cap - b["train_options"]["valid_every"]
            else "at the step cap (best before the last validations)")
        rows.append(f"| {f.parent.name} | {b['method']} | {b['guides'].numel()} | {b['steps']} / {cap} | "
                    f"{b['best_step']} | {b['best_valid']:.1f} | {start:.1f} | {how} |")
    if not rows:
        return []
    return ["| dataset | method | G | steps / cap | best step | best valid loss (mm²) | untrained (mm²) | stopped |",
            "|---|---|---|---|---|---|---|---|"] + rows


def page(results: dict, wall: str, run_dir: Path = None) -> str:
    board = leaderboard(results).replace("](", "](baselines/")
    body = board.split("\n", 1)[1]
    out = ["# Guide-strand interpolation: the benchmark", "",
           "Generated from the `standard` suite (`datasets/bench/`) by these `bench-interp` runs into one "
           "output folder (each resumes the rows already there, so later runs add methods, guide counts or "
           "the cost measurement):", ""]
    seen = []
    for r in results["runs"]:
        cmd = " ".join(r.get("command") or [])
        if cmd and cmd not in seen:
            seen.append(cmd)
            out.append(f"- `{cmd}` (commit {str(r.get('commit', '?'))[:10]}, {r.get('date', '?')})")
    out += ["", f"{f'({wall}) ' if wall else ''}Then `python scripts/baselines_page.py`. Raw rows: "
           "`docs/baselines/results.json`. How to run it and plug in your own method: README, section "
           "*The interpolation benchmark*.", "",
           "## In short", ""]
    out += summary(results)
    out += ["", f"Read the learned rows with their training (the *Training* table): {budget(run_dir)} Each takes "
            "one particle count N (the largest group of its train split; the suite mixes N = 8–40), so it is scored on "
            "the sequences of that N only, and every learned model here starts from skinning's output, which `blend` "
            "and `nearest` beat. "
            "Cost rows: the guide counts given to the cost run, on the CPU; a GPU changes the learned models' cost "
            "most."]
    out += ["", "## Against skinning: which methods beat it, and where", "",
           "Guides simulated alone (what a game or film pipeline runs); mean vertex error over every held-out "
           "sequence, then per dataset and held-out subset (why the sequences are held out: an unseen groom, "
           "motion or collider):", ""]
    out += ranking(results)
    out += [""] + (comparisons(results) or ["- no learned method was run."])
    best = best_simple(results)
    if best and best != "skinning":
        learned = [m for m in dict.fromkeys(r["method"] for r in results["rows"]) if m in LEARNED]
        if learned:
            out += ["", f"## The learned models against the best method that learns nothing ({best})", "",
                    f"`{best}` has the lowest mean error of the methods without training (over every held-out "
                    "sequence, every G); the learned models paired with it on the sequences they apply to:", ""]
            out += comparisons(results, baseline=best, only=learned)
    table = training(run_dir) if run_dir is not None else []
    if table:
        out += ["", "## Training of the learned models", "",
                "Each learned model is trained on its dataset's train split (one model per dataset and G), "
                "validated on its valid split every `valid_every` steps with early stopping, under the step cap "
                "of the run's `--option` flags (a compute budget: a model that stops at the cap with its best "
                "validation at the end is not converged, and its row in the leaderboard is a lower bound on "
                "what the method can do). Validation loss: mean squared vertex error (mm²) over the validation "
                "windows; *untrained* is the model at step 0 (its output starts at skinning).", ""] + table
    out += ["", "## Guides simulated alone against the dense run's copies", ""]
    out += guide_gap(results) or ["- not measured in this run."]
    out += ["", "## Where does interpolation pay for itself?", ""]
    out += pays_off(results) or ["- no cost measurement in this run."]
    out += ["", body]
    return "\n".join(out)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", help="the --out folder of a bench-interp run")
    ap.add_argument("--docs", default=str(ROOT / "docs"))
    ap.add_argument("--wall", default="", help="wall time of the run, for the page (e.g. '24 min on 2 cores')")
    args = ap.parse_args(argv)
    run, docs = Path(args.run), Path(args.docs)
    results = json.loads((run / "results.json").read_text())
    (docs / "baselines").mkdir(parents=True, exist_ok=True)
    for old in (docs / "baselines").glob("*.png"):
        old.unlink()
    for f in run.glob("*.png"):
        shutil.copy2(f, docs / "baselines" / f.name)
    # one row per line: small diffs when a later run rescoring some methods is committed
    rows = ",\n".join(json.dumps(r, separators=(",", ":")) for r in results["rows"])
    rest = json.dumps({k: v for k, v in results.items() if k != "rows"}, separators=(",", ":"))
    (docs / "baselines" / "results.json").write_text('{"rows":[\n' + rows + "\n]," + rest[1:] + "\n")
    (docs / "baselines.md").write_text(page(results, args.wall, run))
    print(f"wrote {docs / 'baselines.md'}")


if __name__ == "__main__":
    main()
