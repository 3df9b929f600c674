"""Outputs that are whole or absent: temporary names, verified renames, stale temporaries, and
HDF5 files whose writes can fail without crashing the process.

Every file the command line writes goes through here:

- :func:`atomic_path` yields a temporary name next to the final one (``.<name>.tmp<pid><ext>``,
  same folder, so the rename is atomic), checks the bytes written (non-empty, and ``verify``
  reads the file back where that is cheap), then renames it into place. On any failure the
  temporary is removed and nothing appears under the final name.
- Temporaries of runs that were killed (their pid no longer alive on this host) are removed by
  the next write of the same final file (:func:`remove_stale`).
- :func:`h5_file` opens an HDF5 file for writing through a Python file object that never lets a
  disk error reach the HDF5 library: the first failed write (ENOSPC, EFBIG under ``ulimit -f``,
  EIO) is recorded, later writes are kept in memory (bounded) so the library's view stays
  consistent, and the error is raised once the file is closed (or at :func:`check_writes`).
  HDF5 2.0 crashes with SIGSEGV when a failed write reaches it and the file is then closed;
  this way a full disk is one clean ``OSError`` naming the file.
"""
from __future__ import annotations

import contextlib
import errno
import os
import re
from typing import Callable, List, Optional

__all__ = ["temp_name", "remove_stale", "atomic_path", "write_bytes", "h5_file", "check_writes", "WriteError"]

#: bytes of writes that failed (or came after a failure) that :func:`h5_file` keeps in memory to
#: serve reads; larger writes past it are dropped (the file is deleted anyway)
OVERLAY_LIMIT = 256 << 20


class WriteError(OSError):
    """Writing an output file failed (full disk, file size limit, I/O error); nothing was left
    under its final name. The message names the file and the operating system's reason;
    ``errno`` is the system's error number."""

    def __init__(self, code: Optional[int], message: str):
        super().__init__(message)
        self.errno = code


def temp_name(final: str) -> str:
    """The temporary name of ``final`` for this process: ``<dir>/.<name>.tmp<pid><ext>`` (the
    extension kept, so writers that choose the format by extension still do)."""
    folder, base = os.path.split(os.path.abspath(final))
    return os.path.join(folder, f".{base}.tmp{os.getpid()}{os.path.splitext(base)[1]}")


def final_name(path: str) -> str:
    """The final name a temporary stands for (``.x.h5.tmp12.h5`` or ``x.h5.tmp12`` → ``x.h5``);
    any other path as it is."""
    folder, base = os.path.split(path)
    m = re.match(r"^(\.?)(.+?)\.tmp\d+", base)
    if not m:
        return path
    name = m.group(2)
    return os.path.join(folder, name) if m.group(1) or not name.startswith(".") else path


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError, ValueError):
        return True
    return True


def remove_stale(final: str) -> List[str]:
    """Remove the temporaries of ``final`` left by runs that were killed: ``.<name>.tmp<pid>…``
    (and the older ``<name>.tmp<pid>…``) whose process is no longer alive. Returns their paths."""
    folder, base = os.path.split(os.path.abspath(final))
    pattern = re.compile(rf"^\.?{re.escape(base)}\.tmp(\d+)")
    removed = []
    try:
        names = os.listdir(folder)
    except OSError:
        return removed
    for name in names:
        m = pattern.match(name)
        if m and not _alive(int(m.group(1))):
            path = os.path.join(folder, name)
            with contextlib.suppress(FileNotFoundError):
                if os.path.isdir(path):
                    continue
                os.remove(path)
                removed.append(path)
    return removed


def _reason(err: BaseException) -> str:
    if isinstance(err, OSError) and err.errno is not None:
        return os.strerror(err.errno)
    return str(err) or type(err).__name__


@contextlib.contextmanager
def atomic_path(final: str, verify: Optional[Callable[[str], None]] = None, min_bytes: int = 1):
    """Yield a temporary path for ``final``; when the block succeeds, check it holds at least
    ``min_bytes`` bytes, call ``verify(tmp)`` (raise to refuse it), and rename it to ``final``.
    Any failure removes the temporary (``final`` keeps what it held before). Stale temporaries
    of ``final`` from killed runs are removed first. Write errors become :class:`WriteError`."""
    folder = os.path.dirname(os.path.abspath(final))
    try:
        os.makedirs(folder, exist_ok=True)
    except OSError as err:
        raise WriteError(err.errno, f"{final}: cannot create its folder: {_reason(err)}") from None
    remove_stale(final)
    tmp = temp_name(final)
    try:
        yield tmp
        size = os.path.getsize(tmp) if os.path.exists(tmp) else -1
        if size < min_bytes:
            raise WriteError(errno.EIO, f"{final}: the writer left {max(size, 0)} bytes (expected at least "
                                        f"{min_bytes}); nothing was written")
        if verify is not None:
            verify(tmp)
        os.replace(tmp, final)
    except BaseException as err:
        with contextlib.suppress(OSError):
            os.remove(tmp)
        if isinstance(err, OSError) and not isinstance(err, (WriteError, FileNotFoundError)):
            raise WriteError(err.errno, f"{final}: writing failed: {_reason(err)}; nothing was written") from None
        raise


