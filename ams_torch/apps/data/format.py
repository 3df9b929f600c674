"""The dataset format (version 3; version 2 is still read): names, units and dims, checksums,
listing and opening files, file headers, which files belong together, and the output folder's
lock record."""
from __future__ import annotations

import glob
import hashlib
import json
import os
import re
import socket
from typing import Dict, Iterable, List, Optional, Sequence, Tuple, Union

import numpy as np

__all__ = ["FORMAT", "FORMAT_VERSION", "READ_VERSIONS", "GUIDES_ALONE", "alone_name", "alone_count", "is_framed",
           "array_info", "SEQ_PREFIX", "SPLITS", "SHARD_FILE", "ARRAYS", "FRAMED", "PER_FRAME",
           "PER_SEQUENCE", "POSE_FIELDS", "LOCK_FILE", "FRAME_DIGESTS", "DatasetError", "sequence_name",
           "array_digest", "sequence_checksum", "list_files", "list_datasets", "open_dataset", "read_header",
           "check_together", "holder_text", "lock_holder"]

FORMAT = "ams_torch.dataset"
FORMAT_VERSION = 3
#: versions this library reads: 2 (before guides alone, motion velocities, num_pinned and hold-outs) and 3
READ_VERSIONS = (2, 3)
#: per-frame arrays ``guides_alone_<G>`` (F, G, N, 3) m: the first G guides simulated alone
GUIDES_ALONE = "guides_alone_"
SEQ_PREFIX = "seq_"
SPLITS = ("train", "valid", "test")
SHARD_FILE = re.compile(r"^(?P<name>.+)-shard-(?P<i>\d{5})-of-(?P<n>\d{5})\.h5$")
#: array -> (units, dims): the ``units`` and ``dims`` attributes every stored array carries
ARRAYS = {"positions": ("m", "frame,strand,particle,xyz"), "velocities": ("m/s", "frame,strand,particle,xyz"),
          "guide_positions": ("m", "frame,guide,particle,xyz"), "rotations": ("1", "frame,row,column"),
          "translations": ("m", "frame,xyz"), "linear_velocities": ("m/s", "frame,xyz"),
          "angular_velocities": ("rad/s", "frame,xyz"), "collider_rotations": ("1", "frame,collider,row,column"),
          "collider_translations": ("m", "frame,collider,xyz"), "rest_positions": ("m", "strand,particle,xyz"),
          "root_triangles": ("index", "strand"), "root_barycentrics": ("1", "strand,corner"),
          "guide_indices": ("index", "guide"), "vertices": ("m", "vertex,xyz"), "faces": ("index", "face,corner"),
          "motion_velocities": ("m/s", "frame,strand,particle,xyz"), "num_pinned": ("count", "strand")}
#: large per-frame arrays: per-frame digests (and the guides_alone_<G> arrays, see is_framed)
FRAMED = ("positions", "velocities", "guide_positions", "motion_velocities")
PER_FRAME = FRAMED + ("rotations", "translations", "linear_velocities", "angular_velocities",
                      "collider_rotations", "collider_translations")
PER_SEQUENCE = ("rest_positions", "root_triangles", "root_barycentrics", "guide_indices", "num_pinned")


def alone_name(count: int) -> str:
    """The array of the first ``count`` guides simulated alone: ``guides_alone_64``."""
    return f"{GUIDES_ALONE}{int(count)}"


def alone_count(name: str) -> Optional[int]:
    """G of an array name ``guides_alone_<G>``, else None."""
    if name.startswith(GUIDES_ALONE) and name[len(GUIDES_ALONE):].isdigit():
        return int(name[len(GUIDES_ALONE):])
    return None


def is_framed(name: str) -> bool:
    """Whether array ``name`` is a large per-frame array with per-frame digests."""
    return name in FRAMED or alone_count(name) is not None


def array_info(name: str) -> Tuple[str, str]:
    """(units, dims) of a stored array (the ``units`` and ``dims`` attributes it carries)."""
    if alone_count(name) is not None:
        return "m", "frame,guide,particle,xyz"
    return ARRAYS[name]
POSE_FIELDS = ("rotations", "translations", "linear_velocities", "angular_velocities")
LOCK_FILE = ".lock"  # held (flock) by a generate run writing the folder; see ams_torch.apps.datagen
FRAME_DIGESTS = "frame_sha256"  # subgroup of a sequence: (F, 32) uint8 SHA-256 of each frame of each FRAMED array


class DatasetError(ValueError):
    """A dataset cannot be read as asked: the message names the file, and where it applies the
    sequence and the array (corrupt data, checksum mismatch, files that do not belong together)."""


def sequence_name(index: int) -> str:
    """HDF5 group name of sequence ``index``: ``seq_000012``."""
    return f"{SEQ_PREFIX}{int(index):06d}"


def array_digest(chunks: Iterable[np.ndarray]) -> str:
    """SHA-256 (hex) of the C-order bytes of consecutive slabs of one array."""
    h = hashlib.sha256()
    for c in chunks:
        h.update(np.ascontiguousarray(c).tobytes())
    return h.hexdigest()


def sequence_checksum(entries: Dict[str, Tuple[str, tuple, str]]) -> str:
    """The checksum of a sequence: SHA-256 over the sorted lines ``name:dtype:shape:digest`` of
    its datasets (``entries[name] = (numpy dtype str, shape, dataset digest)``)."""
    lines = [f"{k}:{d}:{'x'.join(str(s) for s in shape)}:{g}" for k, (d, shape, g) in sorted(entries.items())]
    return hashlib.sha256("\n".join(lines).encode()).hexdigest()


