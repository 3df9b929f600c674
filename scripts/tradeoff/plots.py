"""The figures of docs/tradeoff.md: error against cost per scene, error against substeps."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from tradeoff.choose import ms, pareto
from tradeoff.scenes import BASE, setting_key

AXIS_STYLE = {"base": ("k", "*", "base (library default)"), "substeps": ("tab:blue", "o", "substeps M"),
              "particles": ("tab:orange", "s", "particles N"), "dtype": ("tab:green", "D", "float64"),
              "grid": ("tab:purple", "^", "hair–hair grid"), "stages": ("tab:red", "v", "a stage off"),
              "joint": ("0.6", ".", "joint M × N"), "joint_gs": ("tab:olive", "x", "joint M × N, geometric stiffness"),
              "preset": ("tab:cyan", "P", "preset")}


def _axis_of(r: dict) -> str:
    s = r["settings"]
    if setting_key(s) == setting_key(dict(BASE, grid=s.get("grid") and BASE["grid"], off=[])):
        return "base"
    for a in ("stages", "dtype", "grid", "substeps", "particles", "preset"):
        if a in r["axes"]:
            return a
    return "joint_gs" if s.get("gs") else "joint"


def _log_axes(ax) -> None:
    from matplotlib.ticker import FuncFormatter, NullFormatter

    ax.set_xscale("log")
    ax.set_yscale("log")
    for axis in (ax.xaxis, ax.yaxis):
        axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        axis.set_minor_formatter(NullFormatter())


def plot_pareto(records: list[dict], infos: list[dict], path: Path) -> None:
    """RMS error against native ms/frame per scene, log–log, with the Pareto front, the presets
    and the reference's resolution (its difference to its checks) as a dashed line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = [i["scene"] for i in infos]
    fig, axes = plt.subplots(1, len(scenes), figsize=(5.0 * len(scenes), 4.3), squeeze=False)
    for ax, info in zip(axes[0], infos):
        sc = info["scene"]
        rs = [r for r in records if r["scene"] == sc and r.get("rms_error_mm") is not None and ms(r) is not None]
        seen = set()
        for r in rs:
            a = _axis_of(r)
            color, marker, label = AXIS_STYLE[a]
            ax.scatter(ms(r), r["rms_error_mm"], c=color, marker=marker, s=60 if a == "base" else 28,
                       label=label if a not in seen else None, zorder=3)
            seen.add(a)
            if a == "stages":
                ax.annotate("−" + r["settings"]["off"][0], (ms(r), r["rms_error_mm"]), fontsize=6,
                            xytext=(3, -8), textcoords="offset points", color="tab:red")
        pts = [(ms(r), r["rms_error_mm"]) for r in rs]
        front = pareto(pts)
        ax.step([pts[i][0] for i in front], [pts[i][1] for i in front], where="post", color="k", lw=0.8, alpha=0.6,
                label="Pareto front", zorder=2)
        for r in rs:
            for p in r.get("presets", []):
                ax.scatter(ms(r), r["rms_error_mm"], s=160, facecolors="none", edgecolors="k", lw=1.2, zorder=4)
                ax.annotate(p, (ms(r), r["rms_error_mm"]), fontsize=8, fontweight="bold", xytext=(6, 4),
                            textcoords="offset points")
        floor = max((c["rms_error_mm"] for c in info.get("checks", []) if c.get("rms_error_mm")), default=None)
        if floor:
            ax.axhline(floor, color="tab:red", ls="--", lw=0.8, label="reference vs its checks")
        _log_axes(ax)
        ax.set_xlabel("ms / frame (native path, CPU, 1 thread)")
        ax.set_ylabel("RMS error vs reference (mm)")
        ax.set_title(sc + ("" if info.get("votes") else " (does not vote)"))
        ax.grid(True, which="both", alpha=0.25)
    handles, labels = [], []
    for ax in axes[0]:
        for h, lab in zip(*ax.get_legend_handles_labels()):
            if lab not in labels:
                handles.append(h)
                labels.append(lab)
    fig.legend(handles, labels, loc="lower center", ncol=5, fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.12, 1, 1))
    fig.savefig(path, dpi=90)
    plt.close(fig)


def plot_convergence(slopes: dict, path: Path) -> None:
    """RMS error against substeps M, log–log, per scene: against the same-N time reference (solid,
    the time discretisation alone) and against the full reference (dotted), with a slope −1 guide."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.0, 4.4))
    for k, (sc, d) in enumerate(slopes.items()):
        color = f"C{k}"
        t = [(m, e) for m, e in zip(d["substeps"], d["time_rms_error_mm"]) if e]
        if t:
            slope = f"slope {d['slope']:.2f}" if d["slope"] is not None else ""
            ax.plot([a for a, _ in t], [b for _, b in t], "o-", color=color, label=f"{sc}: vs same-N time ref. ({slope})")
        ax.plot(d["substeps"], d["rms_error_mm"], "s:", color=color, alpha=0.7, label=f"{sc}: vs reference")
    firsts = [d["time_rms_error_mm"][0] for d in slopes.values() if d["time_rms_error_mm"][0]]
    if firsts:
        m = np.array(next(iter(slopes.values()))["substeps"], dtype=float)
        ax.plot(m, min(firsts) / m, "k--", lw=0.8, label="slope −1")
    _log_axes(ax)
    if slopes:
        ax.set_xticks(next(iter(slopes.values()))["substeps"])
    ax.set_xlabel("substeps M")
    ax.set_ylabel("RMS error (mm)")
    ax.set_title(f"Error against substeps (N = {BASE['particles']}, float32)", fontsize=10)
    ax.grid(True, which="both", alpha=0.25)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
