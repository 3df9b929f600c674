"""The metadata of a dataset file that its readers depend on: which attributes must be there and
what they hold (tables), their agreement with the stored arrays, and a digest over every
attribute (``attrs_sha256``) so that an edited attribute is found like an edited array.

The per-array checksums cover the arrays; before this module, an attribute changed after
writing (``frames`` of a sequence set to 1000, an ``index`` duplicated, ``frame_sha256`` or
``recipe_digest`` deleted) passed ``validate`` and changed what the Dataset returned. Now:

- :data:`FILE_ATTRS` and :data:`SEQUENCE_ATTRS`: every attribute the Dataset and ``validate``
  read, with a check of its kind (``key -> (check, what)``); a missing or malformed one is a
  problem naming it.
- :func:`metadata_problems`: those tables, plus the relations between attributes and arrays
  (a sequence's ``frames`` equals the file's and every per-frame array's length, its ``index``
  its group name, its ``group`` index // batch, its ``split`` the masks', ``strands`` and
  ``particles`` the rest shape; ``recipe_digest`` is the SHA-256 of the stored ``recipe``; every
  framed array has its per-frame digests), and the ``attrs_sha256`` digests where a file has
  them (files written before they existed are checked by the relations alone).
- :func:`attrs_digest` is what the writer stores, generic over the attributes: new attributes
  are covered without a change here.
- :func:`duplicate_files`: the same file given twice (``HairSequenceDataset([f, f])``).
"""
from __future__ import annotations

import hashlib
import json
import os
import re
from typing import Callable, Dict, List, Sequence, Tuple

import numpy as np

from ams_torch.apps.data.format import FRAME_DIGESTS, FRAMED, PER_FRAME, SEQ_PREFIX, SPLITS, sequence_name

__all__ = ["ATTRS_DIGEST", "FILE_ATTRS", "SEQUENCE_ATTRS", "attrs_digest", "metadata_problems", "check_metadata", "refuse_duplicates",
           "duplicate_files"]

#: the attribute of a file and of each sequence group holding :func:`attrs_digest` of the others
ATTRS_DIGEST = "attrs_sha256"


# -- kinds of values ---------------------------------------------------------------------------
def _integer(lo: int = 0) -> Tuple[Callable, str]:
    def ok(v):
        return isinstance(v, (int, np.integer)) and not isinstance(v, (bool, np.bool_)) and int(v) >= lo
    return ok, f"an integer >= {lo}"


def _number_positive(v) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_)) \
        and bool(np.isfinite(v)) and v > 0


def _text(v) -> bool:
    return isinstance(v, (str, bytes))


def _json(kind=None) -> Callable:
    def ok(v):
        if not _text(v):
            return False
        try:
            parsed = json.loads(v)
        except (TypeError, ValueError):
            return False
        return kind is None or isinstance(parsed, kind)
    return ok


def _hex64(v) -> bool:
    return isinstance(v, str) and re.fullmatch(r"[0-9a-f]{64}", v) is not None


def _indices(v) -> bool:
    a = np.asarray(v)
    return a.ndim == 1 and a.dtype.kind in "iu" and (a.size == 0 or a.min() >= 0)


#: file attribute -> (check, what it must be)
FILE_ATTRS: Dict[str, Tuple[Callable, str]] = {
    "format": (_text, "a string"), "format_version": _integer(1), "recipe_digest": (_hex64, "a SHA-256 hex digest"),
    "recipe_name": (_text, "a string"), "recipe": (_json(dict), "a JSON object"),
    "recipe_hash": (_hex64, "a SHA-256 hex digest"), "store": (_json(dict), "a JSON object"),
    "split": (_json(dict), "a JSON object"), "shard": _integer(0), "num_shards": _integer(1),
    "num_sequences": _integer(1), "batch": _integer(1), "frames": _integer(1),
    "sequences": (_indices, "a list of sequence indices"),
}
#: sequence group attribute -> (check, what it must be)
SEQUENCE_ATTRS: Dict[str, Tuple[Callable, str]] = {
    "index": _integer(0), "group": _integer(0), "split": (lambda v: v in SPLITS, f"one of {list(SPLITS)}"),
    "seed": _integer(0), "frames": _integer(1), "dt": (_number_positive, "a positive number of seconds"),
    "strands": _integer(1), "particles": _integer(2), "motion": (_json(dict), "a JSON object"),
    "wind": (_json((dict, type(None))), "a JSON object or null"), "groom": (_json(dict), "a JSON object"),
    "params": (_json(dict), "a JSON object"), "scene": (_json(dict), "a JSON object"),
    "checksum": (_hex64, "a SHA-256 hex digest"),
}


