"""Validating dataset files and folders: structure, shapes, NaN/Inf, checksums (per array, per
frame, per sequence), masks, the stored head mesh, and that the files make one complete dataset."""
from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence, Tuple, Union

import numpy as np

from ams_torch.apps.data.metadata import duplicate_files, is_hdf5, metadata_problems
from ams_torch.apps.data.format import (FRAME_DIGESTS, PER_FRAME, POSE_FIELDS, SEQ_PREFIX, SPLITS, DatasetError,
                                        alone_count, alone_name, check_together, is_framed, list_files, lock_holder,
                                        open_dataset, read_header, sequence_checksum, sequence_name)

__all__ = ["validate_file", "validate", "ValidationReport"]


# -- validation -------------------------------------------------------------------------------
def _expected_shapes(g, frames: int) -> Dict[str, tuple]:
    s, n = g["rest_positions"].shape[:2]
    guides = int(g["guide_indices"].shape[0]) if "guide_indices" in g else 0
    cols = int(g["collider_rotations"].shape[1]) if "collider_rotations" in g else 0
    return {"positions": (frames, s, n, 3), "velocities": (frames, s, n, 3), "guide_positions": (frames, guides, n, 3),
            "rotations": (frames, 3, 3), "translations": (frames, 3), "linear_velocities": (frames, 3),
            "angular_velocities": (frames, 3), "collider_rotations": (frames, cols, 3, 3),
            "collider_translations": (frames, cols, 3), "root_triangles": (s,), "root_barycentrics": (s, 3),
            "guide_indices": (guides,), "motion_velocities": (frames, s, n, 3), "num_pinned": (s,),
            **{k: (frames, alone_count(k), n, 3) for k in g.keys() if alone_count(k) is not None}}


def _store_counts(store: dict) -> List[int]:
    g = store.get("guides", 0)
    return sorted(int(x) for x in g) if isinstance(g, list) else ([int(g)] if g else [])


def _required(store: dict) -> List[str]:
    req = ["rest_positions"] + [k for k, on in (("positions", store.get("positions", True)),
                                                ("velocities", store.get("velocities", False)),
                                                ("motion_velocities", store.get("motion_velocities", False))) if on]
    counts = _store_counts(store)
    if counts:
        req += ["guide_indices", "guide_positions"]
    if store.get("guides_alone", False):  # format 3 (format 2 stores have no such key)
        req += [alone_name(c) for c in counts]
    if "guides_alone" in store:  # format 3: the pinned prefix of every strand
        req.append("num_pinned")
    return req + (list(POSE_FIELDS) if store.get("poses", True) else [])


def _check_array(g, name: str, key: str) -> Tuple[List[str], Optional[tuple]]:
    """Read one array slab by slab: (problems, checksum entry)."""
    d, problems, bad = g[key], [], 0
    h = hashlib.sha256()
    framed = is_framed(key) and FRAME_DIGESTS in g and key in g[FRAME_DIGESTS]
    stored_frames = g[FRAME_DIGESTS][key][()] if framed else None
    try:
        for k in range(d.shape[0]) if framed else [None]:
            slab = np.ascontiguousarray(d[k] if k is not None else d[()])
            if np.issubdtype(slab.dtype, np.floating):
                bad += int(slab.size - np.count_nonzero(np.isfinite(slab)))
            h.update(slab.tobytes())
            if framed and hashlib.sha256(slab.tobytes()).digest() != stored_frames[k].tobytes():
                problems.append(f"{name}/{key}: frame {k}: checksum mismatch (data changed after writing)")
    except (OSError, ValueError, RuntimeError) as err:
        return [f"{name}/{key}: unreadable (corrupt data): {err}"], None
    if bad:
        problems.append(f"{name}/{key}: {bad} NaN/Inf value(s)")
    if d.attrs.get("sha256") not in (None, h.hexdigest()) and not any("frame" in p for p in problems):
        problems.append(f"{name}/{key}: checksum mismatch (data changed after writing)")
    return problems, (d.dtype.str, d.shape, h.hexdigest())