def list_files(root: Union[str, Sequence[str]]) -> List[str]:
    """The dataset files under ``root``: a directory (its ``*.h5``, sorted; the ``.partial`` work
    folder of an unfinished run is not included), one file, or a list of files."""
    if isinstance(root, (list, tuple)):
        files = [str(p) for p in root]
    elif os.path.isdir(root):
        files = sorted(glob.glob(os.path.join(root, "*.h5")))
    else:
        files = [str(root)]
    for p in files:
        if not os.path.isfile(p):
            raise FileNotFoundError(f"no such dataset file or folder {p!r}")
    return files


def list_datasets(root: str) -> List[str]:
    """The dataset folders of ``root``: ``[root]`` when it holds dataset files (``*.h5``), else its
    sub-folders that do (a suite generated by ``ams-torch generate FOLDER``), sorted by name."""
    if not os.path.isdir(root):
        raise FileNotFoundError(f"no such dataset or suite folder {root!r}")
    if glob.glob(os.path.join(root, "*.h5")):
        return [root]
    found = sorted(p for p in glob.glob(os.path.join(root, "*"))
                   if os.path.isdir(p) and glob.glob(os.path.join(p, "*.h5")))
    if not found:
        raise FileNotFoundError(f"{root}: neither a dataset (no *.h5) nor a suite (no sub-folder holds *.h5)")
    return found


def open_dataset(path: str):
    """Open a dataset file for reading; DatasetError naming the file when it is not one we read."""
    import h5py

    try:
        f = h5py.File(path, "r")
    except (OSError, ValueError) as err:
        raise DatasetError(f"{path}: cannot be opened as HDF5 (truncated or corrupt file): {err}") from None
    fmt, version = f.attrs.get("format"), f.attrs.get("format_version")
    if fmt != FORMAT:
        f.close()
        raise DatasetError(f"{path}: not an ams_torch dataset (attribute format = {fmt!r})")
    if version not in READ_VERSIONS:
        f.close()
        hint = ("regenerate it with `ams-torch generate` (its recipe is in the file's 'recipe' attribute)"
                if version is not None and int(version) < FORMAT_VERSION else "upgrade ams_torch to read it")
        raise DatasetError(f"{path}: format_version {version} is not read by this library (it reads versions "
                           f"{', '.join(str(v) for v in READ_VERSIONS)}); {hint}")
    return f


def read_header(path: str) -> Optional[dict]:
    """The attributes that say which dataset a file belongs to: ``digest`` (recipe_digest),
    ``name``, ``shard``, ``num_shards``, ``num_sequences``, ``sequences`` (list); None when unreadable."""
    import h5py

    try:
        with h5py.File(path, "r") as f:
            a = f.attrs
            return {"digest": str(a["recipe_digest"]), "name": str(a["recipe_name"]), "shard": int(a["shard"]),
                    "num_shards": int(a["num_shards"]), "num_sequences": int(a["num_sequences"]),
                    "sequences": np.asarray(a["sequences"]).tolist()}
    except (OSError, KeyError, ValueError, TypeError):
        return None


def _grouped(by: Dict, what: str) -> str:
    return "; ".join(f"{what} {k}: {', '.join(os.path.basename(p) for p in v)}" for k, v in sorted(by.items()))


def check_together(headers: Dict[str, dict]) -> List[str]:
    """Problems that make files unusable as one dataset: several recipes (digests), several
    shard counts, a sequence in more than one file. ``headers[path]``: the file's attributes."""
    problems, digests, counts, owner = [], {}, {}, {}
    for p, h in headers.items():
        digests.setdefault(h["digest"][:12], []).append(p)
        counts.setdefault(h["num_shards"], []).append(p)
        for i in h["sequences"]:
            owner.setdefault(i, []).append(p)
    if len(digests) > 1:
        problems.append(f"the files come from {len(digests)} different recipes (recipe_digest): {_grouped(digests, 'digest')}")
    if len(counts) > 1:
        problems.append(f"the files are of {len(counts)} different shardings: {_grouped(counts, 'num_shards')}")
    dup = sorted(i for i, ps in owner.items() if len(ps) > 1)
    if dup:
        files = sorted({os.path.basename(p) for i in dup for p in owner[i]})
        problems.append(f"{len(dup)} sequence(s) appear in more than one file (e.g. sequence {dup[0]} in "
                        f"{', '.join(os.path.basename(p) for p in owner[dup[0]])}); files involved: {', '.join(files)}")
    return problems


def holder_text(info: dict) -> str:
    """A lock file's record (pid, host, start, command) in words."""
    if not info:
        return "holder unknown"
    return f"pid {info.get('pid')} on host {info.get('host')}, since {info.get('started')}: {info.get('command')}"


def lock_holder(out: str) -> Optional[str]:
    """Who is generating into ``out`` now ("pid 123 on host h, since ...: command"), or None."""
    try:
        with open(os.path.join(out, LOCK_FILE)) as fh:
            info = json.loads(fh.read() or "{}")
    except (OSError, ValueError):
        return None
    if not info:
        return None
    if info.get("host") == socket.gethostname():
        try:
            os.kill(int(info.get("pid", -1)), 0)
        except ProcessLookupError:
            return None  # a killed run: the kernel released its flock
        except (PermissionError, ValueError, OverflowError):
            pass
    return holder_text(info)