# -- the digest ----------------------------------------------------------------------------------
def _canonical(value) -> bytes:
    """Bytes that identify an attribute value as h5py returns it (strings by their text)."""
    if isinstance(value, bytes):
        value = value.decode("utf-8", "replace")
    if isinstance(value, str):
        return b"s:" + value.encode("utf-8")
    a = np.asarray(value)
    if a.dtype.kind in "OSU":
        return b"S:" + json.dumps([x.decode() if isinstance(x, bytes) else str(x) for x in a.ravel().tolist()]).encode()
    a = np.ascontiguousarray(a)
    return f"{a.dtype.str}:{a.shape}:".encode() + hashlib.sha256(a.tobytes()).digest()


def attrs_digest(attrs) -> str:
    """SHA-256 (hex) over every attribute of an HDF5 object (name, kind and value) except
    :data:`ATTRS_DIGEST` itself. Call it on the object's ``attrs`` after they are written."""
    h = hashlib.sha256()
    for k in sorted(attrs.keys()):
        if k != ATTRS_DIGEST:
            h.update(k.encode() + b"=" + _canonical(attrs[k]) + b"\n")
    return h.hexdigest()


# -- problems ----------------------------------------------------------------------------------
def _missing_or_bad(attrs, table: Dict[str, Tuple[Callable, str]], where: str) -> Dict[str, str]:
    """{attribute: problem} for the attributes of ``table`` that are missing or malformed."""
    out = {}
    for key, (ok, what) in table.items():
        if key not in attrs:
            out[key] = f"{where}attribute {key!r} is missing"
        else:
            try:
                good = ok(attrs[key])
            except (TypeError, ValueError, OverflowError):
                good = False
            if not good:
                out[key] = f"{where}attribute {key!r} must be {what}; got {str(attrs[key])[:60]!r}"
    return out


def _digest_problem(obj, where: str) -> List[str]:
    stored = obj.attrs.get(ATTRS_DIGEST)
    if stored is None or attrs_digest(obj.attrs) == stored:
        return []
    return [f"{where}attributes changed after writing ({ATTRS_DIGEST} mismatch)"]


def _sequence_problems(g, name: str, f, masks: dict, position: int) -> List[str]:
    a = g.attrs
    where = f"{name}: "
    bad = _missing_or_bad(a, SEQUENCE_ATTRS, where)
    found = list(bad.values())
    frames = int(f.attrs["frames"])
    if "index" not in bad and name != sequence_name(int(a["index"])):
        found.append(f"{where}attribute 'index' = {int(a['index'])} does not match the group's name")
    if "frames" not in bad and int(a["frames"]) != frames:
        found.append(f"{where}attribute 'frames' = {int(a['frames'])}, the file's is {frames}")
    for key in PER_FRAME:
        if key in g and g[key].shape[:1] != (frames,):
            found.append(f"{where}{key} holds {g[key].shape[0] if g[key].ndim else 0} frames, the file's "
                         f"'frames' is {frames}")
    if "index" not in bad and "group" not in bad and int(a["group"]) != int(a["index"]) // int(f.attrs["batch"]):
        found.append(f"{where}attribute 'group' = {int(a['group'])} but sequence {int(a['index'])} is in batch group "
                     f"{int(a['index']) // int(f.attrs['batch'])}")
    if "split" not in bad and masks and position is not None:
        claimed = [s for s in SPLITS if masks[s] is not None and position < len(masks[s]) and masks[s][position]]
        if claimed and claimed != [a["split"]]:
            found.append(f"{where}attribute 'split' = {a['split']!r} but the masks put it in {claimed}")
    if "rest_positions" in g:
        s, n = g["rest_positions"].shape[:2]
        for key, want in (("strands", s), ("particles", n)):
            if key not in bad and int(a[key]) != want:
                found.append(f"{where}attribute {key!r} = {int(a[key])}, rest_positions has {want}")
    for key in g.keys():
        if key != FRAME_DIGESTS and not _hex64(g[key].attrs.get("sha256")):
            found.append(f"{where}{key}: attribute 'sha256' (its checksum) is missing or malformed")
    for key in FRAMED:
        if key in g:
            d = g.get(f"{FRAME_DIGESTS}/{key}")
            if d is None:
                found.append(f"{where}{FRAME_DIGESTS}/{key} is missing (the per-frame digests of {key})")
            elif d.shape != (frames, 32):
                found.append(f"{where}{FRAME_DIGESTS}/{key} has shape {d.shape}, expected ({frames}, 32)")
    return found + _digest_problem(g, where)


