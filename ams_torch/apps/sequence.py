"""The ``simulate`` outputs: ``sequence.h5`` streamed frame by frame (O(1) frames in memory), the
last frame as ``final.npz``, and reading a sequence back (whole, or lazily frame by frame).

``sequence.h5`` holds ``positions`` (F, S, N, 3) float32 m (world frame, gzip, one chunk per
frame), ``rotations`` (F, 3, 3) and ``translations`` (F, 3) m (the head poses),
``rest_positions`` (S, N, 3) m, ``collider_rotations`` (F, C, 3, 3) and
``collider_translations`` (F, C, 3) m when the scene has colliders, and the attributes
``scene``, ``params``, ``ms_per_frame`` (JSON), ``dt`` (s), ``units``, ``frames`` (F) and
``complete`` (True). Frames are appended as they are simulated, under a temporary name that is
renamed when the run ends and the file reads back; a run that fails part-way keeps the frames
it made as ``<stem>.partial.h5`` (``complete`` False); a killed run's temporary is removed by the
next run (:mod:`ams_torch.apps.atomic`).
"""
from __future__ import annotations

import contextlib
import errno
import json
import os
from typing import Optional

import numpy as np

from ams_torch.apps.atomic import WriteError, atomic_path, check_writes, h5_file, remove_stale, temp_name

__all__ = ["SequenceWriter", "write_sequence", "write_final", "read_sequence", "open_sequence", "partial_name"]

_POSES = {"rotations": (3, 3), "translations": (3,)}


def partial_name(path: str) -> str:
    """Where a run that failed part-way keeps its frames: ``sequence.h5`` → ``sequence.partial.h5``."""
    stem, ext = os.path.splitext(path)
    return f"{stem}.partial{ext or '.h5'}"


class SequenceWriter:
    """Append frames to a sequence HDF5 file as they are simulated.

    Args:
        path: the final file (``sequence.h5``); written under a temporary name until
            :meth:`finish`.
        scene: the validated scene dict; params: the run's :class:`~ams_torch.Params`;
        rest: (S, N, 3) m the rest shape; colliders: C, the scene's [[colliders]] count.

    :meth:`frame` appends one frame (arrays as :meth:`frame` says), :meth:`finish` renames the
    file into place, :meth:`abort` keeps what was done as ``<stem>.partial.h5`` (or nothing).
    A failed write raises :class:`~ams_torch.apps.atomic.WriteError` at the frame it happened.
    """

    def __init__(self, path: str, scene: dict, params, rest, colliders: int = 0):
        self.path, self.count = path, 0
        rest = np.asarray(rest, dtype=np.float32)
        if rest.ndim != 3 or rest.shape[-1] != 3:
            raise ValueError(f"rest must be (S, N, 3); got {rest.shape}")
        os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
        remove_stale(path)
        self.tmp = temp_name(path)
        self._stack = contextlib.ExitStack()
        try:
            self.f = self._stack.enter_context(h5_file(self.tmp, name=path))
            s, n = rest.shape[:2]
            shapes = {"positions": (s, n, 3), **_POSES}
            if colliders:
                shapes.update(collider_rotations=(colliders, 3, 3), collider_translations=(colliders, 3))
            for name, shape in shapes.items():
                extra = dict(compression="gzip", compression_opts=1) if name == "positions" else {}
                self.f.create_dataset(name, shape=(0,) + shape, maxshape=(None,) + shape, chunks=(1,) + shape,
                                      dtype=np.float32, **extra)
            self.names = list(shapes)
            self.f.create_dataset("rest_positions", data=rest)
            self.f.attrs.update(scene=json.dumps(scene), params=json.dumps(params.to_dict()), dt=float(params.dt),
                                units="metres, seconds; world frame, +y up", complete=False, frames=0)
            check_writes(self.f, path)
        except BaseException:
            self._discard()
            raise

    def frame(self, k: int, arrays: dict) -> None:
        """Append frame k (0-based, in order): ``positions`` (S, N, 3) m, ``rotations`` (3, 3),
        ``translations`` (3,) m, and with colliders ``collider_rotations`` (C, 3, 3),
        ``collider_translations`` (C, 3) m. Non-finite positions raise ValueError."""
        if k != self.count:
            raise ValueError(f"{self.path}: frame {k} given after {self.count} frames (frames go in order)")
        x = np.asarray(arrays["positions"], dtype=np.float32)
        if not np.isfinite(x).all():
            raise ValueError(f"the simulation produced non-finite positions at frame {k + 1}")
        for name in self.names:
            d = self.f[name]
            d.resize(k + 1, axis=0)
            d[k] = np.asarray(arrays[name], dtype=np.float32)
        self.count = k + 1
        check_writes(self.f, self.path)

    def _close(self) -> None:
        self._stack.close()  # closes the HDF5 file; raises WriteError when a write failed

    def _discard(self) -> None:
        try:
            self._stack.close()
        except OSError:
            pass
        finally:
            with contextlib.suppress(OSError):
                os.remove(self.tmp)

    def finish(self, ms_per_frame: Optional[dict] = None) -> str:
        """Close the file, read it back (frame count, the last frame decodes), rename it to its
        final name. Returns the path."""
        try:
            self.f.attrs.update(ms_per_frame=json.dumps(ms_per_frame or {}), complete=True, frames=self.count)
            self._close()
            _verify(self.tmp, self.path, self.count)
            os.replace(self.tmp, self.path)
        except BaseException:
            self._discard()
            raise
        return self.path

    def abort(self, keep: bool = True) -> Optional[str]:
        """After a failure: keep the frames done as ``<stem>.partial.h5`` (``complete`` False),
        when ``keep`` and there are any and the file can be closed; else remove it. Returns the
        partial file's path, or None."""
        if not keep or self.count == 0:
            self._discard()
            return None
        try:
            self.f.attrs.update(complete=False, frames=self.count)
            self._close()
            _verify(self.tmp, self.path, self.count)
            os.replace(self.tmp, partial_name(self.path))
        except (OSError, ValueError):
            self._discard()
            return None
        return partial_name(self.path)


