"""The interpolation benchmark: score guide-to-dense methods against dense simulation.

``ams-torch bench-interp DATASET_OR_SUITE --methods skinning,upsampler,pkg.mod:factory --guides 64,256 --out DIR``
runs :func:`run`:

1. the source is a dataset of ``ams-torch generate`` (a folder or a file), or a suite name of
   ``datasets/bench/`` (``mini``, ``standard``, ``full``: a recipe or a folder of recipes), which is
   generated first into ``DIR/data/<recipe>`` (resumably, like ``generate``);
2. for every dataset, guide count G and method: ``fit`` on the train split (learned methods
   cache their model under ``DIR/models``), then ``predict`` every sequence of every held-out
   split (whole sequences), with the guides simulated alone as input (``--guide-source alone``,
   the default; ``dense`` scores the dense run's own copies of the guides: pure interpolation
   error; ``both`` scores both);
3. every prediction is checked (shape, finiteness) and scored with :func:`baselines.metrics.sequence_metrics`;
   the row is added to ``DIR/results.json`` at once (atomically), so a killed run resumes where it
   stopped;
4. the cost (:mod:`baselines.cost`): ms/frame of the guides simulated alone + each method next to
   the dense simulation, on the same device, at the strand counts of ``--cost-sizes``;
5. ``DIR/leaderboard.md`` and plots (:mod:`baselines.report`).

Every row carries the method, G, guide source, dataset, split and sequence; the file carries the
provenance (commit, versions, backend, device, machine, dataset checksums, the command).
"""
from __future__ import annotations

import hashlib
import json
import os
import re
import time
from pathlib import Path
from typing import Callable, Dict, List, Optional, Sequence

import torch

from baselines.protocol import MethodError, NotApplicable, check_prediction, describe, resolve_method, safe_name
from baselines.scene import make_sample

__all__ = ["run", "resolve_source", "suite_path", "dataset_info", "provenance", "BenchError", "SUITES_DIR",
           "RESULTS", "GUIDE_SOURCES"]

SUITES_DIR = Path(__file__).resolve().parents[1] / "datasets" / "bench"
RESULTS = "results.json"
GUIDE_SOURCES = ("alone", "dense")
SCHEMA = 1


class BenchError(ValueError):
    """The benchmark cannot run as asked (a dataset without guides, an unknown suite, ...)."""


# -- sources ----------------------------------------------------------------------------------
def suite_path(name: str) -> Path:
    """The suite ``name`` of ``datasets/bench/``: ``<name>.toml`` (one recipe) or the folder
    ``<name>/`` (a recipe per track)."""
    for p in (SUITES_DIR / f"{name}.toml", SUITES_DIR / name):
        if p.exists():
            return p
    known = sorted({p.stem for p in SUITES_DIR.glob("*.toml")} | {p.name for p in SUITES_DIR.iterdir() if p.is_dir()}) \
        if SUITES_DIR.is_dir() else []
    raise BenchError(f"{name!r} is neither a dataset (no such file or folder) nor a suite of {SUITES_DIR} "
                     f"(suites: {', '.join(known) or 'none'})")


def resolve_source(source: str, out: Path, device=None, log: Callable[[str], None] = print,
                   progress: bool = True) -> List[tuple]:
    """[(name, dataset path)]: a dataset file or folder, a generated suite's folder (each dataset
    sub-folder), or a suite name of ``datasets/bench/`` generated first into ``out/data`` (resumes
    like ``generate``; a recipe that needs absent assets is skipped with a message)."""
    from ams_torch.apps.data.format import list_datasets

    if os.path.isfile(source):
        return [(Path(source).stem, Path(source))]
    if os.path.isdir(source):
        return [(Path(p).name, Path(p)) for p in list_datasets(source)]
    suite = suite_path(source)
    dev = None if device is None else str(device)
    data = out / "data"
    if suite.is_file():
        from ams_torch.apps.datagen import generate
        from ams_torch.apps.recipe import load_recipe

        recipe = load_recipe(str(suite))
        generate(recipe, str(data / recipe.name), device=dev, progress=progress, log=log)
        return [(recipe.name, data / recipe.name)]
    from ams_torch.apps.datagen.suite import generate_suite

    names = generate_suite(str(suite), str(data), device=dev, progress=progress, log=log)
    if not names:
        raise BenchError(f"suite {source!r}: none of its recipes can run here")
    return [(n, data / n) for n in sorted(names)]


