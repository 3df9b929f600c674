"""The first GPU run: every check of the CUDA path in one command, within 8 minutes on one H100/H200.

    scripts/validate_cuda.sh OUT_DIR                 # on the GPU machine (drives this script)
    scripts/validate_cuda.sh OUT_DIR --dry-run       # the same Python on the CPU at toy sizes (make test)
    python scripts/validate_cuda.py OUT_DIR [--dry-run] [--only STEP ...] [--budget-s 470]

Steps (each in its own process with its own timeout, so a failing or hanging step does not stop
the others; every result is written as soon as it is known):

  preflight  CUDA torch, a GPU, nvcc's CUDA major = torch's, ninja, a C++ compiler; versions.
  build      every backend (CUDA, CPU, the emulator's self-test) from an empty cache
             (OUT_DIR/cache), in parallel; a backend that does not build is a failure.
  tests      the CUDA tests (pytest -k cuda over the native, CUDA-device and CUDA-graph tests; --dry-run:
             collected, and tests/test_cuda_device.py run on the CPU with AMS_TORCH_CUDA_TEST_DEVICE=cpu).
  compile    torch.compile(sim.step, fullgraph=True) (inductor) of an every-stage scene, vs eager.
  parity     the default scene (make demo), 120 frames, CPU vs CUDA: float64 <= 1e-9 m, float32
             <= 1e-4 m (max |x| difference over every particle and frame).
  sizes      what the tests never reach: a 1M-strand banded solve (residual), 20k strands x 3 scenes
             every stage, N = 128 (CUDA vs CPU on a sample of strands).
  graph      the step captured in a CUDA graph (GraphedStep) at 1k and 10k strands: replay vs
             eager, ms/frame.
  ptxas      registers/spills of every kernel for this device's architecture (and the budget).
  bench      scripts/bench_frame.py --device cuda at 1k / 10k / 100k strands x 32 particles ->
             OUT_DIR/benchmarks/cuda.{md,json} (copy to docs/benchmarks/ to publish).
  sanitizer  compute-sanitizer memcheck and racecheck of two small frames (optional: skipped when
             the tool is missing or the time is short).

OUT_DIR/summary.md and summary.json: pass/fail/skip per step with its numbers, the device, the
versions; OUT_DIR/steps/<step>.log: each step's output. Exit status 0 when no step failed.
With --dry-run the steps run on the CPU at toy sizes (the emulated CUDA backends stand in for the
CUDA ones, the eager stand-in for the graph capture); make test runs it (tests/test_validate_cuda.py).
"""
from __future__ import annotations

import argparse
import functools
import json
import os
import platform
import shutil
import subprocess
import sys
import time
import traceback
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

#: (step, timeout s on the GPU, least time worth starting it with)
STEPS = (("preflight", 60, 5), ("build", 200, 60), ("tests", 150, 30), ("compile", 90, 20), ("parity", 70, 15),
         ("sizes", 80, 20), ("graph", 40, 10), ("ptxas", 60, 10), ("bench", 150, 30), ("sanitizer", 90, 40))
TOLERANCE = {"float64": 1e-9, "float32": 1e-4}  # m, parity CPU vs CUDA over the default scene


class Skip(Exception):
    """The step does not apply here (the message says why)."""


def sizes(dry: bool) -> dict:
    """Problem sizes of every step: the real ones, or toy ones for the dry run."""
    if dry:
        return dict(parity_strands=24, parity_frames=4, banded_strands=2000, big_strands=40, big_scenes=3,
                    long_strands=6, long_n=128, sample=12, graph_strands=(20,), graph_frames=3, compile_strands=20,
                    bench_strands=(40,), bench_scenes=("dynamics",), head_subdivisions=2, sdf=16, grid=8)
    return dict(parity_strands=None, parity_frames=120, banded_strands=1_000_000, big_strands=20_000, big_scenes=3,
                long_strands=2_000, long_n=128, sample=512, graph_strands=(1_000, 10_000), graph_frames=30,
                compile_strands=1_000, bench_strands=(1_000, 10_000, 100_000), bench_scenes=("dynamics", "every_stage"),
                head_subdivisions=4, sdf=64, grid=64)