def _check_sequence(g, name: str, frames: int, store: dict) -> List[str]:
    """Problems of one sequence group (an empty list when it is sound)."""
    missing = [k for k in _required(store) if k not in g]
    if missing:
        return [f"{name}: missing dataset(s) {missing}"]
    problems = [] if "checksum" in g.attrs else [f"{name}: no checksum attribute"]
    if g["rest_positions"].ndim != 3 or g["rest_positions"].shape[-1] != 3:
        return problems + [f"{name}/rest_positions: shape {g['rest_positions'].shape}, expected (S, N, 3)"]
    expect = _expected_shapes(g, frames)
    entries = {}
    for key in sorted(k for k in g.keys() if k != FRAME_DIGESTS):
        d = g[key]
        if key in expect and d.shape != expect[key]:
            problems.append(f"{name}/{key}: " + (f"{d.shape[0] if d.ndim else 0} frames, expected {frames}"
                                                 if (key in PER_FRAME or is_framed(key)) and d.shape[:1] != (frames,)
                                                 else f"shape {d.shape}, expected {expect[key]}"))
            continue
        found, entry = _check_array(g, name, key)
        problems += found
        if entry is not None:
            entries[key] = entry
    gi = g["guide_indices"][()] if "guide_indices" in entries else np.zeros(0)
    if gi.size and (gi.min() < 0 or gi.max() >= g["rest_positions"].shape[0]):
        problems.append(f"{name}/guide_indices: out of range [0, {g['rest_positions'].shape[0]})")
    if not problems and "checksum" in g.attrs and sequence_checksum(entries) != g.attrs["checksum"]:
        problems.append(f"{name}: sequence checksum mismatch")
    return problems


def _check_file_parts(f, listed: List[str]) -> List[str]:
    """Masks (each sequence in exactly one split) and the stored head mesh of a file."""
    problems = []
    k = len(listed)
    masks = {s: f[f"mask/{s}"][()] if f"mask/{s}" in f else None for s in SPLITS}
    if any(m is None or m.shape != (k,) or m.dtype != bool for m in masks.values()):
        problems.append(f"mask: expected boolean datasets mask/train, mask/valid, mask/test of shape ({k},)")
    elif k and not np.array_equal(sum(m.astype(int) for m in masks.values()), np.ones(k, int)):
        problems.append("mask: every sequence must be in exactly one of train, valid, test")
    head = f.get("scene/head")
    if head is None:
        problems.append("scene/head: missing (the scene's head description)")
    elif "faces" in head:
        nf = head["faces"].shape[0]
        for name in listed:
            rt = f[name]["root_triangles"][()] if name in f and "root_triangles" in f[name] else None
            if rt is not None and rt.size and (rt.min() < 0 or rt.max() >= nf):
                problems.append(f"{name}/root_triangles: index outside the stored head mesh's {nf} faces")
    return problems


def validate_file(path: str) -> List[str]:
    """Check one dataset file: it opens, has the format's attributes, holds exactly the sequences
    it lists, every sequence has the datasets its ``store`` settings promise with consistent
    shapes and frame counts, no NaN/Inf, every checksum (per array, per frame, per sequence)
    matches, the masks and the head mesh are consistent. Returns the problems found (each
    naming the file and the sequence/dataset), an empty list when the file is sound."""
    try:
        f = open_dataset(path)
    except DatasetError as err:
        return [str(err)]
    with f:
        try:
            frames, store = int(f.attrs["frames"]), json.loads(f.attrs["store"])
            listed = [sequence_name(i) for i in np.asarray(f.attrs["sequences"]).tolist()]
            present = sorted(k for k in f.keys() if k.startswith(SEQ_PREFIX))
        except (KeyError, ValueError, OSError, TypeError) as err:
            return [f"{path}: unreadable file attributes: {err}"]
        problems = [f"{path}: missing sequence(s) {sorted(set(listed) - set(present))[:5]}"] \
            if set(listed) - set(present) else []
        if set(present) - set(listed):
            problems.append(f"{path}: unlisted sequence(s) {sorted(set(present) - set(listed))[:5]}")
        try:
            problems += [f"{path}: {p}" for p in metadata_problems(f)]  # attributes the readers depend on
            problems += [f"{path}: {p}" for p in _check_file_parts(f, listed)]
            for name in present:
                problems += [f"{path}: {p}" for p in _check_sequence(f[name], name, frames, store)]
        except (KeyError, OSError, ValueError, RuntimeError) as err:
            problems.append(f"{path}: unreadable (corrupt data): {err}")
    return problems


