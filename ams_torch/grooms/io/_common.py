"""Shared helpers of the groom readers/writers: bounded binary reads and error messages."""
from __future__ import annotations

import os
from typing import List, Sequence

import numpy as np


class GroomFileError(ValueError):
    """A groom file is truncated, corrupt or not in the format its extension says.

    The message starts with the file's path and says what is wrong and where (byte offset).
    """


def fail(path, problem: str) -> GroomFileError:
    return GroomFileError(f"{os.fspath(path)}: {problem}")


class ByteReader:
    """Sequential little-endian reads from a byte string that fail with a clear message."""

    def __init__(self, path, data: bytes, what: str):
        self.path = path
        self.data = memoryview(data)
        self.pos = 0
        self.what = what  # format name used in messages

    @property
    def left(self) -> int:
        return len(self.data) - self.pos

    def array(self, dtype, count: int, item: str) -> np.ndarray:
        dt = np.dtype(dtype)
        count = int(count)
        if count < 0:
            raise fail(self.path, f"corrupt {self.what} file: negative count {count} for {item}")
        nbytes = dt.itemsize * count
        if nbytes > self.left:
            raise fail(self.path, f"truncated {self.what} file: {item} needs {nbytes} bytes at offset "
                                  f"{self.pos}, but only {self.left} are left (file size {len(self.data)})")
        out = np.frombuffer(self.data, dtype=dt, count=count, offset=self.pos)
        self.pos += nbytes
        return out

    def scalar(self, dtype, item: str):
        return self.array(dtype, 1, item)[0]

    def seek(self, pos: int, item: str) -> None:
        if not 0 <= pos <= len(self.data):
            raise fail(self.path, f"corrupt {self.what} file: {item} points to offset {pos}, outside the "
                                  f"file ({len(self.data)} bytes)")
        self.pos = pos

    def expect_end(self, after: str) -> None:
        if self.left:
            raise fail(self.path, f"corrupt {self.what} file: {self.left} unexpected trailing bytes after {after} "
                                  f"(offset {self.pos}); the counts in the file do not match its size")


def read_bytes(path) -> bytes:
    with open(path, "rb") as f:
        return f.read()


def check_points(path, strands: Sequence[np.ndarray]) -> None:
    """Raise if any point is NaN/Inf (a corrupt file usually shows up this way)."""
    for i, s in enumerate(strands):
        if not np.all(np.isfinite(s)):
            j = int(np.flatnonzero(~np.isfinite(s).all(1))[0])
            raise fail(path, f"corrupt file: non-finite coordinates at strand {i}, point {j}")


def split_points(points: np.ndarray, counts: np.ndarray) -> List[np.ndarray]:
    """(P, 3) points and (S,) counts → list of S arrays (n_i, 3) (views)."""
    ends = np.cumsum(counts)
    return np.split(points, ends[:-1]) if len(counts) else []


def concat_strands(strands: Sequence[np.ndarray]):
    """List of (n_i, 3) → (P, 3) float32 points and (S,) int64 counts."""
    counts = np.array([len(s) for s in strands], dtype=np.int64)
    if len(strands) == 0:
        return np.zeros((0, 3), np.float32), counts
    pts = np.concatenate([np.asarray(s, dtype=np.float32).reshape(-1, 3) for s in strands], 0)
    return pts, counts


def strand_tangents(points: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Unit tangents (P, 3) of concatenated polylines (central differences, one-sided at ends)."""
    out = np.zeros_like(points, dtype=np.float32)
    start = 0
    for n in counts:
        n = int(n)
        if n >= 2:
            seg = points[start:start + n].astype(np.float64)
            t = np.gradient(seg, axis=0)
            t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-30)
            out[start:start + n] = t
        start += n
    return out