# ----------------------------------------------------------------------------------------------
# the steps: each returns a dict of results ("status" defaults to pass), raises Skip or fails
# ----------------------------------------------------------------------------------------------

def step_preflight(ctx: dict) -> dict:
    import torch
    from torch.utils import cpp_extension

    from ams_torch.native import ptxas

    info = {"torch": torch.__version__, "torch_cuda": torch.version.cuda, "python": platform.python_version(),
            "cuda_available": torch.cuda.is_available(), "ninja": cpp_extension.is_ninja_available(),
            "cxx": shutil.which(os.environ.get("CXX", "c++")), "cpu_count": os.cpu_count(),
            "compute_sanitizer": _sanitizer()}
    nvcc = ptxas.find_nvcc()
    info["nvcc"] = nvcc
    if nvcc:
        out = subprocess.run([nvcc, "--version"], capture_output=True, text=True).stdout
        info["nvcc_version"] = out.strip().splitlines()[-1] if out.strip() else None
        rel = [w for w in out.replace(",", " ").split() if w[:1].isdigit() and "." in w]
        info["nvcc_release"] = rel[0] if rel else None
    problems = []
    if not info["ninja"]:
        problems.append("ninja is not installed")
    if not info["cxx"]:
        problems.append("no C++ compiler")
    if torch.cuda.is_available():
        dev = torch.cuda.current_device()
        p = torch.cuda.get_device_properties(dev)
        info.update(device=p.name, capability=f"{p.major}.{p.minor}", sms=p.multi_processor_count,
                    memory_gib=round(p.total_memory / 2 ** 30, 1), device_count=torch.cuda.device_count())
        try:
            info["driver"] = subprocess.run(["nvidia-smi", "--query-gpu=driver_version", "--format=csv,noheader"],
                                            capture_output=True, text=True, timeout=20).stdout.strip() or None
        except (OSError, subprocess.SubprocessError):
            info["driver"] = None
    if not ctx["dry"]:
        if torch.version.cuda is None:
            problems.append("this torch has no CUDA")
        if not torch.cuda.is_available():
            problems.append("no CUDA device visible")
        if nvcc is None:
            problems.append("nvcc not found (set CUDA_HOME)")
        elif torch.version.cuda and info.get("nvcc_release") and \
                info["nvcc_release"].split(".")[0] != torch.version.cuda.split(".")[0]:
            problems.append(f"nvcc {info['nvcc_release']} and torch's CUDA {torch.version.cuda} differ in major "
                            "version")
    info["status"] = "fail" if problems else "pass"
    info["detail"] = "; ".join(problems) or ("dry run on the CPU" if ctx["dry"] else f"{info.get('device')}")
    return info


def _kinds(dry: bool) -> list:
    from ams_torch.native import build

    cpu = build.kinds("cpu")
    other = build.kinds("emulation") if dry else build.kinds("cuda")
    return other + cpu