# -- dataset facts ----------------------------------------------------------------------------
def dataset_info(path: Path) -> dict:
    """What the benchmark needs to know of a dataset before opening it: ``checksum`` (SHA-256 over
    the recipe digest and every sequence's stored checksum), ``splits`` with their sequence
    counts, ``guides_alone`` (the guide counts simulated alone), ``guides_max`` (how many dense
    copies of guides are stored), ``recipe``."""
    from ams_torch.apps.data.format import list_files, open_dataset

    h = hashlib.sha256()
    splits: Dict[str, int] = {}
    alone, gmax, recipe = None, 0, None
    for p in list_files(str(path)):
        with open_dataset(p) as f:
            recipe = recipe or str(f.attrs.get("recipe_name", ""))
            h.update(str(f.attrs.get("recipe_digest", "")).encode())
            for name in sorted(k for k in f.keys() if k.startswith("seq_")):
                g = f[name]
                h.update(f"{name}:{g.attrs.get('checksum', '')}".encode())
                have = {int(m.group(1)) for k in g.keys() for m in [re.fullmatch(r"guides_alone_(\d+)", k)] if m}
                alone = have if alone is None else alone & have
                if "guide_indices" in g:
                    gmax = int(g["guide_indices"].shape[0]) if gmax == 0 else min(gmax, int(g["guide_indices"].shape[0]))
                sp = str(g.attrs.get("split", ""))
                splits[sp] = splits.get(sp, 0) + 1
    return {"checksum": h.hexdigest(), "splits": splits, "guides_alone": sorted(alone or ()), "guides_max": gmax,
            "recipe": recipe}


def _check_guides(name: str, info: dict, guides: Sequence[int], sources: Sequence[str]) -> None:
    if info["guides_max"] == 0:
        raise BenchError(f"dataset {name!r} stores no guide strands: generate it from a recipe with "
                         f"`[store] guides = [64, 256]` (the guide counts to score)")
    for g in guides:
        if g > info["guides_max"]:
            raise BenchError(f"dataset {name!r} stores {info['guides_max']} guides; --guides {g} needs more "
                             f"(recipe key [store] guides)")
        if "alone" in sources and g not in info["guides_alone"]:
            raise BenchError(f"dataset {name!r}: the guides were simulated alone for G in {info['guides_alone'] or 'none'}, "
                             f"not G = {g}: add {g} to the recipe's [store] guides, or score the dense run's copies "
                             f"(--guide-source dense)")


# -- provenance -------------------------------------------------------------------------------
def _git(*args) -> Optional[str]:
    import subprocess

    try:
        r = subprocess.run(["git", *args], cwd=Path(__file__).resolve().parents[1], capture_output=True, text=True,
                           timeout=10)
        return r.stdout.strip() if r.returncode == 0 else None
    except (OSError, subprocess.SubprocessError):
        return None


def _cpu_name() -> str:
    import platform

    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def provenance(device, command: Optional[List[str]] = None) -> dict:
    """Commit (and whether the tree had changes), library/torch/Python versions, the native
    backends built, the device and machine, threads, load average, date and the command."""
    import platform
    import sys

    import ams_torch as at

    dev = torch.device(device)
    dirty = _git("status", "--porcelain", "--untracked-files=no")
    out = {"commit": _git("rev-parse", "HEAD"), "tree_changed": bool(dirty) if dirty is not None else None,
           "ams_torch": at.__version__, "torch": torch.__version__, "python": platform.python_version(),
           "device": torch.cuda.get_device_name(dev) if dev.type == "cuda" else f"CPU: {_cpu_name()}",
           "cpu": _cpu_name(), "cores": os.cpu_count(), "threads": torch.get_num_threads(),
           "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
           "platform": platform.platform(), "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
           "command": command if command is not None else sys.argv}
    try:
        status = at.native_status()
        out["native"] = {k: ("built" if v.get("built") else v.get("reason")) for k, v in status.items()
                         if isinstance(v, dict) and v.get("attempted")}
    except Exception as err:  # noqa: BLE001 - provenance must not stop a run
        out["native"] = f"unknown ({err})"
    return out


# -- results file -----------------------------------------------------------------------------
def _atomic_json(path: Path, data) -> None:
    tmp = path.with_name(f"{path.name}.tmp{os.getpid()}")
    with open(tmp, "w") as fh:
        json.dump(data, fh, indent=1, default=float, allow_nan=True)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


