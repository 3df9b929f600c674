"""Native backends: built when the simulator is constructed, one warning per backend that cannot be,
``backend="native"`` refusing with the backend and the reason, ``native_status()`` for every kind,
the smoke test after loading, the architecture list of CUDA builds, and a cache that never loads a
damaged library (issue 27 B1–B3, issue 28 item 5).

Subprocess tests start from an empty process (and, where the test says so, an empty cache):
whether something is built or warned is a per-process fact.
"""
from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch
from helpers import built_native

from ams_torch.native import build as _native
from ams_torch.native.cuda_arch import nvcc_arches, parse_arch_list, resolve_arch_list

REPO = Path(__file__).resolve().parents[1]
SCENE = """
import json, os, sys, warnings
import torch
import ams_torch
from ams_torch import testing
from ams_torch.native import build
from ams_torch.stages.collide import SphereCollider
from ams_torch.stages.hair_hair import HairHair
rest = testing.sphere_groom(12, 8, dtype=torch.float64)
kw = dict(colliders=[SphereCollider((0.0, 0.0, 0.0), 0.106)], hair_hair=HairHair(resolution=8))
def ours(caught):
    return [str(w.message) for w in caught if issubclass(w.category, build.NativeBuildWarning)]
"""


def _run(script: str, tmp_path: Path, **env) -> dict:
    full = dict(os.environ, PYTHONPATH=str(REPO), **env)
    proc = subprocess.run([sys.executable, "-c", textwrap.dedent(SCENE) + textwrap.dedent(script)], env=full,
                          capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-4000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_no_compiler_native_raises_auto_warns_once_per_backend_and_runs(tmp_path):
    """CXX pointing nowhere, an empty cache: backend="native" raises naming the backend it needs (the
    CPU library: frame, collisions, grid and banded solve) and why; "auto" warns once, at
    construction, and runs 3 frames on the torch path; nothing warns again (steps, a second simulator)."""
    out = _run("""
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            sim = ams_torch.Simulator(rest, dtype=torch.float64, backend="auto", **kw)
            at_construction = ours(caught)
            state = sim.initial_state()
            for _ in range(3):
                state = sim.step(state)
            try:
                ams_torch.Simulator(rest, dtype=torch.float64, backend="native", **kw)
                error = None
            except ValueError as e:
                error = str(e)
            later = ours(caught)[len(at_construction):]
        print(json.dumps(dict(error=error, warned=at_construction, later=later, backend=sim.config.backend,
                              finite=bool(torch.isfinite(state.x).all()),
                              status=build.native_status()["cpu"]["reason"])))
    """, tmp_path, CXX="/nonexistent/c++", AMS_TORCH_CACHE=str(tmp_path / "cache"))
    assert "1 native backend(s)" in out["error"], out["error"]
    assert "cpu: no C++ compiler ('/nonexistent/c++')" in out["error"], out["error"]
    assert "backend='native'" in out["error"]
    warned = out["warned"]
    assert len(warned) == 1 and "backend 'cpu' unavailable" in warned[0], warned
    assert "no C++ compiler" in out["status"]
    assert out["later"] == [] and out["backend"] == "torch" and out["finite"]
    assert not (tmp_path / "cache").exists() or not any((tmp_path / "cache").iterdir())


def test_construction_builds_every_backend_the_config_needs(tmp_path):
    """With colliders and hair–hair, native_status() shows the CPU library (frame, collision, grid
    and banded kernels) built right after construction, before any step; and nothing is built in
    the steps."""
    built_native("cpu")  # (in the shared cache: the subprocess loads it)
    out = _run("""
        before = {k: build.native_status()[k]["attempted"] for k in ("cpu", "cuda")}
        sim = ams_torch.Simulator(rest, dtype=torch.float64, backend="native", **kw)
        after = {k: build.native_status()[k]["built"] for k in ("cpu",)}
        def refuse(kind, st):
            raise RuntimeError("built inside a step")
        build._build_and_load = refuse
        state = sim.initial_state()
        for _ in range(2):
            state = sim.step(state)
        print(json.dumps(dict(before=before, after=after, backend=sim.config.backend,
                              cuda=build.native_status()["cuda"]["attempted"])))
    """, tmp_path)
    assert not any(out["before"].values()), out
    assert all(out["after"].values()), out
    assert out["backend"] == "native" and not out["cuda"]


def test_simulator_builds_only_its_devices_library(tmp_path):
    """A CPU simulator builds (loads) the CPU library and nothing else: not the CUDA one, not the
    emulations or the self-test; every stage's kernels are then there (one library)."""
    built_native("cpu")
    out = _run("""
        sim = ams_torch.Simulator(rest, dtype=torch.float32)
        st = build.native_status()
        ns = build.native_ops("cpu")
        print(json.dumps(dict(attempted=sorted(k for k in build.kinds() if st[k]["attempted"]),
                              ops=[hasattr(ns, op) for op in ("solve_banded", "frame", "frame_finish", "finish",
                                                              "frame_contact", "frame_posed", "frame_adjoint",
                                                              "collide", "collide_adjoint", "p2g", "pressure", "g2p", "sweeps",
                                                              "sweeps_adjoint")])))
    """, tmp_path)
    assert out["attempted"] == ["cpu"] and all(out["ops"]), out


def test_needed_backends_is_the_devices_library():
    from ams_torch.sim.backends import needed_backends

    assert needed_backends("cpu") == (["cpu"], ["cpu"])
    assert needed_backends("cpu", hair_hair=True, colliders=True) == (["cpu"], ["cpu"])
    assert needed_backends("meta") == ([], [])


def test_native_refuses_a_dtype_without_kernels():
    from ams_torch import testing
    import ams_torch

    from ams_torch.sim.backends import resolve_backend

    with pytest.raises(ValueError, match="no native kernels for cpu/torch.float16"):
        resolve_backend("native", "cpu", torch.float16, hair_hair=False, colliders=0)
    with pytest.raises(ValueError, match="dtype must be torch.float32 or torch.float64"):  # refused at the boundary
        ams_torch.Simulator(testing.sphere_groom(4, 6), dtype=torch.float16, backend="native")


def test_native_status_lists_every_kind():
    st = _native.native_status()
    kinds = _native.kinds()
    assert set(kinds) == {"cpu", "cuda", "cuda_emu", "selftest_cuda", "selftest_cuda_emu"}
    for kind in kinds:
        for key in ("built", "reason", "flags", "attempted", "library", "device", "notes"):
            assert key in st[kind], (kind, key)
        assert st[kind]["built"] or st[kind]["reason"], kind
    if not torch.cuda.is_available():
        assert "no CUDA device" in st["cuda"]["reason"] or "without CUDA" in st["cuda"]["reason"]
    with pytest.raises(ValueError, match="unknown native backend"):
        _native.native_ops("frame_tpu")


def test_failed_smoke_test_makes_the_backend_unavailable(tmp_path):
    """A library that loads but whose probe fails (e.g. built for another GPU architecture) is
    unavailable, with the probe's error as the reason, and warned about once."""
    built_native("cpu")
    out = _run("""
        from ams_torch.native import probes
        real = probes.probe
        def broken(kind, ns, device):
            if kind == "cpu":
                raise AssertionError("solve_banded: relative difference 1 from the torch definition")
            return real(kind, ns, device)
        probes.probe = broken
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            first, second = build.native_ops("cpu"), build.native_ops("cpu")
        st = build.native_status()["cpu"]
        print(json.dumps(dict(none=first is None and second is None, built=st["built"], reason=st["reason"],
                              warned=len(ours(caught)))))
    """, tmp_path)
    assert out["none"] and not out["built"] and out["warned"] == 1
    assert "smoke test failed" in out["reason"] and "relative difference" in out["reason"]


# -- the cache: a damaged library is never loaded, and is rebuilt -------------------------------

TOY = """
import json, os, sys, warnings
from pathlib import Path
from ams_torch.native import build
root = Path(sys.argv[1])
build.CSRC_ROOT = root / "csrc"  # a backend of one small C++ file (no torch headers: builds in a second)
build._ALL["toy_cpu"] = ("ams_torch_toy_cpu", ("toy/toy.cpp",), (), "ams_torch_toy_cpu", "cpu")
build._state["toy_cpu"] = build._fresh_state()
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    ok = build.native_ops("toy_cpu") is not None
st = build.native_status()["toy_cpu"]
print(json.dumps(dict(ok=ok, reason=st["reason"], library=st["library"], build_dir=st["build_dir"],
                      warned=sum(issubclass(w.category, build.NativeBuildWarning) for w in caught))))
"""


@pytest.fixture(scope="module")
def toy_cache(tmp_path_factory):
    """A cache holding one built toy backend; returns a function that loads it in a new process."""
    root = tmp_path_factory.mktemp("toy")
    (root / "csrc" / "toy").mkdir(parents=True)
    (root / "csrc" / "toy" / "toy.cpp").write_text('extern "C" int ams_torch_toy() { return 42; }\n')

    def load() -> dict:
        env = dict(os.environ, PYTHONPATH=str(REPO), AMS_TORCH_CACHE=str(root / "cache"))
        proc = subprocess.run([sys.executable, "-c", TOY, str(root)], env=env, capture_output=True, text=True,
                              timeout=300)
        assert proc.returncode == 0, f"rc {proc.returncode}: {proc.stderr[-3000:]}"
        return json.loads(proc.stdout.strip().splitlines()[-1])

    first = load()
    assert first["ok"], first
    return load, Path(first["build_dir"])


@pytest.mark.parametrize("damage", ["truncated", "empty", "random", "no_hash"])
def test_damaged_cached_library_is_rebuilt_not_loaded(toy_cache, damage):
    """The cached library damaged (a truncated one used to kill every process with SIGBUS; an empty
    or random one fell back to torch and was never rebuilt): the next process checks the recorded
    size and SHA-256 before loading, rebuilds (relinks: the cached objects are intact), loads the
    new library and records it."""
    load, build_dir = toy_cache
    marker = json.loads((build_dir / _native.MARKER_NAME).read_text())
    lib = build_dir / marker["library"]
    data = lib.read_bytes()
    if damage == "truncated":
        lib.write_bytes(data[: len(data) // 3])
    elif damage == "empty":
        lib.write_bytes(b"")
    elif damage == "random":
        lib.write_bytes(os.urandom(len(data)))
    else:  # a marker of the old format: no size and hash recorded
        (build_dir / _native.MARKER_NAME).write_text(json.dumps({"library": marker["library"], "key": marker["key"]}))
    assert _native._cached_library(build_dir) is None
    out = load()
    assert out["ok"] and out["warned"] == 0 and Path(out["library"]) == lib, out
    fresh = json.loads((build_dir / _native.MARKER_NAME).read_text())
    assert fresh["size"] == lib.stat().st_size > 0 and _native._cached_library(build_dir) == lib


def test_intact_cached_library_is_loaded_as_it_is(tmp_path):
    built_native("cpu")
    src = Path(_native.native_status()["cpu"]["build_dir"])
    dst = tmp_path / "cache" / src.name
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("*.lock", "lock"))
    lib = _native._cached_library(dst)
    assert lib is not None
    stamp = lib.stat().st_mtime_ns
    out = _run("""
        ok = build.native_ops("cpu") is not None
        print(json.dumps(dict(ok=ok)))
    """, tmp_path, AMS_TORCH_CACHE=str(tmp_path / "cache"))
    assert out["ok"] and lib.stat().st_mtime_ns == stamp


# -- CUDA architectures (B1) ----------------------------------------------------------------------

TORCH_ARCHES = ["sm_75", "sm_80", "sm_86", "sm_90", "sm_100", "sm_120", "compute_120"]
NVCC13 = {"7.5", "8.0", "8.6", "8.7", "8.8", "8.9", "9.0", "10.0", "10.3", "11.0", "12.0", "12.1"}


def test_arch_list_unset_follows_the_devices_clamped_with_ptx():
    assert resolve_arch_list(None, [(9, 0)], TORCH_ARCHES, NVCC13) == ("9.0+PTX", [])
    archs, notes = resolve_arch_list("", [(9, 0), (8, 0), (9, 0)], TORCH_ARCHES, NVCC13)
    assert archs == "8.0;9.0+PTX" and notes == []
    # a GPU newer than torch and the toolkit: the newest supported architecture, as PTX
    archs, notes = resolve_arch_list(None, [(13, 0)], TORCH_ARCHES, NVCC13)
    assert archs == "12.0+PTX" and "newer" in notes[0]
    archs, _ = resolve_arch_list(None, [(12, 0)], TORCH_ARCHES, {"7.5", "8.0", "9.0"})  # an older nvcc
    assert archs == "9.0+PTX"


def test_arch_list_preset_is_checked_and_completed():
    archs, notes = resolve_arch_list("5.2;7.0;8.0", [(9, 0)], TORCH_ARCHES, NVCC13)
    assert archs == "8.0;9.0"
    assert any("5.2 left out" in n for n in notes) and any("7.0 left out" in n for n in notes)
    assert any("added 9.0" in n for n in notes)
    archs, notes = resolve_arch_list("Hopper", [(9, 0)], TORCH_ARCHES, NVCC13)
    assert archs == "9.0+PTX" and notes == []
    archs, notes = resolve_arch_list("8.0 9.0a", [], TORCH_ARCHES, None)  # no device, nvcc unknown
    assert archs == "8.0;9.0a" and notes == []
    with pytest.raises(ValueError, match="no architecture left"):
        resolve_arch_list("5.2;6.1", [], TORCH_ARCHES, NVCC13)
    with pytest.raises(ValueError, match="'sm90' is not an architecture"):
        parse_arch_list("8.0;sm90")
    with pytest.raises(ValueError, match="no CUDA device"):
        resolve_arch_list(None, [], TORCH_ARCHES, NVCC13)


def test_nvcc_arches_parses_the_toolkit():
    nvcc = shutil.which("nvcc")
    if nvcc is None:
        pytest.skip("nvcc not found")
    found = nvcc_arches(nvcc)
    assert found and "9.0" in found and "8.0" in found
    assert nvcc_arches("/nonexistent/nvcc") is None


def test_cache_key_covers_every_header_a_build_reads(tmp_path, monkeypatch):
    """Touching a header included only indirectly (frame.h -> collide.h) changes the cache tag of
    every backend that reads it, and of no other (the CPU and CUDA libraries and the CUDA
    emulation read it, the self-test does not)."""
    import shutil

    from ams_torch.native import build

    copy = tmp_path / "csrc"
    shutil.copytree(build.CSRC_ROOT, copy)
    monkeypatch.setattr(build, "CSRC_ROOT", copy)
    monkeypatch.setattr(build.emulation, "SHIM_DIR", copy / "emulation")
    key = {"probe": 1}
    assert "collide/collide.h" in build.include_closure(("frame/frame_cpu.cpp",))  # through frame/frame.h
    before = {k: build.build_tag(k, key) for k in build._ALL}
    readers = {k for k, spec in build._ALL.items() if "collide/collide.h" in build.include_closure(spec[1])}
    assert readers == {"cpu", "cuda", "cuda_emu"}
    with open(copy / "collide" / "collide.h", "a") as fh:
        fh.write("\n// touched\n")
    after = {k: build.build_tag(k, key) for k in build._ALL}
    assert {k for k in before if before[k] != after[k]} == readers


def test_one_library_per_device_one_namespace_one_contraction_setting():
    """Every source of the CPU (CUDA) library registers its functions under that library's one
    namespace, and nowhere else; every op group's sources are in it; no source or header sets its
    own floating-point contraction (a pragma would give shared inline/template functions a
    different rounding per source, and the linker keeps one copy): the build's flag does, for all."""
    from ams_torch.native import build

    register = re.compile(r"\bTORCH_LIBRARY(?:_FRAGMENT|_IMPL)?\s*\(\s*(\w+)")
    for kind, (_, sources, headers, namespace, _) in build._BACKENDS.items():
        assert set(sources) == {s for group in build.GROUPS.values() for s in group[kind == "cuda"]}, kind
        found = {ns for src in sources for ns in register.findall((build.CSRC_ROOT / src).read_text())}
        assert found == {namespace}, (kind, found)
    for path in build.CSRC_ROOT.rglob("*"):
        if path.suffix in (".cpp", ".cu", ".h", ".cuh") and "emulation" not in path.parts:
            assert not re.search(r"#\s*pragma\s+(GCC\s+optimize|clang\s+fp|STDC\s+FP_CONTRACT)", path.read_text()), path
    for device in ("cpu", "emulation"):
        cflags = build._build_config(device)[0]
        assert "-ffp-contract=off" in cflags and not any(f.startswith("-ffp-contract=") and f != "-ffp-contract=off"
                                                        for f in cflags), (device, cflags)


def test_includes_are_path_qualified(tmp_path, monkeypatch):
    """Every csrc/ include names its file from csrc/ (the one include directory); an include written
    relative to the includer's folder, which the compiler would still find, is refused by the
    include closure (it would read a file that the cache key does not hash)."""
    from ams_torch.native import build

    for spec in {**build._BACKENDS, **build._SELFTEST}.values():
        for rel in spec[1] + spec[2]:
            for inc in build._INCLUDE.findall((build.CSRC_ROOT / rel).read_text()):
                assert not (build.CSRC_ROOT / rel).parent.joinpath(inc).is_file() or "/" in inc, (rel, inc)
    copy = tmp_path / "csrc"
    shutil.copytree(build.CSRC_ROOT, copy)
    monkeypatch.setattr(build, "CSRC_ROOT", copy)
    src = copy / "frame" / "frame_cpu.cpp"
    src.write_text(src.read_text().replace('#include "frame/ftl.h"', '#include "ftl.h"')
                   .replace('#include "frame/frame.h"', '#include "frame.h"'))
    with pytest.raises(ValueError, match="relative to its folder"):
        build.include_closure(("frame/frame_cpu.cpp",))


@pytest.mark.parametrize("backend,contact,colliders,hair_hair,grad,want", [
    ("torch", "frame", 0, False, False, "torch"),
    ("torch", "substep", 2, True, True, "torch"),
    ("native", "frame", 0, False, False, "native_finish"),
    ("native", "frame", 1, False, False, "native"),
    ("native", "frame", 0, True, False, "native"),
    ("native", "substep", 1, False, False, "native_contact"),
    ("native", "substep", 0, False, False, "native_finish"),  # substep contact without colliders: none
    ("native", "frame", 1, True, True, "native_adjoint"),
    ("native", "substep", 1, False, True, "native_adjoint_contact"),  # substep by substep, the contact between
])
def test_frame_route(backend, contact, colliders, hair_hair, grad, want):
    """The one decision of how a frame's dynamics run (sim.backends.frame_route)."""
    from ams_torch.sim.backends import FRAME_ROUTES, frame_route
    from ams_torch.sim.state import Config

    cfg = Config(dt=0.02, backend=backend, contact=contact, colliders=colliders, hair_hair=hair_hair)
    assert frame_route(cfg, grad) == want and want in FRAME_ROUTES