def step_build(ctx: dict) -> dict:
    from ams_torch.native import build

    kinds = _kinds(ctx["dry"])
    if ctx["dry"]:  # the shared cache, in this process (make test has built them already)
        results = {}
        for kind in kinds:
            build.native_ops(kind)
            results[kind] = build.native_status()[kind]
    else:  # an empty cache, one process per backend, in parallel
        jobs = max(1, (os.cpu_count() or 4) // max(1, min(len(kinds), 6)))
        env = dict(os.environ, MAX_JOBS=str(jobs))
        code = ("import json, sys; from ams_torch.native import build; k = sys.argv[1]; build.native_ops(k); "
                "print(json.dumps(build.native_status()[k]))")

        def one(kind):
            proc = subprocess.run([sys.executable, "-c", code, kind], env=env, capture_output=True, text=True,
                                  cwd=ROOT, timeout=ctx["timeout"])
            try:
                return kind, json.loads(proc.stdout.strip().splitlines()[-1])
            except (ValueError, IndexError):
                return kind, {"built": False, "reason": f"rc {proc.returncode}: {proc.stderr[-1500:]}"}

        with ThreadPoolExecutor(max_workers=min(len(kinds), 6)) as pool:
            results = dict(pool.map(one, kinds))
    failed = {k: r["reason"] for k, r in results.items() if not r.get("built")}
    table = {k: {"built": r.get("built"), "seconds": r.get("build_seconds"), "flags": r.get("flags"),
                 "notes": r.get("notes"), "reason": r.get("reason")} for k, r in results.items()}
    return {"status": "fail" if failed else "pass", "detail": "; ".join(f"{k}: {v}" for k, v in failed.items())
            or f"{len(results)} backends built", "backends": table}


TEST_FILES = ("tests/test_cuda_device.py", "tests/test_cuda_graph.py", "tests/test_native_solver.py",
              "tests/test_native_frame.py", "tests/test_native_collide.py", "tests/test_native_grid.py",
              "tests/test_native_finish.py", "tests/test_step.py", "tests/test_hair_hair.py")


def step_tests(ctx: dict) -> dict:
    xml = ctx["out"] / "tests.xml"
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *TEST_FILES]
    cmd += ["--collect-only"] if ctx["dry"] else ["-k", "cuda and not nvcc and not binding_compiles", "-ra",
                                                  f"--junitxml={xml}"]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=ctx["timeout"])
    tail = proc.stdout.strip().splitlines()[-1:] or [""]
    print(proc.stdout[-6000:], proc.stderr[-3000:])
    if ctx["dry"] and proc.returncode == 0:
        # the GPU-only test module's code on the CPU (its device and reference are then the same
        # kernels): a test that went stale against the ops fails here, not on the first GPU
        env = dict(os.environ, AMS_TORCH_CUDA_TEST_DEVICE="cpu")
        proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", TEST_FILES[0]],
                              capture_output=True, text=True, cwd=ROOT, timeout=ctx["timeout"], env=env)
        print(proc.stdout[-6000:], proc.stderr[-3000:])
        tail = [f"{tail[0]}; {TEST_FILES[0]} on the CPU: " + ((proc.stdout.strip().splitlines() or [""])[-1])]
    return {"status": "pass" if proc.returncode == 0 else "fail", "detail": tail[0], "returncode": proc.returncode}


@functools.lru_cache(maxsize=8)
def _groom(subdivisions: int, sdf: int, strands: int, particles: int):
    """(head SDF grid, rest shape) of a hanging groom: built once per process and size."""
    import ams_torch as at
    from ams_torch.geometry.sdf import SDFGrid
    from ams_torch.grooms.head import hanging_groom

    head = at.default_head(subdivisions)
    grid = SDFGrid.from_mesh(head, resolution=sdf)
    return grid, hanging_groom(head, strands, particles, 0.25, sdf=grid, seed=1)


def _every_stage(device, dtype, strands: int, s: dict, particles: int = 32):
    """A simulator of a hanging groom with every stage: head collisions, hair–hair."""
    import ams_torch as at

    grid, rest = _groom(s["head_subdivisions"], s["sdf"], strands, particles)
    return at.Simulator(rest, at.Params(), device=device, dtype=dtype, colliders=[at.MeshCollider(grid)],
                        hair_hair=at.HairHair(resolution=s["grid"]))


def _sync(device) -> None:
    import torch

    if str(device).startswith("cuda"):
        torch.cuda.synchronize()