def metadata_problems(f) -> List[str]:
    """Problems of an open dataset file's metadata (an empty list when it is sound): the
    attribute tables, their relations to each other and to the arrays, the ``attrs_sha256``
    digests. Messages name the sequence and the attribute (not the file)."""
    found = list(_missing_or_bad(f.attrs, FILE_ATTRS, "").values())
    found += _digest_problem(f, "file: ")
    if found:
        return found  # the relations below read these attributes
    a = f.attrs
    if int(a["shard"]) >= int(a["num_shards"]):
        found.append(f"attribute 'shard' = {int(a['shard'])} but 'num_shards' = {int(a['num_shards'])}")
    recipe = a["recipe"].encode() if isinstance(a["recipe"], str) else bytes(a["recipe"])
    if hashlib.sha256(recipe).hexdigest() != a["recipe_digest"]:
        found.append("attribute 'recipe_digest' is not the SHA-256 of the stored recipe")
    listed = np.asarray(a["sequences"]).tolist()
    if len(set(listed)) != len(listed):
        found.append(f"attribute 'sequences' lists a sequence twice ({sorted(i for i in set(listed) if listed.count(i) > 1)[:5]})")
    if listed and max(listed) >= int(a["num_sequences"]):
        found.append(f"attribute 'sequences' lists sequence {max(listed)} of a {int(a['num_sequences'])}-sequence dataset")
    batch, n, shard = int(a["batch"]), int(a["num_shards"]), int(a["shard"])
    foreign = [i for i in listed if (i // batch) % n != shard]
    if foreign:
        found.append(f"attribute 'sequences' lists sequence(s) {foreign[:5]} of another shard (shard {shard} of {n} "
                     f"holds batch groups g with g % {n} == {shard})")
    masks = {s: (f[f"mask/{s}"][()] if f"mask/{s}" in f else None) for s in SPLITS}
    position = {sequence_name(i): j for j, i in enumerate(sorted(listed))}
    for name in sorted(k for k in f.keys() if k.startswith(SEQ_PREFIX)):
        found += _sequence_problems(f[name], name, f, masks, position.get(name))
    return found


def check_metadata(f, path: str) -> None:
    """Raise :class:`~ams_torch.apps.data.format.DatasetError` naming the file and the first
    metadata problem of the open dataset file ``f`` (see :func:`metadata_problems`)."""
    from ams_torch.apps.data.format import DatasetError

    found = metadata_problems(f)
    if found:
        more = f" (and {len(found) - 1} more)" if len(found) > 1 else ""
        raise DatasetError(f"{path}: {found[0]}{more}; run `ams-torch validate` on the dataset")


def duplicate_files(files: Sequence[str]) -> List[str]:
    """Problems when the same file is given more than once (by any path to it)."""
    seen: Dict[tuple, str] = {}
    out = []
    for p in files:
        try:
            st = os.stat(p)
            key = (st.st_dev, st.st_ino)
        except OSError:
            key = (None, os.path.realpath(p))
        if key in seen:
            out.append(f"{p} is given twice (also as {seen[key]}): every sequence in it would be read twice")
        else:
            seen[key] = p
    return out


def refuse_duplicates(files: Sequence[str]) -> None:
    """Raise :class:`~ams_torch.apps.data.format.DatasetError` when a file is given twice."""
    from ams_torch.apps.data.format import DatasetError

    found = duplicate_files(files)
    if found:
        raise DatasetError(f"{found[0]}; give each dataset file once")


_HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"


def is_hdf5(path: str) -> bool:
    """Whether the file starts with an HDF5 signature (at byte 0, 512, 1024, ...: where the
    format allows its superblock), truncated or not; False for any other file."""
    try:
        with open(path, "rb") as fh:
            for offset in (0, 512, 1024, 2048, 4096, 8192):
                fh.seek(offset)
                if fh.read(8) == _HDF5_MAGIC:
                    return True
    except OSError:
        return False
    return False
