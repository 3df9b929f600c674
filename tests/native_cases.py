"""Inputs of the native parity tests, shared by several test modules (not a test module: pytest
does not collect it; test modules import it, never each other).

The frame (``make_scene``, ``case_scene`` over ``FRAME_CASES``, ``frame_args``, and the kernels
called directly: ``native_frame``, ``native_system``), the collision stage (``make_case`` over
``KINDS``), the hair–hair grid (``squeeze_scene``, ``tol``), the banded solve (``strand_system``,
also used by ``scripts/bench_solver.py`` and ``scripts/validate_cuda.py``) and the emulator's
self-test (``expected_warp_ops``).
"""
from __future__ import annotations

import pytest
import torch

import ams_torch
from ams_torch import testing
from ams_torch.apps.motion import Shake
from ams_torch.geometry.pose import Pose
from ams_torch.geometry.sdf import SDFGrid
from ams_torch.native import build as _native
from ams_torch.sim import native
from ams_torch.sim.model import coefficients
from ams_torch.stages.collide import CapsuleCollider, HollowSphereCollider, MeshCollider, PlaneCollider, SphereCollider
from ams_torch.stages.hair_hair import HairHair
from ams_torch.stages.hair_hair.transfer import scene_frame
from ams_torch.testing import head_groom

F64, F32 = torch.float64, torch.float32


# -- the frame -----------------------------------------------------------------------------------

def native_ns(device: str):
    """The native library of ``device`` ("cpu", "cuda"), built; skips without a CUDA toolkit."""
    kind = device
    ns = _native.native_ops(kind)
    if ns is None:
        reason = _native.native_status()[kind]["reason"]
        if device == "cuda" and reason.startswith("no CUDA toolkit"):
            pytest.skip(reason)
        raise AssertionError(f"native frame kernel ({kind}) failed to build: {reason}")
    return ns


def set_pinned(model, counts) -> None:
    """Pin the first counts[s] particles of strand s (an int for all strands), on the model itself
    (independent of how Params chooses the pinned root)."""
    model.set_pinned(counts)


def make_scene(dtype=F64, device="cpu", strands=13, particles=12, scenes=None, groom="sphere", seed=0,
               jitter=1e-3, frame=3, num_pinned=2, **params):
    """A simulator, a perturbed state at a shaken head pose and the next pose (with velocities).

    scenes: None for one scene (state (S, N, 3)), or B for B scenes with different head motions.
    jitter: m, random displacement of every particle (velocities get 100·jitter m/s), so springs
    are stretched and segments turned. num_pinned: pinned root particles (set on the model).
    Returns (sim, state, pose1).
    """
    rest = {"sphere": lambda: testing.sphere_groom(strands, particles, dtype=F64, seed=seed),
            "wisp": lambda: testing.wisp(strands, particles, seed=seed),
            "curly": lambda: testing.curly_strand(particles)}[groom]()
    if params.get("material", "per_length") == "per_length":  # exercise the bend and torsion springs (off by default)
        params = {"bend_rigidity": 3.2768e-11, "torsion_rigidity": 3.2768e-11, **params}
    sim = ams_torch.Simulator(rest, ams_torch.Params(**params), dtype=dtype, device=device)
    set_pinned(sim.model, num_pinned)
    dt = sim.config.dt

    def motion(b):
        return Shake(amplitude=0.6 + 0.3 * b, frequency=1.5 + 0.5 * b, axis=(0.2 * b, 1.0, 0.1), translation=(0.05, 0.03 * b, 0.02)).poses(frame + 1, dt, dtype=dtype, device=device)

    if scenes is None:
        pose0, pose1 = motion(0)[frame - 1:frame + 1]
    else:
        ms = [motion(b) for b in range(scenes)]
        pose0 = Pose.stack([m[frame - 1] for m in ms])
        pose1 = Pose.stack([m[frame] for m in ms])
    state = sim.initial_state(pose0)
    g = torch.Generator().manual_seed(seed + 1)
    noise = lambda scale: (scale * torch.randn(state.x.shape, generator=g, dtype=F64)).to(dtype=dtype,
                                                                                               device=device)
    state = state.replace(x=state.x + noise(jitter), v=state.v + noise(100 * jitter))
    return sim, state, pose1