@dataclass
class ValidationReport:
    """What :func:`validate` found. ``files[path]``: problems of each file (empty when sound);
    ``problems``: dataset-level problems (files that do not belong together, missing shards or
    sequences, unfinished shards); ``notes``: facts that are not problems. ``ok``: complete and sound."""

    files: Dict[str, List[str]] = field(default_factory=dict)
    problems: List[str] = field(default_factory=list)
    notes: List[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems and not any(self.files.values())


def _completeness(headers: Dict[str, dict], root, allow_partial: bool, report: ValidationReport) -> None:
    later = report.notes if allow_partial else report.problems
    if headers and len({h["digest"] for h in headers.values()}) == 1 and len({h["num_shards"] for h in headers.values()}) == 1:
        h0 = next(iter(headers.values()))
        n, have = h0["num_shards"], {h["shard"] for h in headers.values()}
        if set(range(n)) - have:
            later.append(f"{h0['name']}: {len(have)} of {n} shards present (missing shard(s) "
                         f"{sorted(set(range(n)) - have)[:8]}, 0-based)")
        got = {i for h in headers.values() for i in h["sequences"]}
        if set(range(n)) <= have and got != set(range(h0["num_sequences"])):
            report.problems.append(f"{h0['name']}: {len(got)} of {h0['num_sequences']} sequences present")
    if isinstance(root, (list, tuple)) or not os.path.isdir(str(root)):
        return
    partial = os.path.join(str(root), ".partial")
    for stem in sorted(os.listdir(partial)) if os.path.isdir(partial) else []:
        if os.path.join(str(root), stem + ".h5") in headers:  # finished; a kill cut its clean-up short
            report.notes.append(f"{stem}: a leftover work folder of the finished shard {stem}.h5 (a run killed "
                                f"while removing it); the next generate run removes it")
            continue
        done = len([n for n in os.listdir(os.path.join(partial, stem)) if n.startswith("group-") and n.endswith(".h5")])
        plan = os.path.join(partial, stem, "shard.json")
        total = json.load(open(plan))["groups"] if os.path.isfile(plan) else None
        later.append(f"{stem}: unfinished ({done} of {len(total) if total is not None else '?'} batch groups done; "
                     f"rerun the same generate command to finish it)")
    if not headers and not report.files and not os.path.isdir(partial):
        report.problems.append(f"{root}: no dataset files (*.h5) in this folder")


def validate(root: Union[str, Sequence[str]], progress: bool = False, allow_partial: bool = False) -> ValidationReport:
    """Validate a dataset: every file under ``root`` (see :func:`list_files`), and that together
    they are one complete dataset (one recipe, one shard count, every shard, every sequence
    once, no unfinished shard). ``allow_partial``: missing and unfinished shards are notes (a
    run in progress), not problems. Raises FileNotFoundError (no such path) or
    :class:`DatasetError` (nothing here is an ams_torch dataset)."""
    if isinstance(root, str) and not os.path.exists(root):
        raise FileNotFoundError(f"no such dataset file or folder {root!r}")
    files = list_files(root)
    it = files
    if progress:
        from tqdm.auto import tqdm

        it = tqdm(files, desc="validating", unit="file")
    report = ValidationReport(files={p: validate_file(p) for p in it})
    foreign = [p for p, found in report.files.items()  # not ours, or not HDF5 at all (a .data groom, say)
               if found and ("not an ams_torch dataset" in found[0] or not is_hdf5(p))]
    if files and len(foreign) == len(files):
        raise DatasetError(f"{root}: not an ams_torch dataset ({len(files)} file(s), none written by "
                           f"`ams-torch generate`)")
    headers = {p: h for p in files if (h := read_header(p)) is not None}
    report.problems += duplicate_files(files) + check_together(headers)
    _completeness(headers, root, allow_partial, report)
    holder = lock_holder(str(root)) if isinstance(root, str) and os.path.isdir(root) else None
    if holder:
        report.notes.append(f"a generate run is writing this folder now ({holder})")
    return report