def _write_all(fd: int, data, offset: Optional[int] = None) -> None:
    view = memoryview(data).cast("B")
    done = 0
    while done < len(view):
        n = os.write(fd, view[done:]) if offset is None else os.pwrite(fd, view[done:], offset + done)
        if n <= 0:
            raise OSError(errno.EIO, "short write")
        done += n


def write_bytes(final: str, data: bytes) -> str:
    """Write ``data`` to ``final`` atomically, synced to disk and read back to compare."""

    def same(tmp: str) -> None:
        with open(tmp, "rb") as fh:
            if fh.read() != bytes(data):
                raise WriteError(errno.EIO, f"{final}: the bytes read back differ from the bytes written")

    with atomic_path(final, verify=same) as tmp:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        try:
            _write_all(fd, data)
            os.fsync(fd)
        finally:
            os.close(fd)
    return final


# -- HDF5 through a file object that never fails -------------------------------------------------
class _Sink:
    """A read/write file object for ``h5py.File``: writes go to the file until one fails; from
    then on they are kept in an in-memory overlay (up to :data:`OVERLAY_LIMIT` bytes) that reads
    see, so the HDF5 library never meets an error. ``error`` holds the first failure."""

    def __init__(self, path: str):
        self.path = path
        self.fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_TRUNC, 0o644)
        self.pos = 0
        self.end = 0
        self.error: Optional[OSError] = None
        self.overlay: List[tuple] = []  # (offset, bytes)
        self.kept = 0

    # the file-object protocol h5py uses
    def seek(self, offset: int, whence: int = 0) -> int:
        self.pos = offset if whence == 0 else self.pos + offset if whence == 1 else self.end + offset
        return self.pos

    def tell(self) -> int:
        return self.pos

    def write(self, data) -> int:
        view = memoryview(data).cast("B")
        n = len(view)
        if self.error is None:
            try:
                _write_all(self.fd, view, self.pos)
            except OSError as err:
                self.error = err
                self._keep(self.pos, view)
        else:
            self._keep(self.pos, view)
        self.pos += n
        self.end = max(self.end, self.pos)
        return n

    def _keep(self, offset: int, view) -> None:
        if self.kept + len(view) > OVERLAY_LIMIT and len(view) > 65536:
            return  # raw data past the budget: never read back by a writer, and the file is deleted
        self.overlay.append((offset, bytes(view)))
        self.kept += len(view)

    def readinto(self, buf) -> int:
        out = memoryview(buf).cast("B")
        want = max(0, min(len(out), self.end - self.pos))
        data = os.pread(self.fd, want, self.pos) if want else b""
        out[:len(data)] = data
        out[len(data):want] = bytes(want - len(data))
        for off, b in self.overlay:
            lo, hi = max(off, self.pos), min(off + len(b), self.pos + want)
            if lo < hi:
                out[lo - self.pos:hi - self.pos] = b[lo - off:hi - off]
        self.pos += want
        return want

    def read(self, n: int = -1) -> bytes:
        buf = bytearray(max(0, self.end - self.pos) if n is None or n < 0 else n)
        return bytes(buf[:self.readinto(buf)])

    def truncate(self, size: Optional[int] = None) -> int:
        size = self.pos if size is None else size
        if self.error is None:
            try:
                os.ftruncate(self.fd, size)
            except OSError as err:
                self.error = err
        self.end = size
        return size

    def flush(self) -> None:
        pass

    def close(self) -> None:
        if self.fd >= 0:
            if self.error is None:
                try:
                    os.fsync(self.fd)
                except OSError as err:
                    self.error = err
            os.close(self.fd)
            self.fd = -1
        self.overlay = []

    def failure(self, what: str) -> WriteError:
        err = self.error
        return WriteError(err.errno if err.errno is not None else errno.EIO,
                          f"{what}: writing failed: {_reason(err)}")


_SINKS = {}


@contextlib.contextmanager
def h5_file(path: str, name: Optional[str] = None, **kwargs):
    """``h5py.File(path, "w")`` whose disk errors cannot crash the process: yields the open
    file; closes it on exit; raises :class:`WriteError` naming ``name`` (default ``path``) when a
    write failed (the file is then incomplete: the caller removes it; default name: the final
    name ``path`` stands for, see :func:`final_name`). ``kwargs`` go to ``h5py.File``."""
    import h5py

    sink = _Sink(path)
    try:
        f = h5py.File(sink, "w", **kwargs)
    except BaseException:
        sink.close()
        raise
    _SINKS[id(f)] = sink
    failed = None
    try:
        yield f
    except BaseException as err:
        failed = err
        raise
    finally:
        _SINKS.pop(id(f), None)
        try:
            f.close()
        finally:
            sink.close()
        if sink.error is not None:
            raise sink.failure(name or final_name(path)) from (failed if not isinstance(failed, WriteError) else None)


def check_writes(f, name: Optional[str] = None) -> None:
    """Raise :class:`WriteError` now if a write of ``f`` (opened by :func:`h5_file`) failed, so
    a long writer stops at the next frame instead of at the end."""
    sink = _SINKS.get(id(f))
    if sink is not None and sink.error is not None:
        raise sink.failure(name or final_name(sink.path))