def frame_args(sim, state, pose1, coeffs=None, config=None, hermite=True, external_force=None):
    """The arguments of frame_dynamics / native_frame_dynamics."""
    coeffs = coefficients(sim.model) if coeffs is None else coeffs
    config = sim.config if config is None else config
    return (sim.model, coeffs, config, state.x, state.v, state.ghost_rest, state.sag_offset, state.pose, pose1,
            hermite, state.time, external_force)


def native_system(ns, model, coeffs, config, x, v, ghost_rest, sag_offset, pose0, pose1, hermite, k,
                  external_force=None):
    args = native.op_arguments(model, coeffs, config, x, v, ghost_rest, sag_offset, pose0, pose1, hermite,
                               external_force)
    return ns.frame(*args, k)


def native_frame(ns, model, coeffs, config, x, v, ghost_rest, sag_offset, pose0, pose1, hermite, time,
                 external_force=None):
    """One frame by the native kernel itself (never the fallback)."""
    args = native.op_arguments(model, coeffs, config, x, v, ghost_rest, sag_offset, pose0, pose1, hermite,
                               external_force)
    return ns.frame(*args, -1)


FRAME_CASES = {
    # name: Params changes; "scale": factors applied to coefficient terms (independent of how the
    # material is parametrised)
    "default": {},
    "substeps3": {"substeps": 3},
    "nonhookean": {"integrity_model": "nonhookean", "integrity_transition": 0.2, "integrity_break": 0.5},
    "geometric": {"geometric_stiffness": True},
    "one_particle_angular": {"angular_reaction": False},
    "explicit_angular": {"implicit_angular": False},
    "no_inextensibility": {"inextensibility": False, "substeps": 2},
    "no_pins": {"num_pinned": 0},
    "one_pin": {"num_pinned": 1},
    "three_pins": {"num_pinned": 3},
    "zero_edge": {"scale": {"edge": 0.0}},
    "zero_bend_torsion": {"scale": {"bend": 0.0, "torsion": 0.0}},
    "zero_integrity": {"scale": {"integrity": 0.0}},
    "zero_angular": {"scale": {"angular": 0.0}},
    "zero_drag": {"scale": {"drag": 0.0}},
    "stiff": {"scale": {"edge": 30.0, "bend": 30.0, "torsion": 30.0}, "substeps": 2},
    "ftl_no_damping": {"ftl_damping": 0.0},
}


def case_scene(case: str, **kw):
    """make_scene for FRAME_CASES[case]; returns (sim, state, pose1, coeffs)."""
    params = dict(FRAME_CASES[case])
    scale = params.pop("scale", {})
    params.update(kw)
    sim, state, pose1 = make_scene(**params)
    c = coefficients(sim.model)
    return sim, state, pose1, c._replace(**{k: getattr(c, k) * v for k, v in scale.items()})


# -- the collision stage -------------------------------------------------------------------------

def ball_grid(center, radius, lower, upper, resolution=20):
    c = torch.tensor(center, dtype=F64)
    return SDFGrid.from_function(lambda p: (p - c).norm(dim=-1) - radius, lower, upper, resolution, dtype=F64)