def step_compile(ctx: dict) -> dict:
    import torch

    from ams_torch.apps.motion import Shake

    s, device = ctx["sizes"], ctx["device"]
    sim = _every_stage(device, torch.float32, s["compile_strands"], s)
    poses = Shake(amplitude=1.0).poses(4, sim.params.dt, device=device)
    explained = torch._dynamo.explain(sim.step)(sim.initial_state(), poses[0])
    torch._dynamo.reset()
    t0 = time.perf_counter()
    compiled = torch.compile(sim.step, fullgraph=True, backend="eager" if ctx["dry"] else "inductor")
    se = sc = sim.initial_state()
    sc = compiled(sc, poses[0])
    _sync(device)
    compile_s = time.perf_counter() - t0
    se = sim.step(se, poses[0])
    for pose in poses[1:]:
        se, sc = sim.step(se, pose), compiled(sc, pose)
    err = float((sc.x - se.x).abs().max())
    ok = explained.graph_break_count == 0 and err <= 1e-5
    return {"status": "pass" if ok else "fail", "graph_breaks": explained.graph_break_count, "max_dx_m": err,
            "compile_s": round(compile_s, 1), "detail": f"{explained.graph_break_count} graph breaks, compiled vs "
                                                      f"eager max |dx| {err:.2g} m over 4 frames"}


def _default_scene(strands, frames, device, dtype):
    import tomllib

    from ams_torch.apps.scene import build
    from ams_torch.apps.scene.schema import parse_scene

    path = ROOT / "datasets" / "scenes" / "default.toml"
    raw = tomllib.loads(path.read_text())
    raw["frames"] = int(frames)
    if strands:
        raw.setdefault("groom", {})["strands"] = int(strands)
    return build(parse_scene(raw, where=str(path), base=str(path.parent)), device=device, dtype=dtype)


def step_parity(ctx: dict) -> dict:
    import torch

    s = ctx["sizes"]
    out = {}
    for dtype in (torch.float64, torch.float32):
        cpu = _default_scene(s["parity_strands"], s["parity_frames"], "cpu", dtype)
        runs = {"cpu": cpu, "device": cpu if ctx["device"] == "cpu" else  # (dry run: the same simulator twice)
                _default_scene(s["parity_strands"], s["parity_frames"], ctx["device"], dtype)}
        states = {d: r.sim.initial_state() for d, r in runs.items()}
        worst = 0.0
        dt = cpu.sim.params.dt
        for k in range(s["parity_frames"]):
            for d, r in runs.items():
                states[d] = r.sim.step(states[d], r.motion((k + 1) * dt, dtype=dtype).to(device=r.sim.device))
            worst = max(worst, float((states["device"].x.cpu() - states["cpu"].x).abs().max()))
        name = str(dtype).split(".")[-1]
        out[name] = {"max_dx_m": worst, "bound_m": TOLERANCE[name], "S": runs["cpu"].sim.model.num_strands,
                     "frames": s["parity_frames"], "backend": runs["device"].sim.config.backend}
    ok = all(v["max_dx_m"] <= v["bound_m"] for v in out.values())
    return {"status": "pass" if ok else "fail", "results": out,
            "detail": ", ".join(f"{k} max |dx| {v['max_dx_m']:.3g} m (bound {v['bound_m']:g})" for k, v in out.items())}


def _rel(a, b) -> float:
    a, b = a.double().cpu(), b.double().cpu()
    den = float(b.norm())
    return float((a - b).norm()) / den if den > 0 else float((a - b).norm())


