"""The build cache's files: a library is loaded only if it is the one that was built (size and SHA-256
recorded in ``build.json``), and builders of one cache directory serialise on a lock that a killed
builder cannot leave behind for good (used by :mod:`ams_torch.native.build`)."""
from __future__ import annotations

import contextlib
import hashlib
import json
import os
import socket
import time
from pathlib import Path
from typing import Iterator, Optional

__all__ = ["build_lock", "lock_is_stale", "cached_library", "write_marker", "discard_library"]

ENV_LOCK_STALE = "AMS_TORCH_BUILD_LOCK_STALE_S"
DEFAULT_LOCK_STALE_S = 1200.0
LOCK_NAME = "ams_build.lock"   # ours: JSON {"pid", "host", "time"}
TORCH_LOCK_NAME = "lock"       # torch.utils.file_baton.FileBaton inside the build directory
MARKER_NAME = "build.json"     # written after a successful build: its inputs, the library, its size and hash


# -- the cache: a library is loaded only when it is the one that was built -----------------------

def sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def cached_library(build_dir: Path) -> Optional[Path]:
    """The library recorded in ``build.json``, if it exists with the recorded size and SHA-256."""
    marker = build_dir / MARKER_NAME
    try:
        info = json.loads(marker.read_text())
        library = build_dir / info["library"]
        size, digest = int(info["size"]), str(info["sha256"])
        if library.stat().st_size != size or sha256(library) != digest:
            return None
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return library


def write_marker(build_dir: Path, library: Path, key_parts: dict) -> None:
    info = {"library": library.name, "key": key_parts, "size": library.stat().st_size, "sha256": sha256(library)}
    tmp = build_dir / f".{MARKER_NAME}.{os.getpid()}.tmp"
    tmp.write_text(json.dumps(info))
    os.replace(tmp, build_dir / MARKER_NAME)


def discard_library(build_dir: Path, name: str) -> None:
    """Before a (re)build: remove the marker and any library of ``name`` (ninja would take a
    damaged library newer than its objects as up to date)."""
    for path in [build_dir / MARKER_NAME, *build_dir.glob(f"{name}*.so")]:
        with contextlib.suppress(FileNotFoundError):
            path.unlink()


# ---------------------------------------------------------------------------------------
# build lock
# ---------------------------------------------------------------------------------------

def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    except OSError:
        return False
    try:  # a zombie (killed, not yet reaped) is dead for our purpose
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return True


def lock_is_stale(path: Path, stale_after_s: float) -> bool:
    """True when the build lock ``path`` is abandoned: its owner is a dead process on this host,
    or it is older than ``stale_after_s`` seconds, or it is unreadable and older than 5 s."""
    try:
        age = time.time() - path.stat().st_mtime
    except FileNotFoundError:
        return False
    if age > stale_after_s:
        return True
    try:
        owner = json.loads(path.read_text())
        pid, host = int(owner["pid"]), str(owner["host"])
    except (OSError, ValueError, KeyError, TypeError):
        return age > 5.0  # being written right now, or garbage
    return host == socket.gethostname() and not _pid_alive(pid)


@contextlib.contextmanager
def build_lock(build_dir: Path, stale_after_s: Optional[float] = None, poll_s: float = 0.2) -> Iterator[None]:
    """Hold the build lock of ``build_dir`` (waits for a live holder; breaks a stale one).

    While held, any torch FileBaton ``lock`` in ``build_dir`` is a leftover of a killed build
    (every builder of this directory takes this lock first) and is removed, so that
    ``cpp_extension.load`` does not wait on it forever. Waiting is bounded: a lock older than
    ``stale_after_s`` (default ``$AMS_TORCH_BUILD_LOCK_STALE_S`` or 1200 s) is broken.
    """
    if stale_after_s is None:
        stale_after_s = float(os.environ.get(ENV_LOCK_STALE, DEFAULT_LOCK_STALE_S))
    build_dir = Path(build_dir)
    build_dir.mkdir(parents=True, exist_ok=True)
    path = build_dir / LOCK_NAME
    while True:
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            if lock_is_stale(path, stale_after_s):
                with contextlib.suppress(FileNotFoundError):
                    path.unlink()
            else:
                time.sleep(poll_s)
            continue
        with os.fdopen(fd, "w") as f:
            json.dump({"pid": os.getpid(), "host": socket.gethostname(), "time": time.time()}, f)
        break
    try:
        with contextlib.suppress(FileNotFoundError):
            (build_dir / TORCH_LOCK_NAME).unlink()
        yield
    finally:
        with contextlib.suppress(FileNotFoundError):
            path.unlink()