def _load_results(path: Path) -> dict:
    if not path.exists():
        return {"schema": SCHEMA, "rows": [], "cost": [], "datasets": {}, "runs": []}
    try:
        data = json.loads(path.read_text())
    except ValueError as err:
        raise BenchError(f"{path}: not a results file of bench-interp ({err}); remove it or choose another --out") from None
    if data.get("schema") != SCHEMA:
        raise BenchError(f"{path}: results schema {data.get('schema')!r}, this library writes {SCHEMA}; use another --out")
    return data


def _key(row: dict) -> tuple:
    return (row["dataset"], row["method"], row["guides"], row["guide_source"], row["split"], row["sequence"])


# -- the run ----------------------------------------------------------------------------------
def _open(path: Path, split, guides: int, source: str, window=None):
    """The split of a dataset as benchmark samples of G guides (whole sequences by default)."""
    from ams_torch.apps.data import HairSequenceDataset

    return HairSequenceDataset(str(path), window=window, split=split, guides=guides, guide_source=source)


def _predict(method, spec: str, sample: dict, device) -> tuple:
    """(prediction (T, S, N, 3), ms per frame of the method) for one sample."""
    cuda = torch.device(device).type == "cuda"
    if cuda:
        torch.cuda.synchronize(device)
    t0 = time.perf_counter()
    with torch.no_grad():
        out = method.predict(sample)
    if cuda:
        torch.cuda.synchronize(device)
    ms = (time.perf_counter() - t0) * 1e3 / sample["guide_positions"].shape[0]
    return check_prediction(spec, out, sample), ms


def _reference_rows(name: str, path: Path, split: str, g: int, source: str, sample: dict, ref: torch.Tensor,
                    dense_guides: Optional[torch.Tensor]) -> List[dict]:
    """Rows that describe the data itself: the dense reference's own penetration ("dense"), and
    how far the guide input is from the dense run's guides ("guide input")."""
    from baselines.metrics import sequence_metrics

    base = {"dataset": name, "guides": g, "guide_source": source, "split": split, "sequence": int(sample["sequence"])}
    rows = [dict(base, method="(dense reference)", **{k: v for k, v in sequence_metrics(ref, ref, sample).items()})]
    if dense_guides is not None:
        gi = sample["guide_index"]
        sub = dict(sample, num_pinned=sample["num_pinned"][gi], colliders=[], collider_poses=[], head_collider=-1)
        m = sequence_metrics(sample["guide_positions"], dense_guides, sub)
        rows.append(dict(base, method="(guide input vs dense copies)", **m))
    return rows