def step_sizes(ctx: dict) -> dict:
    import torch

    import ams_torch as at
    from ams_torch.apps.motion import Shake
    from ams_torch.solver.op import solve_banded
    from ams_torch.solver.reference import banded_matvec

    s, device = ctx["sizes"], ctx["device"]
    res = {}
    # 1. the banded solve of 1M strands x 32 particles (float32): relative residual
    sys.path.insert(0, str(ROOT / "tests"))
    from native_cases import strand_system

    base = min(s["banded_strands"], 10_000)  # a base set of systems, tiled on the device
    blocks, rhs = strand_system(base, 32, dtype=torch.float32, device=device, seed=3)
    reps = s["banded_strands"] // base
    blocks, rhs = blocks.repeat(reps, 1, 1, 1, 1), rhs.repeat(reps, 1, 1)
    _sync(device)
    t0 = time.perf_counter()
    x = solve_banded(blocks, rhs, check=False)
    _sync(device)
    seconds = time.perf_counter() - t0
    pick = torch.randperm(blocks.shape[0], generator=torch.Generator().manual_seed(1))[:2000].to(device)
    res["banded_solve"] = {"strands": int(blocks.shape[0]), "seconds": round(seconds, 3),
                           "residual": _rel(banded_matvec(blocks[pick].double(), x[pick].double()), rhs[pick].double())}
    del blocks, rhs, x
    # 2. every stage, 20k strands x 3 scenes: one frame on the device vs the CPU, a sample of strands
    # (strands interact through the grid: the sample is compared after the same frame on both)
    for name, strands, n, scenes in (("every_stage", s["big_strands"], 32, s["big_scenes"]),
                                     ("long_strands", s["long_strands"], s["long_n"], 1)):
        out = {}
        for dtype in (torch.float64, torch.float32):
            sims = {d: _every_stage(d, dtype, strands, s, particles=n) for d in ("cpu", device)}
            poses = Shake(amplitude=0.8).poses(3, sims["cpu"].params.dt, dtype=dtype)
            pose0 = at.Pose.stack([poses[0]] * scenes) if scenes > 1 else poses[0]
            pose1 = at.Pose.stack([poses[1]] * scenes) if scenes > 1 else poses[1]
            states = {d: sims[d].step(sims[d].initial_state(pose0.to(device=d)), pose1.to(device=d)) for d in sims}
            _sync(device)
            pick = torch.randperm(strands, generator=torch.Generator().manual_seed(0))[:s["sample"]]
            got, want = states[device].x.cpu()[..., pick, :, :], states["cpu"].x[..., pick, :, :]
            out[str(dtype).split(".")[-1]] = {"max_dx_m": float((got - want).abs().max()), "rel": _rel(got, want)}
        res[name] = {"strands": strands, "particles": n, "scenes": scenes, **out}
    ok = res["banded_solve"]["residual"] <= 1e-4 and all(r["float64"]["max_dx_m"] <= 1e-9 and r["float32"]["max_dx_m"]
                                                         <= 1e-4 for k, r in res.items() if k != "banded_solve")
    detail = (f"{res['banded_solve']['strands']:,}-strand solve residual {res['banded_solve']['residual']:.2g}; "
              f"every stage "
              f"{res['every_stage']['float64']['max_dx_m']:.2g} / {res['every_stage']['float32']['max_dx_m']:.2g} m; "
              f"N={s['long_n']} {res['long_strands']['float64']['max_dx_m']:.2g} / "
              f"{res['long_strands']['float32']['max_dx_m']:.2g} m (f64 / f32)")
    return {"status": "pass" if ok else "fail", "results": res, "detail": detail}


def step_graph(ctx: dict) -> dict:
    import torch

    from ams_torch.sim.cuda_graph import GraphedStep, eager_capture
    from ams_torch.apps.motion import Shake

    s, device = ctx["sizes"], ctx["device"]
    out = {}
    for strands in s["graph_strands"]:
        sim = _every_stage(device, torch.float32, strands, s)
        frames = Shake(amplitude=0.6).poses(s["graph_frames"] + 1, sim.params.dt, device=device)
        graphed = GraphedStep(sim, capture=None if not ctx["dry"] else eager_capture, clone=False)
        se = sg = sim.initial_state()
        se, sg = sim.step(se, frames[0]), graphed(sg, frames[0])  # capture
        times = {"eager": 0.0, "graph": 0.0}
        for pose in frames[1:]:
            for name in ("eager", "graph"):
                _sync(device)
                t0 = time.perf_counter()
                if name == "eager":
                    se = sim.step(se, pose)
                else:
                    sg = graphed(sg, pose)
                _sync(device)
                times[name] += time.perf_counter() - t0
        err = float((sg.x - se.x).abs().max())
        k = len(frames) - 1
        out[strands] = {"eager_ms": round(1e3 * times["eager"] / k, 3), "graph_ms": round(1e3 * times["graph"] / k, 3),
                        "max_dx_m": err, "captures": graphed.captures, "replays": graphed.replays}
    ok = all(r["max_dx_m"] <= 1e-5 and r["captures"] == 1 for r in out.values())
    detail = "; ".join(f"{n:,} strands: eager {r['eager_ms']} ms, graph {r['graph_ms']} ms/frame"
                       for n, r in out.items())
    return {"status": "pass" if ok else "fail", "results": out, "detail": detail}


