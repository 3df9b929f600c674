"""Native hair–hair grid kernels (SPEC §6): torch definition vs native CPU vs CUDA, per stage and
for the whole stage; edge cases; op registration; backend selection and fallback.

The native CPU kernels are built once per session (``native`` fixture; cached across runs in
``~/.cache/ams_torch`` or ``$AMS_TORCH_CACHE``); CUDA cases run only where a GPU is visible.

Tolerances (max |native − torch| / max |torch| per quantity):
* float64: 1e-10 (measured ≤ 1e-15 per stage, ≤ 1e-13 for whole-stage positions whose change
  x' − x is small next to x).
* float32: ``F32_REL = 8 · R · ε₃₂`` (2.3e-5 at R = 24; measured ≤ 7e-7 per stage, 3e-6 on
  velocities after the stage). Both paths compute trilinear weights from grid coordinates
  g = (x − origin)/h of magnitude up to R, so one rounding of g moves a weight by up to
  R · ε₃₂ (ε₃₂ = 2⁻²³ ≈ 1.2e-7), and fused multiply-adds in the kernels round differently from
  torch's separate ops; every later quantity is a weighted sum or a contraction (ω < 1) of
  those. Positions x' are compared with an extra absolute ``4 ulp(max |x|)``: both paths store
  x' = x + Δx rounded to the precision of x (measured: 1 ulp). With detailed collisions, which
  run on that rounded x', a contact normal turns by ~ulp(x)/radius, hence the whole-stage
  velocity bound ``max(F32_REL, 8 ε₃₂ max|x| / collision_radius)`` (measured 1.6e-5).
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch
from conftest import built_native
from torch.utils._python_dispatch import TorchDispatchMode

from ams_torch.geometry.pose import Pose
from ams_torch.solver import build as _native
from ams_torch.stages.hair_hair import HairHair, hair_hair_stage
from ams_torch.stages.hair_hair.native import g2p_op, p2g_op, pressure_op
from ams_torch.stages.hair_hair.pressure import pressure_torch
from ams_torch.stages.hair_hair.transfer import cell_mass, face_views, g2p_torch, p2g_torch, scene_frame

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_hair_hair import head_groom  # noqa: E402  (the tests' input factory)

REPO = Path(__file__).resolve().parents[1]
DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
DTYPES = [torch.float64, torch.float32]
MASS = 1e-6
DT = 1.0 / 60.0
F64_REL = 1e-10


def f32_rel(r: int) -> float:
    return 8 * r * torch.finfo(torch.float32).eps


@pytest.fixture(autouse=True, scope="module")
def one_cpu_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="session")
def native():
    """The native CPU grid namespace, built (or loaded from the cache) once per session."""
    return built_native("grid_cpu")


def _namespace(device: str):
    if device == "cpu":
        return _native.native_ops("grid_cpu")
    ns = _native.native_ops("grid_cuda")
    st = _native.native_status()["grid_cuda"]
    if ns is None and st["reason"].startswith("no CUDA toolkit"):
        pytest.skip(st["reason"])
    assert ns is not None, f"native CUDA grid kernels failed to build: {st['reason']}"
    return ns


# -- input factory (also used by scripts/bench_hair_hair.py) ---------------------------------
def squeeze_scene(dtype=torch.float64, device="cpu", strands=200, particles=10, resolution=24, scenes=2, squeeze=0.85,
                  jitter=1.5e-3, outside=True, seed=0, **config):
    """A head groom squeezed toward the head (density above the target: pressure active), in
    ``scenes`` differently moving scenes, with random velocities and masses, two pinned particles
    per strand and (``outside``) some particles far outside the grid and some half outside.
    The grid: ``HairHair(resolution, **config)`` fitted to the rest groom (target from it).

    Returns dict: grid, x, v (B, S, N, 3), mass (B, S, N) kg, pose (batch B), free (N,) bool, and
    the flattened op inputs xf, vf (B, P, 3), m (B, P), frame (B, 6, 3), dt (0-d tensor).
    """
    g = torch.Generator().manual_seed(seed)
    rest = head_groom(strands, particles, seed=seed, dtype=torch.float64)
    grid = HairHair(resolution=resolution, **config).build(rest, MASS)
    local = rest[None] * squeeze + jitter * torch.randn((scenes,) + rest.shape, generator=g, dtype=torch.float64)
    if outside:
        far = grid.origin + grid.extent * torch.tensor([1.3, 0.5, 0.5], dtype=torch.float64)
        local[:, :5, -1] = far  # fully outside
        local[:, 5:10, -1, 0] = grid.origin[0] - 0.4 * grid.cell_size  # half outside (x face grid)
        local[:, 10:12, -1, 1] = grid.origin[1] + grid.extent + 0.3 * grid.cell_size
    rot = torch.randn(scenes, 3, generator=g, dtype=torch.float64) * 0.4
    pose = Pose.from_rotvec(rot, torch.randn(scenes, 3, generator=g, dtype=torch.float64),
                            torch.randn(scenes, 3, generator=g, dtype=torch.float64),
                            torch.randn(scenes, 3, generator=g, dtype=torch.float64), dtype=torch.float64)
    x = pose.to_world(local.reshape(scenes, -1, 3)).reshape(local.shape)
    v = pose.velocity_at(x.reshape(scenes, -1, 3)).reshape(x.shape)
    v = v + 0.3 * torch.randn(x.shape, generator=g, dtype=torch.float64)
    mass = MASS * (0.5 + torch.rand(x.shape[:-1], generator=g, dtype=torch.float64))
    free = torch.ones(particles, dtype=torch.bool)
    free[:2] = False
    grid = grid.to(device=device, dtype=dtype)
    pose = pose.to(device=device, dtype=dtype)
    x, v, mass, free = (t.to(device) for t in (x.to(dtype), v.to(dtype), mass.to(dtype), free))
    b, p = scenes, strands * particles
    return dict(grid=grid, x=x, v=v, mass=mass, pose=pose, free=free, xf=x.reshape(b, p, 3), vf=v.reshape(b, p, 3),
                m=mass.reshape(b, p), frame=scene_frame(pose, (scenes,), b, dtype, device).contiguous(),
                dt=torch.full((), DT, dtype=dtype, device=device))


def _solve_args(grid):
    cfg = grid.config
    return cfg.pressure_iterations, cfg.jacobi_omega, cfg.volume_stiffness, 1.0 - cfg.flip


def rel(a: torch.Tensor, ref: torch.Tensor) -> float:
    scale = ref.abs().max()
    return float((a - ref).abs().max() / scale) if scale > 0 else float((a - ref).abs().max())


def tol(dtype, r):
    return F64_REL if dtype == torch.float64 else f32_rel(r)


def _check_positions(x_new, x_ref, x_in, dtype, r):
    ulp = 4 * torch.finfo(dtype).eps * float(x_in.abs().max())
    err = float((x_new - x_ref).abs().max())
    assert err <= ulp + tol(dtype, r) * float((x_ref - x_in).abs().max()), err


# -- per-stage parity ------------------------------------------------------------------------
@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", DTYPES)
def test_p2g_parity(native, device, dtype):
    ns = _namespace(device)
    s = squeeze_scene(dtype, device)
    grid = s["grid"]
    args = (s["xf"], s["vf"], s["m"], s["frame"], grid.origin, grid.cell_size, grid.resolution)
    ref = p2g_torch(*args)
    out = ns.p2g(*args)
    assert out.shape == ref.shape == (2, 3, (grid.resolution + 1) * grid.resolution ** 2, 2)
    assert rel(out[..., 0], ref[..., 0]) <= tol(dtype, grid.resolution)
    assert rel(out[..., 1], ref[..., 1]) <= tol(dtype, grid.resolution)
    # the particles fully outside the grid are not on it: total mass = mass of the others
    inside = s["m"].sum(1) - s["mass"][:, :5, -1].sum(1)
    assert torch.allclose(out[..., 0].sum((1, 2)) / 3, inside, rtol=0.02)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", DTYPES)
def test_pressure_parity_dense_squeeze(native, device, dtype):
    ns = _namespace(device)
    s = squeeze_scene(dtype, device)
    grid = s["grid"]
    h, r = grid.cell_size, grid.resolution
    faces = p2g_torch(s["xf"], s["vf"], s["m"], s["frame"], grid.origin, h, r)
    rho = cell_mass(face_views(faces[..., 0], r)) / h ** 3
    assert float(rho.max()) > 1.2 * float(grid.target_density)  # the squeeze is above the target
    phi_t, field_t = pressure_torch(faces, grid.target_density, s["dt"], h, r, *_solve_args(grid))
    phi_n, field_n = ns.pressure(faces, grid.target_density, s["dt"], h, r, *_solve_args(grid))
    assert int((phi_t > 0).sum()) > 20  # pressure active in many cells, in both scenes
    assert bool((phi_t.flatten(1).amax(1) > 0).all())
    assert rel(phi_n, phi_t) <= tol(dtype, r)
    assert rel(field_n, field_t) <= tol(dtype, r)
    # an odd number of sweeps returns the other buffer
    phi_t3, _ = pressure_torch(faces, grid.target_density, s["dt"], h, r, 3, 0.6, 1.0, 0.05)
    phi_n3, _ = ns.pressure(faces, grid.target_density, s["dt"], h, r, 3, 0.6, 1.0, 0.05)
    assert rel(phi_n3, phi_t3) <= tol(dtype, r)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", DTYPES)
def test_g2p_parity(native, device, dtype):
    ns = _namespace(device)
    s = squeeze_scene(dtype, device)
    grid = s["grid"]
    h, r = grid.cell_size, grid.resolution
    faces = p2g_torch(s["xf"], s["vf"], s["m"], s["frame"], grid.origin, h, r)
    _, field = pressure_torch(faces, grid.target_density, s["dt"], h, r, *_solve_args(grid))
    args = (s["xf"], s["vf"], field, s["frame"], grid.origin, s["free"], s["dt"], h, r, 0.05)
    x_t, v_t = g2p_torch(*args)
    x_n, v_n = ns.g2p(*args)
    assert rel(v_n - s["vf"], v_t - s["vf"]) <= tol(dtype, r)
    _check_positions(x_n, x_t, s["xf"], dtype, r)
    pinned = (torch.arange(s["xf"].shape[1], device=device) % s["free"].shape[0]) < 2
    assert torch.equal(x_n[:, pinned], s["xf"][:, pinned]) and torch.equal(v_n[:, pinned], s["vf"][:, pinned])
    far = torch.zeros(200, 10, dtype=torch.bool, device=device)
    far[:5, -1] = True  # outside the grid: no weight, velocity kept
    far = far.reshape(-1)
    assert torch.equal(v_n[:, far], s["vf"][:, far]) and torch.equal(v_t[:, far], s["vf"][:, far])


# -- whole stage -----------------------------------------------------------------------------
@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("detailed", [False, True])
def test_stage_parity(native, device, dtype, detailed):
    _namespace(device)
    s = squeeze_scene(dtype, device, strands=120, detailed_collisions=detailed, collision_radius=3e-3)
    grid = s["grid"]
    out = {b: hair_hair_stage(grid, s["x"], s["v"], s["mass"], s["pose"], DT, s["free"], backend=b)
           for b in ("torch", "native")}
    (x_t, v_t), (x_n, v_n) = out["torch"], out["native"]
    assert x_n.shape == s["x"].shape and v_n.dtype == dtype
    bound = tol(dtype, grid.resolution)
    if detailed and dtype == torch.float32:
        # contacts see x' rounded to float32 by each path: a normal turns by ~ulp(x)/radius
        bound = max(bound, 8 * torch.finfo(dtype).eps * float(s["x"].abs().max()) / grid.config.collision_radius)
    assert rel(v_n - s["v"], v_t - s["v"]) <= bound
    per_strand = s["free"].expand(120, -1).clone()  # a (S, N) mask, here with one more pinned strand
    per_strand[3] = False
    x_s, v_s = hair_hair_stage(grid, s["x"], s["v"], s["mass"], s["pose"], DT, per_strand, backend="native")
    x_r, v_r = hair_hair_stage(grid, s["x"], s["v"], s["mass"], s["pose"], DT, per_strand, backend="torch")
    assert torch.equal(x_s[:, 3], s["x"][:, 3]) and torch.equal(v_s[:, 3], s["v"][:, 3])
    assert rel(v_s - s["v"], v_r - s["v"]) <= bound
    _check_positions(x_n, x_t, s["x"], dtype, grid.resolution)
    assert float((v_t - s["v"]).abs().max()) > 1e-2  # the stage did change velocities


@pytest.mark.parametrize("device", DEVICES)
def test_leading_scene_dims(native, device):
    _namespace(device)
    s = squeeze_scene(torch.float64, device, strands=60, scenes=6)
    x, v, m = (t.reshape(2, 3, *t.shape[1:]) for t in (s["x"], s["v"], s["mass"]))
    pose = Pose(*(t.reshape(2, 3, *t.shape[1:]) for t in (s["pose"].rotation, s["pose"].translation,
                                                          s["pose"].linear_velocity, s["pose"].angular_velocity)))
    x_n, v_n = hair_hair_stage(s["grid"], x, v, m, pose, DT, s["free"], backend="native")
    x_t, v_t = hair_hair_stage(s["grid"], s["x"], s["v"], s["mass"], s["pose"], DT, s["free"], backend="torch")
    assert x_n.shape == (2, 3, 60, 10, 3)
    assert rel(v_n.reshape(v_t.shape), v_t) <= F64_REL
    assert rel(x_n.reshape(x_t.shape), x_t) <= F64_REL


# -- edge cases ------------------------------------------------------------------------------
@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", DTYPES)
def test_no_cell_above_target_gives_exactly_zero_phi(native, device, dtype):
    """A groom at its rest shape (target = 1.1 × its peak density): φ is exactly 0 on both paths
    (the native kernels skip the sweeps), so the field is the PIC share alone."""
    ns = _namespace(device)
    s = squeeze_scene(dtype, device, squeeze=1.0, jitter=0.0, outside=False, seed=1)
    grid = s["grid"]
    h, r = grid.cell_size, grid.resolution
    faces = p2g_torch(s["xf"], s["vf"], s["m"], s["frame"], grid.origin, h, r)
    rho = cell_mass(face_views(faces[..., 0], r)) / h ** 3
    assert 0.5 * float(grid.target_density) < float(rho.max()) < float(grid.target_density)
    phi_t, field_t = pressure_torch(faces, grid.target_density, s["dt"], h, r, *_solve_args(grid))
    phi_n, field_n = ns.pressure(faces, grid.target_density, s["dt"], h, r, *_solve_args(grid))
    assert bool((phi_t == 0).all()) and bool((phi_n == 0).all())
    vel = torch.where(faces[..., 0] > 0, faces[..., 1] / faces[..., 0].clamp_min(1e-300), torch.zeros_like(faces[..., 0]))
    assert rel(field_n, 0.05 * vel) <= tol(dtype, r)
    assert rel(field_n, field_t) <= tol(dtype, r)


@pytest.mark.parametrize("device", DEVICES)
def test_empty_grid(native, device):
    """Every particle outside the grid: nothing on it, φ = 0, and (x, v) come back unchanged."""
    ns = _namespace(device)
    s = squeeze_scene(torch.float64, device, strands=30, outside=False)
    grid = s["grid"]
    xf = s["xf"] + 10.0 * grid.extent
    h, r = grid.cell_size, grid.resolution
    faces = ns.p2g(xf, s["vf"], s["m"], s["frame"], grid.origin, h, r)
    assert bool((faces == 0).all())
    phi, field = ns.pressure(faces, grid.target_density, s["dt"], h, r, *_solve_args(grid))
    assert bool((phi == 0).all()) and bool((field == 0).all())
    x1, v1 = ns.g2p(xf, s["vf"], field, s["frame"], grid.origin, s["free"], s["dt"], h, r, 0.05)
    assert torch.equal(x1, xf) and torch.equal(v1, s["vf"])
    for backend in ("torch", "native"):
        x2, v2 = hair_hair_stage(grid, xf.reshape(s["x"].shape), s["v"], s["mass"], s["pose"], DT, s["free"],
                                 backend=backend)
        assert torch.equal(x2, xf.reshape(s["x"].shape)) and torch.equal(v2, s["v"])


def test_native_p2g_is_deterministic_across_thread_counts(native):
    s = squeeze_scene(torch.float32, "cpu", strands=400, resolution=32, scenes=1)
    grid = s["grid"]
    args = (s["xf"], s["vf"], s["m"], s["frame"], grid.origin, grid.cell_size, grid.resolution)
    before = torch.get_num_threads()
    try:
        outs = []
        for threads in (1, 2, 1):
            torch.set_num_threads(threads)
            outs.append(native.p2g(*args))
    finally:
        torch.set_num_threads(before)
    assert torch.equal(outs[0], outs[1]) and torch.equal(outs[0], outs[2])


# -- registration ----------------------------------------------------------------------------
@pytest.mark.parametrize("device", DEVICES)
def test_opcheck(native, device):
    _namespace(device)
    for dtype in DTYPES:
        s = squeeze_scene(dtype, device, strands=20, resolution=8, scenes=2)
        grid = s["grid"]
        h, r = grid.cell_size, grid.resolution
        p2g_args = (s["xf"], s["vf"], s["m"], s["frame"], grid.origin, h, r, False)
        torch.library.opcheck(p2g_op, p2g_args)
        faces = p2g_op(*p2g_args)
        pr_args = (faces, grid.target_density, s["dt"], h, r, 4, 0.6, 1.0, 0.05, False)
        torch.library.opcheck(pressure_op, pr_args)
        _, field = pressure_op(*pr_args)
        torch.library.opcheck(g2p_op, (s["xf"], s["vf"], field, s["frame"], grid.origin, s["free"], s["dt"], h, r, 0.05,
                                       False))


class _Record(TorchDispatchMode):
    def __init__(self):
        super().__init__()
        self.ops = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.ops.append(str(func))
        return func(*args, **(kwargs or {}))


def test_backend_selection(native):
    s = squeeze_scene(torch.float64, "cpu", strands=20, resolution=8)
    call = lambda x, v, backend, grid=s["grid"]: hair_hair_stage(grid, x, v, s["mass"], s["pose"], DT,  # noqa: E731
                                                                 s["free"], backend=backend)
    ours = lambda rec: [o for o in rec.ops if "hair_hair" in o]  # noqa: E731
    with _Record() as rec:
        call(s["x"], s["v"], "auto")
    assert ours(rec) == ["ams_torch.hair_hair_p2g.default", "ams_torch.hair_hair_pressure.default",
                         "ams_torch.hair_hair_g2p.default"]
    v = s["v"].clone().requires_grad_(True)
    for backend in ("auto", "torch"):
        with _Record() as rec:
            out = call(s["x"], v, backend)
        assert ours(rec) == [] and out[1].requires_grad  # the differentiable torch definition
    with torch.no_grad(), _Record() as rec:
        call(s["x"], v, "auto")
    assert len(ours(rec)) == 3
    with pytest.raises(ValueError, match="no gradient"):
        call(s["x"], v, "native")
    with pytest.raises(ValueError, match="backend"):
        call(s["x"], s["v"], "fast")
    half = s["grid"].to(torch.bfloat16)
    with _Record() as rec:
        xb, vb = call(s["x"].bfloat16(), s["v"].bfloat16(), "auto", half)
    assert ours(rec) == [] and vb.dtype == torch.bfloat16
    with pytest.raises(ValueError, match="float32 or float64"):
        call(s["x"].bfloat16(), s["v"].bfloat16(), "native", half)


_FALLBACK_SCRIPT = textwrap.dedent(
    """
    import json, sys, warnings
    sys.path.insert(0, {tests!r})
    import torch
    from test_native_grid import squeeze_scene
    from ams_torch.stages.hair_hair import hair_hair_stage
    s = squeeze_scene(torch.float32, "cpu", strands=30, resolution=8)
    run = lambda b: hair_hair_stage(s["grid"], s["x"], s["v"], s["mass"], s["pose"], 1 / 60, s["free"], backend=b)
    with warnings.catch_warnings(record=True):
        warnings.simplefilter("always")
        same = all(torch.equal(a, b) for a, b in zip(run("auto"), run("torch")))
        try:
            run("native")
            error = None
        except RuntimeError as e:
            error = str(e)
    print(json.dumps(dict(same=same, error=error)))
    """
)


def test_disabled_native_falls_back_to_torch(tmp_path):
    """AMS_TORCH_NATIVE=0: 'auto' gives the torch path bit for bit; 'native' says why it cannot."""
    env = dict(os.environ, AMS_TORCH_NATIVE="0", AMS_TORCH_CACHE=str(tmp_path / "cache"), PYTHONPATH=str(REPO))
    script = _FALLBACK_SCRIPT.format(tests=str(REPO / "tests"))
    proc = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["same"]
    assert out["error"] and "AMS_TORCH_NATIVE" in out["error"]
    assert not (tmp_path / "cache").exists() or not any((tmp_path / "cache").iterdir())