def run(source: str, methods: Sequence[str], guides: Sequence[int], out: str, *, train: bool = False,
        retrain: bool = False, device="cpu", guide_source: str = "alone", splits: Optional[Sequence[str]] = None,
        options: Optional[Dict[str, dict]] = None, cost_sizes: Sequence[int] = (10_000, 100_000),
        cost_frames: int = 3, cost_dataset: Optional[str] = None, progress: bool = True,
        log: Callable[[str], None] = print, command: Optional[List[str]] = None) -> dict:
    """Run the benchmark (see the module docstring). Returns the results dict written to
    ``out/results.json``.

    Args:
        source: a dataset path or a suite name. methods: method specs (built-in names,
            ``package.module:factory`` or entry-point names). guides: guide counts G.
        out: output folder (created). train: fit learned methods that have no trained model in
            ``out/models`` yet (without it such a method is an error); retrain: fit them even when
            they have one. device: where methods and the cost runs execute.
        guide_source: "alone" (default), "dense" or "both". splits: the held-out splits to score
            (default: every split of the dataset except train and valid).
        options: per-method keyword options, ``{method spec: {key: value}}``, given to its factory.
        cost_sizes: dense strand counts of the cost measurement (empty: none). cost_dataset: the
            dataset (name in the suite) whose scene the cost measurement regrows (default: the first).
    """
    from baselines import cost, report

    if not methods:
        raise BenchError("give at least one method (--methods)")
    if not guides or any(int(g) < 1 for g in guides):
        raise BenchError(f"--guides must be positive integers; got {list(guides)}")
    sources = GUIDE_SOURCES if guide_source == "both" else (guide_source,)
    if any(s not in GUIDE_SOURCES for s in sources):
        raise BenchError(f"--guide-source must be alone, dense or both; got {guide_source!r}")
    device = torch.device(device)
    outp = Path(out)
    outp.mkdir(parents=True, exist_ok=True)
    results_path = outp / RESULTS
    results = _load_results(results_path)
    results["runs"].append(provenance(device, command))
    datasets = resolve_source(source, outp, device=device, log=log, progress=progress)
    if cost_sizes and cost_dataset is not None and cost_dataset not in dict(datasets):
        raise BenchError(f"--cost-dataset {cost_dataset!r} is not a dataset of this run ({[n for n, _ in datasets]})")
    options = options or {}
    done = {_key(r) for r in results["rows"]}
    for name, path in datasets:
        info = dataset_info(path)
        _check_guides(name, info, guides, sources)
        old = results["datasets"].get(name)
        if old is not None and old["checksum"] != info["checksum"]:
            raise BenchError(f"{results_path} holds results of another dataset named {name!r} (checksum "
                             f"{old['checksum'][:12]} vs {info['checksum'][:12]}): use another --out")
        results["datasets"][name] = dict(info, path=str(path))
        held_out = list(splits) if splits else [s for s in sorted(info["splits"]) if s not in ("train", "valid")]
        missing = [s for s in held_out if s not in info["splits"]]
        if missing or not held_out:
            raise BenchError(f"dataset {name!r} has splits {info['splits']}; cannot score {missing or 'a held-out split'}")
        for g in guides:
            for spec in methods:
                method = _fitted(spec, name, path, int(g), info, outp, train, retrain, device, options.get(spec, {}),
                                 log)
                _drop_other_models(results, done, name, spec, int(g), getattr(method, "model_id", None), log)
                for src in sources:
                    for split in held_out:
                        _score_split(method, spec, name, path, split, int(g), src, device, results, done,
                                     results_path, progress)
    if cost_sizes:
        named = dict(datasets)
        cost_name = cost_dataset if cost_dataset is not None else datasets[0][0]
        log(f"cost: the scene of dataset {cost_name!r}")
        results["cost_dataset"] = cost_name
        results["cost"] = cost.measure(named[cost_name], methods, guides, cost_sizes, device=device,
                                       frames=cost_frames, options=options, log=log, models=outp / "models")
    _atomic_json(results_path, results)
    report.write(results, outp)
    return results


def _fitted(spec: str, name: str, path: Path, g: int, info: dict, outp: Path, train: bool, retrain: bool, device,
            opts: dict, log: Callable[[str], None]):
    """The method ``spec`` ready to predict with G guides. A learned method keeps its trained model
    in ``outp/models/<dataset>/<method>-G<g>.pt``: loaded when there (unless ``retrain``), else
    fitted on the train split when ``train``, else an error saying to pass --train."""
    ckpt = outp / "models" / safe_name(name) / f"{safe_name(spec)}-G{g}.pt"
    ckpt.parent.mkdir(parents=True, exist_ok=True)
    if retrain and ckpt.exists():
        ckpt.unlink()
    try:
        method = resolve_method(spec, {"device": device, "checkpoint": str(ckpt)}, **opts)
    except TypeError as err:  # e.g. an option its factory does not take
        raise MethodError(f"method {spec!r}: its factory failed ({err})") from None
    learned = bool(getattr(method, "learned", False))
    if learned and not ckpt.exists():
        if not train:
            raise BenchError(f"method {spec!r} is learned and has no trained model for dataset {name!r}, G = {g} "
                             f"({ckpt}): pass --train to fit it on the train split")
        if "train" not in info["splits"]:
            raise BenchError(f"dataset {name!r} has no train split (splits: {sorted(info['splits'])}): {spec!r} "
                             f"cannot be fitted")
        log(f"fit {spec} on {name} (G = {g})")
    t0 = time.perf_counter()
    source = "alone" if g in info["guides_alone"] else "dense"
    train_ds = _open(path, "train", g, source, window=None) if "train" in info["splits"] else None
    valid_ds = _open(path, "valid", g, source, window=None) if "valid" in info["splits"] else None
    gidx = train_ds[0]["guide_index"] if train_ds is not None else None
    fitted = method.fit(train_ds, gidx, valid=valid_ds)
    method = fitted if fitted is not None else method
    if learned:
        log(f"  {spec} ready in {time.perf_counter() - t0:.1f} s")
    return method