def step_ptxas(ctx: dict) -> dict:
    import torch

    from ams_torch.native import ptxas

    nvcc = ptxas.find_nvcc()
    if nvcc is None:
        raise Skip("nvcc not found")
    if ctx["dry"]:
        arch = "90"
    elif not torch.cuda.is_available():
        raise Skip("no CUDA device: no architecture to compile for")
    else:
        major, minor = torch.cuda.get_device_capability()
        arch = f"{major}{minor}"
    found = ptxas.reports([arch], nvcc, jobs=4)
    budget = ptxas.load_budget()
    bad = ptxas.violations(found, budget) if arch in budget["arches"] else []
    (ctx["out"] / "ptxas.json").write_text(json.dumps(found, indent=1, sort_keys=True))
    print(ptxas.table(found))
    spills = {k: v["spill_bytes"] for k, v in found[arch].items() if v["spill_bytes"]}
    regs = {k: v["registers"] for k, v in found[arch].items() if "frame_kernel" in k or "stage_kernel" in k
            or "solve_kernel" in k or "adjoint_kernel" in k}
    if arch not in budget["arches"]:  # no budget to judge by: any spill fails
        bad = [f"sm_{arch} {k}: spills {b} bytes" for k, b in spills.items()]
    status = "fail" if bad else "pass"  # spills within the committed budget (docs/cuda.md) pass
    return {"status": status, "arch": f"sm_{arch}", "spills": spills, "registers": regs, "over_budget": bad,
            "detail": f"sm_{arch}: {len(found[arch])} kernels, {len(spills)} spilling, {len(bad)} over budget"
                      + ("" if arch in budget["arches"] else " (no budget for this architecture)")}


def step_bench(ctx: dict) -> dict:
    s = ctx["sizes"]
    out = ctx["out"] / "benchmarks" / ("cuda_dry" if ctx["dry"] else "cuda")
    cmd = [sys.executable, str(ROOT / "scripts" / "bench_frame.py"), "--device", ctx["device"], "--strands",
           *map(str, s["bench_strands"]), "--scenes", *s["bench_scenes"], "--no-memory", "--out", str(out),
           "--torch-max-strands", str(10_000 if not ctx["dry"] else 0)]
    cmd += (["--reps", "2", "--case-cap", "5", "--resolution", "8"] if ctx["dry"]
            else ["--reps", "7", "--case-cap", "20"])
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=ctx["timeout"],
                          env=dict(os.environ, PYTHONPATH=str(ROOT)))
    print(proc.stdout[-4000:], proc.stderr[-3000:])
    if proc.returncode != 0:
        return {"status": "fail", "detail": f"bench_frame.py exited {proc.returncode}: {proc.stderr[-300:]}"}
    records = json.loads(out.with_suffix(".json").read_text())["records"]
    frames = {f"{r['scene']} {r['S']} {r['path']}": r["median_ms"] for r in records if r.get("stage") == "frame"}
    return {"status": "pass", "ms_per_frame": frames, "files": [str(out) + ".md", str(out) + ".json"],
            "detail": f"{len(records)} records -> {out}.md"}


