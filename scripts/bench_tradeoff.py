"""The speed–accuracy trade: error against a resolved reference and ms/frame on both paths.

Scenes (default sizes; ``--quick`` shrinks them):

    wisp            16 strands on a bobbing head (the AMS half of
                    datasets/scenes/wisp_comparison.toml), no head mesh, no stages; 120 frames
    head            grown ``straight`` strands on the default head, shaking (0.6 rad at 1.5 Hz),
                    head collisions (64³ SDF) and hair–hair on; 30 frames
    roller_coaster  datasets/scenes/roller_coaster.toml with 300 of its 600 strands (one 4 g
                    loop, head collisions, non-Hookean integrity); 100 frames

Per scene (``scripts/tradeoff/runs.py``): a float64 reference, refined in substeps and
particles beyond every setting (``stiffness_cap`` lifted, see docs/tradeoff.md), and its
checks (half its substeps; fewer particles; half its substeps with geometric stiffness), whose
differences to it say how far it resolves the settings' errors; then the settings: one axis at
a time around the base (the library default: ``Params()``, N = 32, float32, 64³ grid, every
stage on), a joint M × N grid with geometric stiffness off and on, and a same-N float64 *time
reference* for the substeps sweep. Every setting is run over the whole scene on the native
path and compared with the reference at fixed material points, then timed on the native path
(a window of frames mid-run, all settings interleaved, repeated). A scene votes on the presets
only if its reference resolves the errors (``tradeoff.choose.votes``); the presets are picked
(``tradeoff.choose.choose_presets``) and then, with the base and geometric stiffness off/on,
run again with the one-step energy probe (``tradeoff.energy``) and timed on both paths in the
same interleaved repeats.

Writes ``docs/tradeoff.json`` (one record per setting), ``docs/tradeoff.md`` (the run's
metadata rides at its end in an HTML comment), ``docs/tradeoff_pareto.png`` and
``docs/tradeoff_convergence.png``.

    python scripts/bench_tradeoff.py --wait 40       # full run: waits for a quiet machine first
    python scripts/bench_tradeoff.py --quick         # smoke run, a few minutes
    python scripts/bench_tradeoff.py --render-only   # rewrite the doc and plots from the JSON
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "scripts"))

from ams_torch._bench import machine_info, shown_args  # noqa: E402
from tradeoff import choose, plots, report, runs, scenes  # noqa: E402
from tradeoff.timing import thread_setup, wait_until_quiet  # noqa: E402

META_TAG = "bench_tradeoff meta (read by --render-only):"
SCENES = ("wisp", "head", "roller_coaster")


def configure(args) -> None:
    """The sizes of a full run or a ``--quick`` one."""
    q = args.quick
    m_all = (1, 2, 4, 8, 16)
    args.frames = {"wisp": 12, "head": 4, "roller_coaster": 10} if q else {"wisp": 120, "head": 30, "roller_coaster": 100}
    args.strands = {"wisp": 4, "head": 60, "roller_coaster": 30} if q else {"wisp": 16, "head": args.head_strands,
                                                                           "roller_coaster": 300}
    args.substeps = (1, 2, 4) if q else m_all
    args.particles = (16, 32) if q else (8, 16, 32, 64, 128)
    args.dtypes = ("float64",)
    args.grids = (32, 64) if q else (32, 64, 128)
    args.ref_grid = 64 if q else 128
    args.ref_cap = 1e12
    args.ref_substeps = {"wisp": 8, "head": 4, "roller_coaster": 4} if q else {"wisp": 128, "head": args.head_ref_m,
                                                                             "roller_coaster": 64}
    args.ref_particles = {"wisp": 64, "head": 64, "roller_coaster": 64} if q else {"wisp": 512, "head": args.head_ref_n,
                                                                                  "roller_coaster": 256}
    args.ref_check_particles = {k: v // 2 for k, v in args.ref_particles.items()}
    args.ref_checks = 3
    args.ref_strands = {"roller_coaster": 10 if q else 60}
    args.joint = ({sc: ((1, 2), (16, 32)) for sc in SCENES} if q else
                  {"wisp": (m_all, (8, 16, 32, 64, 128)), "head": (m_all, (16, 32, 64)),
                   "roller_coaster": (m_all, (16, 32, 64))})
    args.budgets = {"fast": 0.9, "balanced": 2.5, "accurate": 6.0}
    args.time_ref_substeps = {sc: 8 for sc in SCENES} if q else {sc: 64 for sc in SCENES}
    # timing window: (frames before it, frames timed)
    args.window = ({"wisp": (4, 4), "head": (1, 2), "roller_coaster": (4, 3)} if q else
                   {"wisp": (40, 40), "head": (12, 4), "roller_coaster": (34, 12)})
    args.repeats = 2 if q else 3


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes", nargs="+", default=list(SCENES), choices=SCENES)
    p.add_argument("--quick", action="store_true", help="smoke run: tiny scenes, output under out/tradeoff_quick")
    p.add_argument("--threads", type=int, default=1, help="torch intra-op threads (default 1; 0: torch's default)")
    p.add_argument("--wait", type=float, default=0.0,
                   help="minutes to wait (polling every 60 s) for a quiet machine before starting: 1-minute load < 1.5 "
                        "and no other test suite or script of the project running")
    p.add_argument("--head-strands", type=int, default=500, help="strands of the head scene")
    p.add_argument("--head-ref-n", type=int, default=512, help="particles of the head reference")
    p.add_argument("--head-ref-m", type=int, default=64, help="substeps of the head reference")
    p.add_argument("--out", type=Path, help="output folder (default docs/; --quick: out/tradeoff_quick)")
    p.add_argument("--render-only", action="store_true", help="rewrite tradeoff.md and the plots from tradeoff.json")
    p.add_argument("--note", default="", help="a sentence added to tradeoff.md")
    args = p.parse_args(argv)
    configure(args)
    out = args.out or (REPO / "out" / "tradeoff_quick" if args.quick else REPO / "docs")
    out.mkdir(parents=True, exist_ok=True)
    if args.render_only:
        records = json.loads((out / "tradeoff.json").read_text())
        meta = read_meta(out / "tradeoff.md")
        for k, v in meta["args"].items():
            setattr(args, k, v)
        args.joint = {k: tuple(tuple(x) for x in v) for k, v in args.joint.items()}
        args.window = {k: tuple(v) for k, v in args.window.items()}
        for info in meta["scenes"]:  # the voting rule may have changed since the run: apply today's
            info["votes"] = choose.votes(info, records, args.budgets)
            info.pop("votes_fallback", None)
        if not any(i["votes"] for i in meta["scenes"]):
            meta["scenes"][0]["votes_fallback"] = True
        write_outputs(out, records, meta, args)
        print(f"rewrote {out / 'tradeoff.md'} and the plots from {out / 'tradeoff.json'}")
        return
    t_start = time.perf_counter()

    def log(msg):
        print(f"[{time.perf_counter() - t_start:7.1f} s] {msg}", flush=True)

    quiet = wait_until_quiet(args.wait, log=log) if args.wait > 0 else None
    if quiet is not None:
        log(f"machine {'quiet' if quiet['quiet'] else 'NOT quiet'} after {quiet['waited_s']} s: load {quiet['load_1min']}")
    t_start = time.perf_counter()
    thread_setup(args.threads)
    machine = machine_info()
    loads = [("at the start", machine["load_avg_1min_at_start"])]
    # warm-up: native kernels, SDF cache, allocator
    raw0 = scenes.scene_raw("wisp", 2, 2)
    scenes.run_setting(raw0, scenes.base_setting(raw0, particles=8))
    records, infos, refs, raws = [], [], {}, {}
    for sc in args.scenes:
        raw = raws[sc] = scenes.scene_raw(sc, args.frames[sc], args.strands.get(sc))
        subset = scenes.strand_subset(raw, args.ref_strands.get(sc))
        recs, info, ref_pts = runs.run_scene(sc, raw, args, subset, log)
        records += recs
        infos.append(info)
        refs[sc] = (ref_pts, subset)
        loads.append((f"after {sc}", info["load_avg_1min_at_end"]))
        log(f"[{sc}] done in {info['wall_s']:.0f} s")
    for info in infos:
        info["votes"] = choose.votes(info, records, args.budgets)
    select = [i["scene"] for i in infos if i["votes"]]
    if not select:
        select = [infos[0]["scene"]]
        log(f"no scene's reference resolves its errors: the presets are chosen on {select[0]} alone")
        infos[0]["votes_fallback"] = True
    chosen = choose.choose_presets(records, infos, select, args.budgets)
    lib = choose.library_presets()
    presets = {}
    for name in choose.PRESET_NAMES:
        c = chosen[name]
        presets[name] = {"substeps": c["substeps"], "particles": c["particles"], "dtype": c["dtype"],
                         "grid": c["grid"] or lib[name]["grid"], "gs": c["gs"]}
        log(f"preset {name}: {presets[name]} (cost {c['cost']:.2f}×, error {c['error']:.2f}× the default)")
    phase2 = {}
    for sc in args.scenes:
        phase2[sc] = runs.run_presets(sc, raws[sc], args, presets, records, *refs[sc], log)
        loads.append((f"after the presets of {sc}", phase2[sc]["load_avg_1min_at_end"]))
    wall = time.perf_counter() - t_start
    loads.append(("at the end", round(os.getloadavg()[0], 2)))
    meta = {"command": f"python scripts/bench_tradeoff.py {shown_args(hide=('--note', '--out'))}".strip(),
            "wall_s": round(wall, 1), "machine": machine, "load_avg_1min": loads, "quiet": quiet, "scenes": infos,
            "presets_chosen": chosen, "presets_library": lib, "phase2": phase2,
            "args": {k: getattr(args, k) for k in ("substeps", "particles", "dtypes", "grids", "joint", "budgets",
                                                   "window", "repeats", "note", "frames", "strands")}}
    (out / "tradeoff.json").write_text("[\n" + ",\n".join(json.dumps(r) for r in records) + "\n]\n")
    write_outputs(out, records, meta, args)
    for name in choose.PRESET_NAMES:
        if presets[name] != lib[name]:
            log(f"NOTE: the library's preset {name} is {lib[name]}; this run picks {presets[name]}")
    log(f"wrote {out / 'tradeoff.md'}, tradeoff.json and the plots in {wall / 60:.1f} min")


def read_meta(md: Path) -> dict:
    """The run's metadata from the HTML comment at the end of tradeoff.md."""
    text = md.read_text()
    start = text.rindex("<!-- " + META_TAG) + len("<!-- " + META_TAG)
    return json.loads(text[start:text.index("-->", start)])


def write_outputs(out: Path, records, meta, args) -> None:
    infos, chosen = meta["scenes"], meta["presets_chosen"]
    slopes = runs.convergence_slopes(records, infos)
    plots.plot_pareto(records, infos, out / "tradeoff_pareto.png")
    plots.plot_convergence(slopes, out / "tradeoff_convergence.png")
    path = out / "tradeoff.md"
    report.write_markdown(path, records, infos, chosen, slopes, meta, args)
    blob = json.dumps(meta).replace("--", "-\\u002d")  # "--" cannot occur in an HTML comment
    path.write_text(path.read_text() + f"\n<!-- {META_TAG} {blob} -->\n")


if __name__ == "__main__":
    main()