def _drop_other_models(results: dict, done: set, name: str, spec: str, g: int, model: Optional[str],
                       log: Callable[[str], None]) -> None:
    """Forget the rows of ``spec`` on dataset ``name`` with G guides that another trained model
    scored (e.g. before training resumed under a larger step cap), so they are scored again with
    ``model`` (a learned method's ``model_id``; None: nothing to check)."""
    if model is None:
        return
    stale = [r for r in results["rows"] if r["dataset"] == name and r["method"] == spec and r["guides"] == g
             and r.get("model") != model]
    if not stale:
        return
    log(f"  {spec} on {name} (G = {g}): {len(stale)} rows came from another trained model; scoring them again")
    ids = {id(r) for r in stale}
    results["rows"] = [r for r in results["rows"] if id(r) not in ids]
    for r in stale:
        done.discard(_key(r))


#: results.json is rewritten at most this often while a split is scored (and at the end of each
#: split): a kill loses at most this much scoring; resuming skips the saved rows
SAVE_EVERY_S = 20.0
_LAST_SAVE = [0.0]


def _score_split(method, spec: str, name: str, path: Path, split: str, g: int, src: str, device, results: dict,
                 done: set, results_path: Path, progress: bool) -> None:
    from baselines.metrics import sequence_metrics

    ds = _open(path, split, g, src)
    dense_ds = _open(path, split, g, "dense") if src == "alone" else None
    bar = range(len(ds))
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(bar, desc=f"{spec} G={g} {src} {split}", leave=False)
    for i in bar:
        seq = int(ds.sequences[ds.items[i][0]][2])
        key = (name, spec, g, src, split, seq)
        ref_key = (name, "(dense reference)", g, src, split, seq)
        if key in done and ref_key in done:
            continue
        sample = make_sample(ds[i], ds, device=device)
        ref = sample.pop("positions")
        tags = _tags(ds, seq)
        new = []
        if ref_key not in done:
            dense = dense_ds[i]["guide_positions"].to(ref) if dense_ds is not None else None
            new += _reference_rows(name, path, split, g, src, sample, ref, dense)
        if key not in done:
            base = {"dataset": name, "guides": g, "guide_source": src, "split": split, "sequence": seq}
            try:
                pred, ms = _predict(method, spec, sample, device)
            except NotApplicable as err:  # by design (e.g. a model bound to its training groom)
                new.append({**base, **describe(method), "method": spec, "not_applicable": str(err)})
            else:
                new.append({**base, **sequence_metrics(pred.to(ref), ref, sample), "ms_per_frame_method": ms,
                            **describe(method), "method": spec})
        for row in new:
            row.update(tags)
            results["rows"].append(row)
            done.add(_key(row))
        if time.monotonic() - _LAST_SAVE[0] >= SAVE_EVERY_S:  # rewriting a growing file per row is O(rows²)
            _atomic_json(results_path, results)
            _LAST_SAVE[0] = time.monotonic()
    _atomic_json(results_path, results)  # every split ends saved
    _LAST_SAVE[0] = time.monotonic()


def _tags(ds, seq: int) -> dict:
    """Why a sequence is held out (its ``holdout`` tags: motion, collider, groom_seed, preset; none:
    by the split's shares) and its motion type, for the leaderboard's breakdown."""
    a = ds.sequence_arrays(seq)
    tags = a.get("holdout") or []
    return {"holdout": "+".join(sorted(tags)) if isinstance(tags, list) else str(tags),
            "motion_type": a.get("motion_type", "")}


def parse_options(items: Sequence[str]) -> Dict[str, dict]:
    """``METHOD.KEY=VALUE`` strings (``--option``) → ``{method: {key: value}}``; VALUE is read as
    JSON when it parses (numbers, true/false, lists), else kept as a string."""
    out: Dict[str, dict] = {}
    for item in items:
        m = re.fullmatch(r"(.+)\.([A-Za-z_][A-Za-z0-9_]*)=(.*)", item)
        if not m:
            raise BenchError(f"--option {item!r}: expected METHOD.KEY=VALUE (e.g. upsampler.steps=2000)")
        try:
            value = json.loads(m.group(3))
        except ValueError:
            value = m.group(3)
        out.setdefault(m.group(1), {})[m.group(2)] = value
    return out