def _sanitizer():
    from torch.utils import cpp_extension

    found = shutil.which("compute-sanitizer")
    if found is None and cpp_extension.CUDA_HOME:
        cand = Path(cpp_extension.CUDA_HOME, "bin", "compute-sanitizer")
        found = str(cand) if cand.exists() else None
    return found


SANITIZED = """
import torch, ams_torch as at
from ams_torch.stages.collide import SphereCollider
from ams_torch.apps.motion import Shake
from ams_torch.testing import sphere_groom
sim = at.Simulator(sphere_groom(64, 16), at.Params(), device="cuda", colliders=[SphereCollider((0, 0, 0), 0.106)],
                   hair_hair=at.HairHair(resolution=16))
state = sim.initial_state()
for pose in Shake().poses(2, sim.params.dt, device="cuda"):
    state = sim.step(state, pose)
torch.cuda.synchronize()
print("ok", float(state.x.abs().max()))
"""


def step_sanitizer(ctx: dict) -> dict:
    tool = _sanitizer()
    if ctx["dry"] or tool is None:
        raise Skip("dry run" if ctx["dry"] else "compute-sanitizer not found")
    out = {}
    for check in ("memcheck", "racecheck"):
        cmd = [tool, "--tool", check, "--error-exitcode", "3", "--target-processes", "all", sys.executable, "-c",
               SANITIZED]
        proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=max(10, ctx["timeout"] / 2),
                              env=dict(os.environ, PYTHONPATH=str(ROOT)))
        print(check, proc.stdout[-3000:], proc.stderr[-3000:])
        out[check] = {"returncode": proc.returncode, "summary": (proc.stdout.strip().splitlines() or [""])[-1]}
    ok = all(v["returncode"] == 0 for v in out.values())
    return {"status": "pass" if ok else "fail", "results": out,
            "detail": "; ".join(f"{k}: rc {v['returncode']} {v['summary']}" for k, v in out.items())}


# ----------------------------------------------------------------------------------------------
# driver
# ----------------------------------------------------------------------------------------------

def run_one(name: str, ctx: dict) -> dict:
    """Run step ``name`` here; its result (a failure with the traceback when it raised)."""
    t0 = time.perf_counter()
    try:
        result = globals()[f"step_{name}"](ctx)
        result.setdefault("status", "pass")
    except Skip as e:
        result = {"status": "skip", "detail": str(e)}
    except Exception as e:  # noqa: BLE001 - any error is this step's failure, never the run's
        traceback.print_exc()
        result = {"status": "fail", "detail": f"{type(e).__name__}: {str(e)[:500]}"}
    result["seconds"] = round(time.perf_counter() - t0, 1)
    return result


def _context(out: Path, dry: bool, timeout: float) -> dict:
    return {"out": out, "dry": dry, "device": "cpu" if dry else "cuda", "sizes": sizes(dry), "timeout": timeout}


def _write_summary(out: Path, results: dict, meta: dict) -> None:
    (out / "summary.json").write_text(json.dumps({"meta": meta, "steps": results}, indent=1, default=str))
    pre = results.get("preflight", {})
    lines = ["# CUDA validation" + (" (dry run on the CPU, toy sizes)" if meta["dry"] else ""), "",
             f"Device: {pre.get('device', 'none')} (compute capability {pre.get('capability', '-')}, "
             f"{pre.get('sms', '-')} SMs, {pre.get('memory_gib', '-')} GiB); driver {pre.get('driver', '-')}; "
             f"torch {pre.get('torch', '-')} (CUDA {pre.get('torch_cuda', '-')}); nvcc {pre.get('nvcc_release', '-')}; "
             f"Python {pre.get('python', '-')}; commit {meta.get('commit', '-')}. Started {meta['started']}, "
             f"{meta.get('wall_s', 0):.0f} s.", "", "| step | result | s | detail |", "|---|---|---:|---|"]
    for name, _, _ in STEPS:
        if name in results:
            r = results[name]
            detail = str(r.get("detail", "")).replace("|", "\\|").replace("\n", " ")
            lines.append(f"| {name} | **{r['status']}** | {r.get('seconds', '')} | {detail} |")
    lines += ["", "Per-step output: `steps/<step>.log`; numbers: `summary.json`."]
    (out / "summary.md").write_text("\n".join(lines) + "\n")


