"""Pictures and videos written whole or not at all: MP4 through the ffmpeg that imageio-ffmpeg
bundles (its exit status and error output checked, the file's boxes and frame count read back)
and PNG encoded in memory, each under a temporary name renamed when verified
(:mod:`ams_torch.apps.atomic`)."""
from __future__ import annotations

import errno
import os
import struct
import subprocess
import threading
from typing import Iterable, Optional

import numpy as np

from ams_torch.apps.atomic import WriteError, atomic_path, write_bytes

__all__ = ["write_video", "write_png", "encode_png", "mp4_frame_count", "VIDEO_EXTENSIONS", "IMAGE_EXTENSIONS",
           "check_picture_path"]

VIDEO_EXTENSIONS = (".mp4",)
IMAGE_EXTENSIONS = (".png",)
#: the highest frame rate written (a scene's default is 1/dt, and dt may be as short as 1e-7 s)
MAX_FPS = 1e7
#: libx264 constant rate factor (imageio's quality 7 of 10: crf = 51 × 0.3 = 15)
CRF = 15


def check_picture_path(path: str, what: str = "--out") -> str:
    """``path`` when it ends in .mp4 (a video) or .png (a picture of the last frame); a
    ValueError naming ``what`` otherwise (a .gif or .avi would get MP4 bytes)."""
    ext = os.path.splitext(str(path))[1].lower()
    if ext not in VIDEO_EXTENSIONS + IMAGE_EXTENSIONS:
        raise ValueError(f"{what} {path!r}: write a video to .mp4 or a picture of the last frame to .png "
                         f"(got {ext or 'no extension'})")
    return path


def encode_png(rgb: np.ndarray) -> bytes:
    """PNG bytes of an (H, W, 3) or (H, W, 4) uint8 image."""
    import imageio.v3 as iio

    return iio.imwrite("<bytes>", np.asarray(rgb, dtype=np.uint8), extension=".png")


def write_png(path: str, rgb: np.ndarray) -> str:
    """Write an (H, W, 3) uint8 image as PNG atomically (encoded in memory, written, synced, read
    back and compared, then renamed). Returns the path."""
    return write_bytes(path, encode_png(rgb))


# -- MP4 ----------------------------------------------------------------------------------------
def _boxes(fh, start: int, end: int):
    """(type, payload offset, payload end) of the ISO-BMFF boxes in [start, end) of a file;
    ValueError when a box runs past ``end`` (a truncated file)."""
    pos = start
    while pos < end:
        fh.seek(pos)
        head = fh.read(8)
        if len(head) < 8:
            raise ValueError(f"a box header at byte {pos} is cut off")
        size, kind = struct.unpack(">I4s", head)
        body = pos + 8
        if size == 1:
            big = fh.read(8)
            if len(big) < 8:
                raise ValueError(f"a box header at byte {pos} is cut off")
            size, body = struct.unpack(">Q", big)[0], pos + 16
        elif size == 0:
            size = end - pos
        if size < body - pos or pos + size > end:
            raise ValueError(f"box {kind.decode('latin-1')!r} at byte {pos} claims {size} bytes, past the end "
                             f"({end})")
        yield kind.decode("latin-1"), body, pos + size
        pos += size


def mp4_frame_count(path: str) -> int:
    """The number of video samples an MP4 holds (its first track's ``stsz`` box), after checking
    that its top-level boxes cover the file exactly and that ``moov`` and ``mdat`` are there.
    ValueError naming the file when it is truncated or not an MP4."""
    size = os.path.getsize(path)
    with open(path, "rb") as fh:
        try:
            top = {k: (a, b) for k, a, b in _boxes(fh, 0, size)}
            if "moov" not in top or "mdat" not in top:
                raise ValueError(f"no {'moov' if 'moov' not in top else 'mdat'} box (the file was never finished)")
            span = top["moov"]
            for name in ("trak", "mdia", "minf", "stbl", "stsz"):
                inner = {k: (a, b) for k, a, b in _boxes(fh, *span)}
                if name not in inner:
                    raise ValueError(f"no {name} box in the movie header")
                span = inner[name]
            fh.seek(span[0])
            _, _, count = struct.unpack(">III", fh.read(12))
        except (ValueError, struct.error) as err:
            raise ValueError(f"{path}: not a complete MP4 file: {err}") from None
    return int(count)


