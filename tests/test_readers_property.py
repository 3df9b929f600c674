"""Property-based hardening of every groom reader (hypothesis).

For each format: random bytes, truncations of a valid file, and header edits (random counts,
flags, flipped bytes) must give a ``GroomFileError`` or a valid ``Groom`` — never another
exception — and must never allocate more than a small factor of the file's size (measured with
``tracemalloc``, which sees numpy's buffers; USD's C++ allocations are not seen).

Profiles: ``ci`` (default, few examples, the file runs in ~20 s) and ``slow`` (many more):
``HYPOTHESIS_PROFILE=slow pytest tests/test_readers_property.py``.
"""
import itertools
import os
import struct
import tracemalloc
import warnings

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ams_torch.grooms.groom import Groom
from ams_torch.grooms.io import GroomFileError, read_groom, write_groom

settings.register_profile("ci", max_examples=12, deadline=None, derandomize=True,
                          suppress_health_check=[HealthCheck.too_slow])
settings.register_profile("slow", max_examples=600, deadline=None, suppress_health_check=[HealthCheck.too_slow])
_NAME = os.environ.get("HYPOTHESIS_PROFILE", "ci")
PROFILE = settings.get_profile(_NAME if _NAME in ("ci", "slow") else "ci")

#: allocations may reach FACTOR × file size + SLACK bytes (Python objects of the result, parser
#: state); measured on valid 2,000-strand files: 1.7–6.2× the size
FACTOR = 16
SLACK = 1 << 19

FORMATS = [".data", ".hair", ".bin", ".tfx", ".ply", "ascii.ply", ".npz", ".usda", ".usdc"]
#: where the counts and flags live in each format (byte ranges that header edits hit)
HEADERS = {".data": 16, ".hair": 128, ".bin": 16, ".tfx": 160, ".ply": 300, "ascii.ply": 300, ".npz": 200,
           ".usda": 400, ".usdc": 200}
INTERESTING = [0, 1, 2, 3, 7, 255, 256, 65535, 65536, 2 ** 24, 2 ** 31 - 1, 2 ** 31, 2 ** 32 - 1]
_counter = itertools.count()


def _ext(fmt):
    return ".ply" if fmt == "ascii.ply" else fmt


def _needs(fmt):
    if fmt.startswith(".usd"):
        pytest.importorskip("pxr")


@pytest.fixture(scope="module")
def valid(tmp_path_factory):
    """A small valid file of every format (ragged strands where the format allows them)."""
    rng = np.random.default_rng(0)
    strands = [np.cumsum(rng.normal(size=(n, 3)) * 0.004, 0).astype(np.float32) for n in (4, 2, 7, 3, 5)]
    ragged = Groom(strands=strands)
    uniform = Groom(rest_positions=torch.as_tensor(np.stack([np.resize(s, (8, 3)) for s in strands])))
    d = tmp_path_factory.mktemp("valid")
    out = {}
    for fmt in FORMATS:
        if fmt.startswith(".usd") and not _has_pxr():
            continue
        path = d / f"valid{fmt}"
        if fmt == ".tfx":
            write_groom(path, uniform)
        elif fmt == "ascii.ply":
            write_groom(path, ragged, ascii=True)
        else:
            write_groom(path, ragged)
        out[fmt] = path.read_bytes()
    return out


def _has_pxr():
    try:
        import pxr  # noqa: F401
    except ImportError:
        return False
    return True


@pytest.fixture(scope="module")
def scratch(tmp_path_factory):
    return tmp_path_factory.mktemp("cases")


def check_reader(scratch, fmt: str, data: bytes) -> None:
    """Read ``data`` as a ``fmt`` file: a GroomFileError or a sound Groom, bounded memory."""
    path = scratch / f"case{next(_counter)}{_ext(fmt)}"  # a new name each time (USD caches layers by path)
    path.write_bytes(data)
    tracemalloc.start()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # implausible sizes of random data warn, that is fine
            try:
                groom = read_groom(path)
            except GroomFileError as err:
                assert str(err).startswith(str(path)), str(err)
                groom = None
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
        path.unlink()
    assert peak <= FACTOR * len(data) + SLACK, f"{fmt}: peak {peak} bytes for a {len(data)}-byte file"
    if groom is not None:
        assert isinstance(groom, Groom)
        for s in groom.polylines():
            assert s.ndim == 2 and s.shape[1] == 3 and len(s) >= 2 and np.all(np.isfinite(s))


@pytest.mark.parametrize("fmt", FORMATS)
def test_valid_files_read_within_the_memory_bound(valid, scratch, fmt):
    _needs(fmt)
    check_reader(scratch, fmt, valid[fmt])


@pytest.mark.parametrize("fmt", FORMATS)
@PROFILE
@given(data=st.data())
def test_random_bytes(valid, scratch, fmt, data):
    _needs(fmt)
    magic = valid[fmt][: data.draw(st.sampled_from([0, 4, 16]))]  # sometimes past the signature
    check_reader(scratch, fmt, magic + data.draw(st.binary(max_size=600)))


@pytest.mark.parametrize("fmt", FORMATS)
@PROFILE
@given(data=st.data())
def test_truncations(valid, scratch, fmt, data):
    _needs(fmt)
    raw = valid[fmt]
    check_reader(scratch, fmt, raw[: data.draw(st.integers(0, len(raw) - 1))])


@pytest.mark.parametrize("fmt", FORMATS)
@PROFILE
@given(data=st.data())
def test_header_edits(valid, scratch, fmt, data):
    _needs(fmt)
    raw = bytearray(valid[fmt])
    head = min(HEADERS[fmt], len(raw) - 4)
    for _ in range(data.draw(st.integers(1, 3))):
        at = data.draw(st.integers(0, head))
        kind = data.draw(st.sampled_from(["u32", "i32", "byte", "digits"]))
        if kind == "u32":
            raw[at:at + 4] = struct.pack("<I", data.draw(st.sampled_from(INTERESTING)))
        elif kind == "i32":
            raw[at:at + 4] = struct.pack("<i", data.draw(st.integers(-2 ** 31, 2 ** 31 - 1)))
        elif kind == "byte":
            raw[at] ^= data.draw(st.integers(1, 255))
        else:  # text formats: a count becomes a huge number
            digits = str(data.draw(st.sampled_from(INTERESTING[5:]))).encode()
            raw[at:at + len(digits)] = digits
    check_reader(scratch, fmt, bytes(raw))