def _verify(tmp: str, path: str, frames: int) -> None:
    """The file opens, holds ``frames`` frames of every per-frame array, the last one decodes."""
    import h5py

    try:
        with h5py.File(tmp, "r") as f:
            for name in ("positions", "rotations", "translations"):
                if f[name].shape[0] != frames:
                    raise ValueError(f"{name} holds {f[name].shape[0]} frames, {frames} were written")
            if frames:
                f["positions"][frames - 1]
    except (OSError, ValueError, KeyError, RuntimeError) as err:
        raise WriteError(errno.EIO, f"{path}: the file does not read back: {err}") from None


def write_sequence(path: str, result: dict, scene: dict, params, rest: np.ndarray) -> str:
    """Write a whole simulation result (``positions`` (F, S, N, 3), ``rotations``,
    ``translations``, optional collider poses, ``ms_per_frame``) with :class:`SequenceWriter`."""
    cols = result["collider_rotations"].shape[1] if "collider_rotations" in result else 0
    w = SequenceWriter(path, scene, params, rest, cols)
    try:
        for k in range(len(result["positions"])):
            w.frame(k, {name: result[name][k] for name in w.names})
    except BaseException:
        w.abort(keep=False)
        raise
    return w.finish(result.get("ms_per_frame"))


def write_final(path: str, result: dict, rest: np.ndarray) -> str:
    """Write the last frame of a run to ``.npz`` atomically (read back before the rename):
    ``positions`` and ``velocities`` (S, N, 3) float32 (m, m/s, world), ``rest_positions``
    (S, N, 3) m head frame, ``rotation`` (3, 3) and ``translation`` (3,) m the head pose,
    ``frame`` and ``time`` (s)."""
    state = result["state"]
    arrays = dict(positions=state.x.detach().cpu().float().numpy(), velocities=state.v.detach().cpu().float().numpy(),
                  rest_positions=np.asarray(rest, dtype=np.float32),
                  rotation=np.asarray(result["rotations"][-1], dtype=np.float32),
                  translation=np.asarray(result["translations"][-1], dtype=np.float32),
                  frame=np.int64(state.frame), time=np.float64(state.time))

    def same(tmp: str) -> None:
        try:
            with np.load(tmp) as z:
                ok = set(z.files) == set(arrays) and all(np.array_equal(z[k], v) for k, v in arrays.items())
        except (OSError, ValueError, EOFError) as err:
            raise WriteError(errno.EIO, f"{path}: does not read back: {err}") from None
        if not ok:
            raise WriteError(errno.EIO, f"{path}: the arrays read back differ from those written")

    with atomic_path(path, verify=same) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)
            fh.flush()
            os.fsync(fh.fileno())
    return path


def _open_h5(path: str, what: str):
    """Open an HDF5 file for reading; a ValueError naming it when it is missing or unreadable."""
    import h5py

    if not os.path.isfile(path):
        raise FileNotFoundError(f"no such {what} {path!r}")
    try:
        return h5py.File(path, "r")
    except (OSError, ValueError) as err:
        raise ValueError(f"{path}: cannot be opened as HDF5 (truncated or corrupt file): {err}") from None


_SMALL = ("rotations", "translations", "rest_positions", "collider_rotations", "collider_translations")


def _header(f, path: str, out: dict) -> dict:
    if "positions" not in f:
        raise ValueError(f"{path}: no 'positions' dataset (not an ams-torch sequence)")
    for k in _SMALL:
        if k in f:
            try:
                out[k] = f[k][()]
            except (OSError, ValueError, RuntimeError) as err:
                raise ValueError(f"{path}: dataset {k!r} is unreadable (corrupt data): {err}") from None
    for k in ("scene", "params", "ms_per_frame"):
        try:
            out[k] = json.loads(f.attrs[k]) if k in f.attrs else {}
        except (TypeError, ValueError) as err:
            raise ValueError(f"{path}: the {k!r} attribute is not JSON ({err})") from None
    out["dt"] = float(f.attrs.get("dt", 1.0 / 60.0))
    return out


def read_sequence(path: str) -> dict:
    """Read a sequence written by :class:`SequenceWriter`: positions (F, S, N, 3), rotations,
    translations, rest_positions (and collider_rotations (F, C, 3, 3), collider_translations
    (F, C, 3) when the scene has colliders) and the parsed ``scene``/``params``/``ms_per_frame``,
    ``dt``. A missing, truncated or corrupt file raises FileNotFoundError/ValueError naming it."""
    with open_sequence(path) as seq:
        try:
            seq["positions"] = seq["positions"][()]
        except (OSError, ValueError, RuntimeError) as err:
            raise ValueError(f"{path}: dataset 'positions' is unreadable (corrupt data): {err}") from None
        return seq


@contextlib.contextmanager
def open_sequence(path: str):
    """Like :func:`read_sequence`, but ``positions`` is the open h5py dataset (read a frame at a
    time: ``seq["positions"][k]``), valid inside the ``with`` block."""
    with _open_h5(path, "sequence file") as f:
        out = _header(f, path, {})
        out["positions"] = f["positions"]
        yield out