def make_colliders(kind: str, rest: torch.Tensor) -> list:
    """Colliders placed across a sphere groom (roots on a 0.1 m ball, strands hanging 0.25 m);
    the capsule and the mesh ball go through particles of the rest shape ``rest`` (S, N, 3)."""
    s, n = rest.shape[:2]
    p1, p2, p3 = (rest[s // 4, n // 2], rest[(3 * s) // 4, n // 2], rest[s // 2, (2 * n) // 3])
    lower, upper = (p3 - 0.09).tolist(), (p3 + torch.tensor([0.12, 0.04, 0.12], dtype=F64)).tolist()
    shapes = {
        "sphere": lambda: SphereCollider((0.0, 0.0, 0.0), 0.106, friction=0.3, follow_head=True),
        "capsule": lambda: CapsuleCollider(p1.tolist(), p2.tolist(), 0.04, friction=0.8),
        "plane": lambda: PlaneCollider((0.0, -0.16, 0.0), (0.15, 1.0, 0.05), friction=0.5),
        "hollow": lambda: HollowSphereCollider((0.0, 0.02, 0.0), 0.2, 0.05, 0.1, friction=0.4),
        "hollow_closed": lambda: HollowSphereCollider((0.0, 0.0, 0.0), 0.16, 0.04, None, friction=0.2),
        # a ball SDF grid whose box covers only part of the hair (the outside-the-box correction too)
        "mesh": lambda: MeshCollider(ball_grid(p3.tolist(), 0.07, lower, upper), follow_head=True, friction=0.6,
                                     projection_iterations=3),
    }
    if kind == "all":
        return [shapes[k]() for k in ("sphere", "capsule", "plane", "hollow", "mesh")]
    return [shapes[kind]()]


def make_case(kind: str, dtype=F64, scenes=None, strands=15, particles=10, seed=0, rounds=1, **params):
    """A simulator with colliders, a state pushed into them and the head pose at the frame's end.
    Returns (sim, x, v, head_pose, collider_poses)."""
    rest = testing.sphere_groom(strands, particles, dtype=F64, seed=seed)
    sim = ams_torch.Simulator(rest, ams_torch.Params(collision_inextensibility=rounds, **params), dtype=dtype,
                              colliders=make_colliders(kind, rest))
    dt = sim.config.dt

    def motion(b):
        return Shake(amplitude=0.4 + 0.3 * b, translation=(0.03, 0.02 * b, 0.0)).poses(3, dt, dtype=dtype)[1]

    head = motion(0) if scenes is None else Pose.stack([motion(b) for b in range(scenes)])
    state = sim.initial_state(head)
    g = torch.Generator().manual_seed(seed + 1)
    noise = lambda scale: (scale * torch.randn(state.x.shape, generator=g, dtype=F64)).to(dtype)  # noqa: E731
    x = state.x + noise(8e-3)
    v = state.v + noise(0.4)
    return sim, x, v, head, ()


KINDS = ["sphere", "capsule", "plane", "hollow", "hollow_closed", "mesh", "all"]


def without_hollow(args) -> list:
    """The collision op's arguments (``native.collision_arguments``) without their hollow spheres
    (kernel type 3: no native adjoint)."""
    args = list(args)
    keep = [c for c in range(len(args[6]) // 3) if args[6][3 * c] != 3]
    args[4] = [t for c in keep for t in args[4][4 * c:4 * c + 4]]
    args[5] = [t for c in keep for t in args[5][4 * c:4 * c + 4]]
    args[6] = [i for c in keep for i in args[6][3 * c:3 * c + 3]]
    args[7] = [f for c in keep for f in args[7][3 * c:3 * c + 3]]
    return args


def sweeps_case(slots: int, seed: int, dtype=F64) -> tuple:
    """Inputs of the pressure sweeps (``sparse._sweeps``, ops ``sweeps`` / ``sweeps_adjoint``): src,
    coef (L + 1,), w (6, L + 1), nbr (6 (L + 1),) int64 random list slots, the last slot a zero
    (src = coef = w = 0, its own neighbour), and an output adjoint g (L + 1,) zero on that slot."""
    g = torch.Generator().manual_seed(seed)
    src = (torch.rand(slots, generator=g, dtype=F64) - 0.3).to(dtype)
    coef = torch.rand(slots, generator=g, dtype=F64).to(dtype)
    w = (0.2 * torch.rand(6, slots, generator=g, dtype=F64)).to(dtype)
    nbr = torch.randint(0, slots, (6, slots), generator=g)
    nbr[:, -1] = slots - 1
    src[-1] = coef[-1] = 0
    w[:, -1] = 0
    gout = torch.randn(slots, generator=g, dtype=F64).to(dtype)
    gout[-1] = 0
    return src, coef, w, nbr.reshape(-1), gout


# -- the hair–hair grid ----------------------------------------------------------------------------

MASS = 1e-6


DT = 1.0 / 60.0


F64_REL = 1e-10


def f32_rel(r: int) -> float:
    return 8 * r * torch.finfo(torch.float32).eps


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


def solve_args(grid):
    cfg = grid.config
    return cfg.pressure_iterations, cfg.jacobi_omega, cfg.volume_stiffness, 1.0 - cfg.flip


def compare_grid_adjoints(ns_ref, ns_other, dtype, device: str = "cpu", strands=60, particles=8, resolution=12,
                          scenes=3, bound: float = 0.0) -> None:
    """The grid's adjoint kernels (p2g_adjoint, pressure_adjoint, g2p_adjoint) of ``ns_other`` (its
    tensors on ``device``) against ``ns_ref``'s (CPU) on one pool (the reference's P2G table), a
    pressure-active squeeze scene: every output within ``bound`` of the reference's largest value
    (on the used slots). Asserts."""
    from ams_torch.stages.hair_hair.transfer import to_head

    s = squeeze_scene(dtype, strands=strands, particles=particles, resolution=resolution, scenes=scenes)
    grid = s["grid"]
    h, r, k = grid.cell_size, grid.resolution, grid.capacity
    on = lambda *ts: [t.to(device) for t in ts]  # noqa: E731
    xl, vl = (t.contiguous() for t in to_head(s["frame"], s["xf"], s["vf"]))
    ident = torch.zeros_like(s["frame"])
    ident[:, :3] = torch.eye(3, dtype=dtype)
    faces, table, blocks, count = ns_ref.p2g(xl, vl, s["m"], ident, grid.origin, h, r, k)
    solve = (grid.target_density, s["dt"], h, r, *solve_args(grid))
    phi, field, _ = ns_ref.pressure(faces, table, blocks, count, *solve, grid.active_capacity)
    assert float(phi[blocks >= 0].max()) > 0  # the squeeze pushes
    gen = torch.Generator().manual_seed(7)
    used = (blocks >= 0)[..., None, None]

    def close(c, d, what):
        d = d.cpu()
        if c.dim() >= 4:
            c, d = torch.where(used, c, 0), torch.where(used, d, 0)
        assert float(c.abs().max()) > 0, what
        assert float((c - d).abs().max()) <= bound * float(c.abs().max()), (what, float((c - d).abs().max()))

    g_faces = torch.randn(faces.shape, generator=gen, dtype=dtype)
    for name, c, d in zip(("xl", "vl", "m"), ns_ref.p2g_adjoint(xl, vl, s["m"], grid.origin, table, g_faces, h, r),
                          ns_other.p2g_adjoint(*on(xl, vl, s["m"], grid.origin, table, g_faces), h, r)):
        close(c, d, "p2g " + name)
    g_field = torch.randn(field.shape, generator=gen, dtype=dtype)
    c = ns_ref.pressure_adjoint(faces, table, blocks, count, *solve, g_field)
    d = ns_other.pressure_adjoint(*on(faces, table, blocks, count, *solve[:2]), *solve[2:], g_field.to(device))
    close(c.flatten(-2), d.flatten(-2), "pressure")
    g_dv = torch.randn(xl.shape, generator=gen, dtype=dtype)
    for name, c, d in zip(("xl", "vl", "field", "dv"),
                          ns_ref.g2p_adjoint(xl, vl, field, table, grid.origin, g_dv, h, r, 0.05),
                          ns_other.g2p_adjoint(*on(xl, vl, field, table, grid.origin, g_dv), h, r, 0.05)):
        close(c, d, "g2p " + name)


def tol(dtype, r):
    return F64_REL if dtype == torch.float64 else f32_rel(r)


# -- the banded solve ------------------------------------------------------------------------------

H = 1.0 / 60.0  # time step of the assembled systems, s


def strand_system(strands: int, n: int, *, mass: float = 1.0, stiffness=(1e3, 3e2, 1e2), dt: float = H,
                  dtype=torch.float64, device="cpu", seed: int = 0, junk: bool = False):
    """Implicit-step matrices of random strands, assembled as the simulator does (SPEC §4).

    Particles follow a random walk (1 cm segments). Springs join i and i−k (k = 1, 2, 3) with
    stiffness ``stiffness[k-1]`` (N/m, ±50 % per spring) along their chord d: D = d dᵀ. Then
        A[i, i]   = m I + dt² Σ_springs∋i κ D,      A[i, i−k] = −dt² κ D_{i,i−k},
    symmetric positive definite (m > 0). With κ = 1e8 and m = 1e-6 its condition number is
    near 1e11.

    Returns blocks: (strands, n, 4, 3, 3) and rhs: (strands, n, 3) (kg·m/s scale ~ m).
    ``junk=True`` fills the entries the solver must never read (strict upper triangle of the
    diagonal blocks, blocks[i, k] for k > i) with NaN.
    """
    g = torch.Generator().manual_seed(seed)
    f64 = torch.float64
    steps = torch.randn(strands, n, 3, generator=g, dtype=f64)
    steps = 0.01 * steps / steps.norm(dim=-1, keepdim=True)
    pos = steps.cumsum(dim=1)
    blocks = torch.zeros(strands, n, 4, 3, 3, dtype=f64)
    blocks[:, :, 0] = mass * torch.eye(3, dtype=f64)
    for k in range(1, 4):
        if k >= n:
            break
        d = pos[:, k:] - pos[:, :-k]
        d = d / d.norm(dim=-1, keepdim=True)
        kappa = stiffness[k - 1] * (0.5 + torch.rand(strands, n - k, 1, 1, generator=g, dtype=f64))
        c = dt * dt * kappa * d.unsqueeze(-1) * d.unsqueeze(-2)
        blocks[:, k:, k] = -c
        blocks[:, k:, 0] += c
        blocks[:, :-k, 0] += c
    rhs = mass * torch.randn(strands, n, 3, generator=g, dtype=f64)
    if junk:
        blocks = blocks.clone()
        iu = torch.triu_indices(3, 3, 1)
        blocks[:, :, 0, iu[0], iu[1]] = float("nan")
        for k in range(1, 4):
            blocks[:, : min(k, n), k] = float("nan")
    return blocks.to(device=device, dtype=dtype), rhs.to(device=device, dtype=dtype)


# -- the emulator's self-test ----------------------------------------------------------------------

def expected_warp_ops(threads: int) -> torch.Tensor:
    """What selftest_cuda.cu's warp_ops kernel must write (CUDA semantics), per thread."""
    rows = []
    for t in range(threads):
        lane, base = t % 32, t - t % 32
        count = min(32, threads - base)
        full = (1 << count) - 1
        val = lambda src: 10 * src if src < count else 10 * lane  # noqa: E731  (absent source: own value)
        up = lane - 2 if lane - 2 >= (lane - lane % 16) else lane
        rows.append([
            lane, full, (full & ((1 << 20) - 1)) if lane < 20 else -1,
            sum(1 << k for k in range(count) if k % 3 == 0), val((lane + 1) % 32),
            val(lane + 3) if lane + 3 < 32 else 10 * lane, val(lane ^ 5), val(up),
            sum(1 << k for k in range(count) if k // 4 == lane // 4), 1 if count > 7 else 0, 1,
            sum(1 << k for k in range(count) if k % 2 == 0 and k // 8 == lane // 8) if lane % 2 == 0 else -1,
            100 + (lane + 1) % 32 if (lane + 1) % 32 < count else -1, threads * (threads - 1) // 2,
        ])
    return torch.tensor(rows, dtype=torch.int64)