def _commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=ROOT,
                              timeout=10).stdout.strip() or "-"
    except (OSError, subprocess.SubprocessError):
        return "-"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--dry-run", action="store_true", help="the CPU at toy sizes (no GPU needed)")
    ap.add_argument("--only", nargs="+", choices=[s for s, _, _ in STEPS])
    ap.add_argument("--budget-s", type=float, default=470.0, help="total time for all steps")
    ap.add_argument("--step", help=argparse.SUPPRESS)  # run one step in this process (the driver's child)
    ap.add_argument("--timeout", type=float, default=600.0, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    out = args.out.resolve()
    (out / "steps").mkdir(parents=True, exist_ok=True)
    if args.step:
        result = run_one(args.step, _context(out, args.dry_run, args.timeout))
        (out / "steps" / f"{args.step}.json").write_text(json.dumps(result, indent=1, default=str))
        return 0
    if not args.dry_run:
        os.environ.setdefault("AMS_TORCH_CACHE", str(out / "cache"))  # every backend from an empty cache
    meta = {"dry": args.dry_run, "started": time.strftime("%Y-%m-%d %H:%M:%S"), "commit": _commit(),
            "cache": os.environ.get("AMS_TORCH_CACHE"), "host": platform.node()}
    t0 = time.monotonic()
    results: dict = {}
    for name, timeout, least in STEPS:
        if args.only and name not in args.only:
            continue
        left = args.budget_s - (time.monotonic() - t0)
        if left < least:
            results[name] = {"status": "skip", "detail": f"out of time ({left:.0f} s left, needs {least} s)"}
        elif args.dry_run:  # the CPU at toy sizes: every step in this process
            results[name] = run_one(name, _context(out, True, 300.0))
        else:
            results[name] = _child(name, out, False, min(timeout, left))
        print(f"[{time.monotonic() - t0:6.1f} s] {name}: {results[name]['status']} - {results[name].get('detail', '')}",
              flush=True)
        meta["wall_s"] = time.monotonic() - t0
        _write_summary(out, results, meta)
    failed = [n for n, r in results.items() if r["status"] == "fail"]
    print(f"summary: {out / 'summary.md'}; " + (f"FAILED: {', '.join(failed)}" if failed else "no step failed"))
    return 1 if failed else 0


def _child(name: str, out: Path, dry: bool, limit: float) -> dict:
    """Run one step in a child process with a time limit; its output goes to steps/<name>.log."""
    log = out / "steps" / f"{name}.log"
    result_file = out / "steps" / f"{name}.json"
    result_file.unlink(missing_ok=True)
    cmd = [sys.executable, str(Path(__file__).resolve()), str(out), "--step", name, "--timeout", str(limit)]
    cmd += ["--dry-run"] if dry else []
    t0 = time.perf_counter()
    with open(log, "w") as f:
        try:
            proc = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT, cwd=ROOT, timeout=limit,
                                  env=dict(os.environ, PYTHONPATH=str(ROOT)))
            rc = proc.returncode
        except subprocess.TimeoutExpired:
            return {"status": "fail", "detail": f"timed out after {limit:.0f} s (log: steps/{name}.log)",
                    "seconds": round(time.perf_counter() - t0, 1)}
    if result_file.exists():
        return json.loads(result_file.read_text())
    return {"status": "fail", "seconds": round(time.perf_counter() - t0, 1),
            "detail": f"the step's process ended with status {rc} and no result (a crash? log: steps/{name}.log)"}


if __name__ == "__main__":
    sys.exit(main())