def _ffmpeg_command(exe: str, width: int, height: int, fps: float, out: str) -> list:
    from fractions import Fraction

    rate = str(Fraction(float(fps)).limit_denominator(100000))
    return [exe, "-y", "-nostdin", "-f", "rawvideo", "-vcodec", "rawvideo", "-s", f"{width}x{height}", "-pix_fmt",
            "rgb24", "-r", rate, "-i", "-", "-an", "-vcodec", "libx264", "-pix_fmt", "yuv420p", "-crf", str(CRF),
            "-v", "error", out]


def _even(frame: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8, padded by its edge to even H and W (H.264 in yuv420p needs them)."""
    f = np.ascontiguousarray(np.asarray(frame, dtype=np.uint8)[..., :3])
    if f.ndim != 3:
        raise ValueError(f"video frames must be (H, W, 3) images; got shape {f.shape}")
    pad = ((0, f.shape[0] % 2), (0, f.shape[1] % 2), (0, 0))
    return np.pad(f, pad, mode="edge") if any(p[1] for p in pad[:2]) else f


def _encode(frames: Iterable[np.ndarray], out: str, fps: float, path: str) -> int:
    """Pipe the frames to ffmpeg writing ``out``; returns how many were written. Raises
    WriteError with ffmpeg's own words when it fails (full disk, size limit, ...)."""
    import imageio_ffmpeg

    proc: Optional[subprocess.Popen] = None
    count, shape, broken, log = 0, None, False, []
    drain = None
    try:
        for frame in frames:
            f = _even(frame)
            if proc is None:
                shape = f.shape
                proc = subprocess.Popen(_ffmpeg_command(imageio_ffmpeg.get_ffmpeg_exe(), f.shape[1], f.shape[0], fps,
                                                        out), stdin=subprocess.PIPE, stdout=subprocess.DEVNULL,
                                        stderr=subprocess.PIPE)
                drain = threading.Thread(target=lambda: log.append(proc.stderr.read()), daemon=True)
                drain.start()  # read ffmpeg's error output as it comes (a full pipe would stall it)
            elif f.shape != shape:
                raise ValueError(f"{path}: video frame {count} is {f.shape[1]}x{f.shape[0]}, the first was "
                                 f"{shape[1]}x{shape[0]}")
            try:
                proc.stdin.write(f.tobytes())
            except (BrokenPipeError, OSError):
                broken = True  # ffmpeg has stopped: its status and log say why
                break
            count += 1
        if proc is None:
            raise ValueError(f"{path}: no frames to write")
        try:
            proc.stdin.close()
        except (BrokenPipeError, OSError):
            broken = True
        status = proc.wait()
        drain.join()
    except BaseException:
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.wait()
        raise
    said = [line.strip() for line in b"".join(log).decode("utf-8", "replace").splitlines() if line.strip()]
    if status != 0 or broken or said:
        why = said[-1] if said else (f"killed by signal {-status}" if status < 0 else f"exit status {status}")
        if status < 0 and -status == 25:  # SIGXFSZ
            why += " (the file size limit, ulimit -f)"
        code = errno.ENOSPC if "No space left" in " ".join(said) else errno.EIO
        raise WriteError(code, f"{path}: ffmpeg could not write the video: {why}")
    return count


def write_video(frames: Iterable[np.ndarray], path: str, fps: float = 30.0) -> str:
    """Write RGB frames (an iterable of (H, W, 3) uint8; odd sizes are padded to even) to an MP4
    (H.264 by the ffmpeg imageio-ffmpeg bundles, no system libraries), atomically: a temporary
    name, ffmpeg's exit status and error output checked, the file read back (its boxes whole,
    as many frames as were sent), then renamed. Raises ValueError for a path that is not .mp4,
    :class:`~ams_torch.apps.atomic.WriteError` naming the file when writing fails (nothing is
    left under ``path``)."""
    if os.path.splitext(str(path))[1].lower() not in VIDEO_EXTENSIONS:
        raise ValueError(f"{path}: a video is written as .mp4 (got {os.path.splitext(str(path))[1] or 'no extension'})")
    if not (isinstance(fps, (int, float)) and np.isfinite(fps) and 0 < fps <= MAX_FPS):
        raise ValueError(f"{path}: fps must be a number in (0, {MAX_FPS:g}]; got {fps!r}")
    sent = {}

    def verify(tmp: str) -> None:
        try:
            got = mp4_frame_count(tmp)
        except ValueError as err:
            raise WriteError(errno.EIO, f"{path}: {str(err).replace(tmp, 'the video')}") from None
        if got != sent["count"]:
            raise WriteError(errno.EIO, f"{path}: the video holds {got} frames, {sent['count']} were written")

    with atomic_path(path, verify=verify) as tmp:
        sent["count"] = _encode(frames, tmp, float(fps), path)
    return path
