"""Fused native frame of strand dynamics (SPEC §15): torch definition vs native CPU (vs CUDA).

The torch definition is ``ams_torch.sim.dynamics.frame_dynamics`` with ``assembly.assemble_system``;
the native kernel (``ams_torch/native/csrc/frame``) is built once per session (``native`` fixture,
cached across runs). Tolerances:

* assembly, term by term, float64: the native contribution of each term agrees with the torch one to
  1e-12 relative (measured: ~1e-16; the arithmetic and its order are the same, up to the order of
  sums inside torch's matmul/einsum kernels, fused multiply-adds and atan2 to an ulp);
* one frame, float64: 1e-10 relative (measured ~1e-14: the solve and follow-the-leader amplify
  rounding by the condition number of the step, ~1e3 for the default material);
* one frame, float32: the native result is no farther from the float64 frame than twice the torch
  float32 result is (plus 8 ulps): both are rounding errors of the same computation amplified by
  the same conditioning (measured: native ≈ torch ≈ 1e-6 in x, 1e-5 in v; 2e-4 in v for a stiff
  groom with cond ~ 1e4).
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
from helpers import DEVICES, rel
from native_cases import (F32, F64, FRAME_CASES, case_scene, frame_args, make_scene, native_frame, native_ns,
                          native_system, set_pinned)

from ams_torch.apps.motion import Shake
import ams_torch
from ams_torch import testing
from ams_torch.geometry.pose import Pose
from ams_torch.sim import native
from ams_torch.sim.op_support import pose_tensors
from ams_torch.sim.dynamics import frame_dynamics, substep_system
from ams_torch.sim.model import coefficients
from ams_torch.sim.stepping import resolve_pose
from ams_torch.native import build as _native

REPO = Path(__file__).resolve().parents[1]
EPS32 = torch.finfo(F32).eps


# ---------------------------------------------------------------------------------------
# fixtures and input factories
# ---------------------------------------------------------------------------------------


def torch_system(model, coeffs, config, x, v, ghost_rest, sag_offset, pose0, pose1, hermite, k,
                 external_force=None):
    """Substep k's system as frame_dynamics assembles it (the definition), at the state (x, v)."""
    return substep_system(model, coeffs, config, x, v, ghost_rest, sag_offset, pose0, pose1, hermite, k,
                          external_force)


# ---------------------------------------------------------------------------------------
# term by term: one substep's assembled system
# ---------------------------------------------------------------------------------------

def _isolate(coeffs, keep, g):
    """Coefficients with every spring/coupling term zeroed except those in ``keep``, the kept ones
    random per element (0.5–1.5 × their value), so each entry is exercised."""
    out = {}
    for name in ("edge", "bend", "torsion", "integrity", "angular", "drag"):
        c = getattr(coeffs, name)
        if name in keep:
            out[name] = c * (0.5 + torch.rand(c.shape, generator=g, dtype=F64)).to(c.dtype)
        else:
            out[name] = torch.zeros_like(c)
    return coeffs._replace(**out)


TERMS = {
    # name: (coefficients kept, Params/Config changes)
    "mass": ((), {}),
    "drag": (("drag",), {}),
    "gravity": ((), {"gravity": (0.3, -9.81, 0.2)}),
    "edge": (("edge",), {}),
    "bend": (("bend",), {}),
    "torsion": (("torsion",), {}),
    "springs_geometric": (("edge", "bend", "torsion"), {"geometric_stiffness": True}),
    "integrity_hookean": (("integrity",), {}),
    "integrity_nonhookean": (("integrity",), {"integrity_model": "nonhookean"}),
    "angular_couple_implicit": (("angular",), {}),
    "angular_couple_explicit": (("angular",), {"implicit_angular": False}),
    "angular_one_particle_implicit": (("angular",), {"angular_reaction": False}),
    "angular_one_particle_explicit": (("angular",), {"angular_reaction": False, "implicit_angular": False}),
    "external_force": ((), {"external": True}),
    "all": (("edge", "bend", "torsion", "integrity", "angular", "drag"),
            {"geometric_stiffness": True, "gravity": (0.3, -9.81, 0.2), "external": True}),
    "all_nonhookean_one_particle": (("edge", "bend", "torsion", "integrity", "angular", "drag"),
                                    {"integrity_model": "nonhookean", "angular_reaction": False, "external": True}),
}
CONFIG_FIELDS = ("geometric_stiffness", "integrity_model", "implicit_angular", "angular_reaction")


def _term_case(term: str, dtype=F64, num_pinned=2, substeps=2):
    keep, changes = TERMS[term]
    changes = dict(changes)
    external = changes.pop("external", False)
    gravity = changes.pop("gravity", (0.0, 0.0, 0.0))
    # soft ghosts far from their particles: the non-Hookean law sees all three branches
    sim, state, pose1 = make_scene(dtype=dtype, jitter=3e-3, gravity=gravity, num_pinned=num_pinned,
                                   substeps=substeps, integrity_model=changes.get("integrity_model", "hookean"))
    g = torch.Generator().manual_seed(7)
    coeffs = _isolate(coefficients(sim.model), keep, g)
    config = replace(sim.config, integrity_model="none" if "integrity" not in keep else
                     changes.get("integrity_model", "hookean"), angular="angular" in keep,
                     **{k: v for k, v in changes.items() if k in CONFIG_FIELDS and k != "integrity_model"})
    ext = (1e-5 * torch.randn(state.x.shape, generator=g, dtype=F64)).to(dtype) if external else None
    if config.nonhookean:  # transition and breaking points inside the elongations present: every branch
        anchor = state.pose.to_world(state.ghost_rest) - state.pose.rotate(state.sag_offset)
        e = ((anchor - state.x).norm(dim=-1) / sim.model.segment_length).flatten().double()
        t, b = torch.quantile(e, 0.3), torch.quantile(e, 0.7)
        coeffs = coeffs._replace(transition=t.to(dtype), breaking=b.to(dtype))
    return sim, state, pose1, coeffs, config, ext


@pytest.mark.parametrize("term", list(TERMS))
def test_assembly_term_by_term(cpu_ops, term):
    """Each term alone (and all together): native blocks and rhs of a substep equal the torch
    definition's to 1e-12 relative, measured on the term's own contribution."""
    sim, state, pose1, coeffs, config, ext = _term_case(term)
    base_coeffs = _isolate(coefficients(sim.model), (), torch.Generator().manual_seed(7))
    base_config = replace(config, integrity_model="none", angular=False)
    m = sim.model  # the baseline: no term, no gravity, no external force
    base_model = SimpleNamespace(rest_positions=m.rest_positions, rest_lengths=m.rest_lengths,
                                 edge_rest_length=m.edge_rest_length, segment_length=m.segment_length,
                                 pinned=m.pinned, has_pinned=m.has_pinned, gravity=torch.zeros_like(m.gravity))
    args = (sim.model, coeffs, config, state.x, state.v, state.ghost_rest, state.sag_offset, state.pose, pose1, True)
    for k in (0, 1):  # the first substep (start pose) and the last (end pose exactly)
        ref_b, ref_r = torch_system(*args, k, ext)
        nat_b, nat_r = native_system(cpu_ops, *args, k, ext)
        base_b, base_r = torch_system(base_model, base_coeffs, base_config, *args[3:], k, None)
        assert nat_b.shape == ref_b.shape and nat_r.shape == ref_r.shape
        for what, nat, ref, base in (("blocks", nat_b, ref_b, base_b), ("rhs", nat_r, ref_r, base_r)):
            assert rel(nat, ref) <= 1e-12, f"{term} substep {k} {what}: {rel(nat, ref):.3g}"
            own = (ref - base).norm().item()
            if own > 0:  # the term's own contribution, not drowned by the mass
                err = (nat - ref).norm().item() / own
                assert err <= 1e-12, f"{term} substep {k} {what}: {err:.3g} of the term's contribution"
    if term != "mass":
        assert (ref_b - base_b).abs().max() > 0 or (ref_r - base_r).abs().max() > 0, "term had no effect"


def test_nonhookean_case_covers_every_branch(cpu_ops):
    """The non-Hookean term-by-term state has particles in the Hookean, soft and yield ranges."""
    sim, state, _, coeffs, _, _ = _term_case("integrity_nonhookean")
    anchor = state.pose.to_world(state.ghost_rest) - state.pose.rotate(state.sag_offset)
    e = (anchor - state.x).norm(dim=-1) / sim.model.segment_length
    t, b = float(coeffs.transition), float(coeffs.breaking)
    assert (e < t).any() and ((e > t) & (e < b)).any() and (e > b).any()


@pytest.mark.parametrize("num_pinned", [0, 1, 2, 3])
def test_assembly_pinned_rows(cpu_ops, num_pinned):
    sim, state, pose1, coeffs, config, ext = _term_case("all", num_pinned=num_pinned)
    args = (sim.model, coeffs, config, state.x, state.v, state.ghost_rest, state.sag_offset, state.pose, pose1, True)
    ref_b, ref_r = torch_system(*args, 0, ext)
    nat_b, nat_r = native_system(cpu_ops, *args, 0, ext)
    assert rel(nat_b, ref_b) <= 1e-12 and rel(nat_r, ref_r) <= 1e-12


# ---------------------------------------------------------------------------------------
# one frame
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("case", list(FRAME_CASES))
def test_frame_float64(cpu_ops, case):
    sim, state, pose1, coeffs = case_scene(case, jitter=2e-3)
    args = frame_args(sim, state, pose1, coeffs)
    x_ref, v_ref = frame_dynamics(*args)
    x_nat, v_nat = native_frame(cpu_ops, *args)
    assert rel(x_nat, x_ref) <= 1e-10 and rel(v_nat, v_ref) <= 1e-10, (rel(x_nat, x_ref), rel(v_nat, v_ref))


@pytest.mark.parametrize("hermite", [True, False])
@pytest.mark.parametrize("scenes", [None, 3])
def test_frame_scenes_and_hermite(cpu_ops, hermite, scenes):
    """B > 1 scenes with different head motions, each pose per scene; Hermite on and off."""
    sim, state, pose1 = make_scene(scenes=scenes, substeps=3, jitter=2e-3)
    args = frame_args(sim, state, pose1, hermite=hermite)
    x_ref, v_ref = frame_dynamics(*args)
    x_nat, v_nat = native_frame(cpu_ops, *args)
    assert x_nat.shape == state.x.shape
    assert rel(x_nat, x_ref) <= 1e-10 and rel(v_nat, v_ref) <= 1e-10
    if scenes:  # every scene right on its own (a wrong pose index would be a scene's whole motion)
        for b in range(scenes):
            assert rel(x_nat[b], x_ref[b]) <= 1e-10


def test_frame_scenes_with_one_start_pose(cpu_ops):
    """B scenes from one shared start pose (pose batch ()) to per-scene end poses."""
    sim, state, pose1 = make_scene(scenes=2, substeps=2)
    shared = Pose(state.pose.rotation[0], state.pose.translation[0], state.pose.linear_velocity[0],
                  state.pose.angular_velocity[0], check=False)
    state = state.replace(pose=shared)
    args = frame_args(sim, state, pose1)
    x_ref, v_ref = frame_dynamics(*args)
    x_nat, v_nat = native_frame(cpu_ops, *args)
    assert rel(x_nat, x_ref) <= 1e-10 and rel(v_nat, v_ref) <= 1e-10


@pytest.mark.parametrize("groom,strands,particles", [("wisp", 9, 4), ("curly", 1, 30), ("sphere", 17, 5)])
def test_frame_small_strands(cpu_ops, groom, strands, particles):
    """4-particle strands (the minimum), one lone strand, and a strand count that is not a
    multiple of the SIMD width (the padded group)."""
    sim, state, pose1 = make_scene(groom=groom, strands=strands, particles=particles, substeps=2)
    args = frame_args(sim, state, pose1)
    x_ref, v_ref = frame_dynamics(*args)
    x_nat, v_nat = native_frame(cpu_ops, *args)
    assert rel(x_nat, x_ref) <= 1e-10 and rel(v_nat, v_ref) <= 1e-10


def test_frame_per_strand_pinned_counts(cpu_ops):
    """num_pinned differs between strands (and so between SIMD lanes of one group)."""
    sim, state, pose1 = make_scene(strands=11, particles=9, substeps=2)
    counts = torch.tensor([0, 1, 2, 3, 2, 1, 0, 3, 2, 2, 1], dtype=torch.int64)
    set_pinned(sim.model, counts)
    args = frame_args(sim, state, pose1)
    x_ref, v_ref = frame_dynamics(*args)
    x_nat, v_nat = native_frame(cpu_ops, *args)
    assert rel(x_nat, x_ref) <= 1e-10 and rel(v_nat, v_ref) <= 1e-10
    # pinned particles land exactly on their targets, the free ones do not
    target = pose1.to_world(sim.model.rest_positions)
    for s, p in enumerate(counts.tolist()):
        if p:
            torch.testing.assert_close(x_nat[s, :p], target[s, :p], rtol=0, atol=1e-15)


def test_frame_nonhookean_yielding(cpu_ops):
    """Particles pulled beyond the breaking point (the yield branch and its slope ρ): half of them."""
    sim, state, pose1 = make_scene(jitter=6e-3, integrity_model="nonhookean", substeps=2)
    anchor = state.pose.to_world(state.ghost_rest) - state.pose.rotate(state.sag_offset)
    e = ((anchor - state.x).norm(dim=-1) / sim.model.segment_length).flatten()
    c = coefficients(sim.model)
    coeffs = c._replace(transition=torch.quantile(e, 0.2).to(c.transition.dtype),
                        breaking=torch.quantile(e, 0.5).to(c.breaking.dtype))
    args = frame_args(sim, state, pose1, coeffs)
    x_ref, v_ref = frame_dynamics(*args)
    x_nat, v_nat = native_frame(cpu_ops, *args)
    assert rel(x_nat, x_ref) <= 1e-10 and rel(v_nat, v_ref) <= 1e-10


@pytest.mark.parametrize("shape", ["full", "broadcast"])
def test_frame_external_force(cpu_ops, shape):
    sim, state, pose1 = make_scene(scenes=2, substeps=2)
    g = torch.Generator().manual_seed(3)
    force = 2e-5 * torch.randn(state.x.shape if shape == "full" else state.x.shape[1:], generator=g, dtype=F64)
    args = frame_args(sim, state, pose1, external_force=force)
    x_ref, v_ref = frame_dynamics(*args)
    x_nat, v_nat = native_frame_dynamics_checked(cpu_ops, args)
    assert rel(x_nat, x_ref) <= 1e-10 and rel(v_nat, v_ref) <= 1e-10
    x_free, _ = frame_dynamics(*args[:-1], None)
    assert rel(x_nat, x_free) > 1e-8  # the force did something


def native_frame_dynamics_checked(ns, args):
    """native_frame_dynamics, asserting that it ran the native kernel (equal to calling it directly)."""
    out = native.native_frame_dynamics(*args)
    direct = native_frame(ns, *args)
    assert torch.equal(out[0], direct[0]) and torch.equal(out[1], direct[1])
    return out


@pytest.mark.parametrize("case", ["default", "nonhookean", "stiff"])
def test_frame_float32(cpu_ops, case):
    """float32: no farther from the float64 frame than twice the torch float32 frame (module doc)."""
    out = {}
    for dtype in (F32, F64):
        sim, state, pose1, coeffs = case_scene(case, dtype=dtype, strands=21, particles=16)
        args = frame_args(sim, state, pose1, coeffs)
        out[dtype] = frame_dynamics(*args), native_frame(cpu_ops, *args)
    (x64, v64), _ = out[F64]
    (x_t, v_t), (x_n, v_n) = out[F32]
    assert x_n.dtype == F32
    for nat, tor, ref, name in ((x_n, x_t, x64, "x"), (v_n, v_t, v64, "v")):
        bound = 2 * rel(tor, ref) + 8 * EPS32
        assert rel(nat, ref) <= bound, f"{case} {name}: native {rel(nat, ref):.3g}, torch {rel(tor, ref):.3g}"


def test_sixty_frames_of_a_shaken_groom(cpu_ops):
    """60 frames of a shaken groom, float64, each path fed its own output: the native trajectory
    stays on the torch one (report: the max difference, in metres)."""
    rest = testing.sphere_groom(24, 16, dtype=F64)
    sim = ams_torch.Simulator(rest, ams_torch.Params(substeps=2), dtype=F64)
    poses = Shake(amplitude=0.8, frequency=2.0, translation=(0.05, 0.03, 0)).poses(61, sim.config.dt, dtype=F64)
    state = sim.initial_state(poses[0])
    coeffs = coefficients(sim.model)
    xs = {"torch": (state.x, state.v), "native": (state.x, state.v)}
    worst = 0.0
    for f in range(60):
        p0, p1 = poses[f], poses[f + 1]
        for name in xs:
            x, v = xs[name]
            a = (sim.model, coeffs, sim.config, x, v, state.ghost_rest, state.sag_offset, p0, p1, True, state.time)
            xs[name] = frame_dynamics(*a) if name == "torch" else native_frame(cpu_ops, *a)
        worst = max(worst, (xs["native"][0] - xs["torch"][0]).abs().max().item())
    moved = (xs["torch"][0] - state.x).abs().max().item()
    print(f"60 frames: max |x_native - x_torch| = {worst:.3g} m (motion {moved:.3g} m)")
    assert moved > 1e-2
    assert worst <= 1e-10


def test_poses_without_velocities_through_the_simulator(cpu_ops):
    """A control pose without velocities: the simulator's pose resolution gives the end pose its
    velocities and linear interpolation (hermite False); native equals torch from there. Passing
    the pose without velocities and hermite=True is the same (Pose.interpolate's own rule)."""
    sim, state, pose1 = make_scene(substeps=3)
    bare = Pose(pose1.rotation, pose1.translation)
    resolved, hermite = resolve_pose(state.pose, bare, sim.config.dt)
    assert not hermite
    args = frame_args(sim, state, resolved, hermite=hermite)
    x_ref, v_ref = frame_dynamics(*args)
    x_nat, v_nat = native_frame_dynamics_checked(cpu_ops, args)
    assert rel(x_nat, x_ref) <= 1e-10 and rel(v_nat, v_ref) <= 1e-10
    args = frame_args(sim, state, bare, hermite=True)
    x_ref2, _ = frame_dynamics(*args)
    x_nat2, _ = native_frame_dynamics_checked(cpu_ops, args)
    assert torch.equal(x_ref2, x_ref) and rel(x_nat2, x_ref) <= 1e-10
    # and a whole simulator step from there uses that resolution
    new = sim.step(state, bare)
    assert torch.isfinite(new.x).all()


def test_batched_equals_one_at_a_time(cpu_ops):
    """Every SIMD lane computes the same bits as a lone strand."""
    sim, state, pose1 = make_scene(strands=11, particles=8, substeps=2)
    args = frame_args(sim, state, pose1)
    x_all, v_all = native_frame(cpu_ops, *args)
    for s in (0, 5, 10):
        one = ams_torch.Simulator(sim.model.rest_positions[s:s + 1], sim.params, dtype=F64)
        set_pinned(one.model, 2)
        st = state.replace(x=state.x[s:s + 1], v=state.v[s:s + 1], ghost_rest=state.ghost_rest[s:s + 1],
                           sag_offset=state.sag_offset[s:s + 1])
        x1, v1 = native_frame(cpu_ops, *frame_args(one, st, pose1))
        assert torch.equal(x1[0], x_all[s]) and torch.equal(v1[0], v_all[s]), s


def test_thread_count_does_not_change_results(cpu_ops):
    sim, state, pose1 = make_scene(strands=40, particles=8, scenes=2)
    args = frame_args(sim, state, pose1)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = native_frame(cpu_ops, *args)
        torch.set_num_threads(2)
        two = native_frame(cpu_ops, *args)
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(one[0], two[0]) and torch.equal(one[1], two[1])


# ---------------------------------------------------------------------------------------
# dispatch: the entry point, fallbacks, the registered ops
# ---------------------------------------------------------------------------------------

def test_entry_point_dispatch(cpu_ops):
    sim, state, pose1 = make_scene(substeps=2)
    args = frame_args(sim, state, pose1)
    assert native.native_frame_available("cpu", F64) and native.native_frame_available("cpu", F32)
    assert not native.native_frame_available("cpu", torch.float16)
    assert native.native_frame_supported(*args[:2], *args[3:9], None)
    native_frame_dynamics_checked(cpu_ops, args)
    # a callable external force: the torch path, exactly
    force = lambda x, v, t: 1e-5 * torch.ones_like(x)
    cargs = args[:-1] + (force,)
    assert not native.native_frame_supported(*args[:2], *args[3:9], force)
    x_c, v_c = native.native_frame_dynamics(*cargs)
    x_t, v_t = frame_dynamics(*cargs)
    assert torch.equal(x_c, x_t) and torch.equal(v_c, v_t)


def test_gradients_stay_on_the_torch_definition(cpu_ops):
    sim, state, pose1 = make_scene(substeps=1, strands=5, particles=6)
    v = state.v.clone().requires_grad_()
    args = frame_args(sim, state.replace(v=v), pose1)
    assert not native.native_frame_supported(*args[:2], *args[3:9], None)
    x, _ = native.native_frame_dynamics(*args)
    x.sum().backward()
    assert v.grad is not None and torch.isfinite(v.grad).all()
    with torch.no_grad():
        assert native.native_frame_supported(*args[:2], *args[3:9], None)


def test_op_default_is_the_torch_definition():
    """The op's default implementation (what every device without a kernel runs) is frame_dynamics."""
    sim, state, pose1 = make_scene(scenes=2, substeps=2, integrity_model="nonhookean")
    args = frame_args(sim, state, pose1)
    op_args = native.op_arguments(*args[:10], None)
    x_d, v_d = native._frame_torch(*op_args)
    x_t, v_t = frame_dynamics(*args)
    assert rel(x_d, x_t) <= 1e-15 and rel(v_d, v_t) <= 1e-15
    b_d, r_d = native._assembly_torch(*op_args, 1)
    b_t, r_t = torch_system(*args[:10], 1)
    assert torch.equal(b_d, b_t) and torch.equal(r_d, r_t)


@pytest.mark.parametrize("device", DEVICES)
def test_opcheck(cpu_ops, device):
    native_ns(device)
    for dtype, kw in ((F64, {"integrity_model": "nonhookean"}), (F32, {"angular_reaction": False})):
        sim, state, pose1 = make_scene(dtype=dtype, device=device, strands=5, particles=6, scenes=2, substeps=2, **kw)
        g = torch.Generator().manual_seed(5)
        force = (1e-5 * torch.randn(state.x.shape, generator=g, dtype=F64)).to(dtype=dtype, device=device)
        op_args = native.op_arguments(*frame_args(sim, state, pose1)[:10], force)
        torch.library.opcheck(torch.ops.ams_torch.frame_dynamics.default, op_args + ([],))
        (_, t, lin, ang), _ = pose_tensors(pose1, state.x)  # the frame's end fused in
        torch.library.opcheck(torch.ops.ams_torch.frame_dynamics.default, op_args + ([t, lin, ang],))
        op_args = native.op_arguments(*frame_args(sim, state, pose1)[:10], None)
        torch.library.opcheck(torch.ops.ams_torch.frame_assembly.default, op_args + (1,))


def test_torch_compile_fullgraph(cpu_ops):
    sim, state, pose1 = make_scene(dtype=F32, strands=9, particles=8, substeps=2)
    coeffs = coefficients(sim.model)

    def frame(x, v):
        x1, v1 = native.native_frame_dynamics(sim.model, coeffs, sim.config, x, v, state.ghost_rest,
                                              state.sag_offset, state.pose, pose1, True, state.time)
        return x1 + 0.0, 2.0 * v1

    torch._dynamo.reset()
    compiled = torch.compile(frame, fullgraph=True, dynamic=False)
    with torch.no_grad():
        got = compiled(state.x, state.v)
        want = frame(state.x, state.v)
    assert torch.equal(got[0], want[0]) and torch.equal(got[1], want[1])


def test_op_counts(cpu_ops):
    """One frame of the entry point is one registered op (plus the two outputs it allocates),
    independent of the number of strands."""
    from torch.profiler import ProfilerActivity, profile

    counts = []
    for strands in (7, 70):
        sim, state, pose1 = make_scene(strands=strands, particles=8, substeps=2)
        args = frame_args(sim, state, pose1)
        with torch.no_grad():
            native.native_frame_dynamics(*args)
            with profile(activities=[ProfilerActivity.CPU]) as prof:
                native.native_frame_dynamics(*args)
        events = [e for e in prof.events() if e.name.startswith(("aten::", "ams_torch"))]
        top = [e for e in events if e.cpu_parent is None]
        counts.append((len(top), len(events)))
    assert counts[0] == counts[1]
    assert counts[0][0] <= 2 and counts[0][1] <= 10, counts


_FALLBACK_SCRIPT = textwrap.dedent(
    """
    import json, os, sys, warnings
    sys.path.insert(0, {tests!r})
    os.environ["AMS_TORCH_NATIVE"] = "0"
    import torch
    from native_cases import make_scene, frame_args, make_case
    from ams_torch.sim import native
    from ams_torch.sim.dynamics import frame_dynamics
    from ams_torch.sim.stepping import collisions
    from ams_torch.native import build
    from ams_torch.stages.collide import resolve_world_poses
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sim, state, pose1 = make_scene(scenes=2, substeps=2)
        args = frame_args(sim, state, pose1)
        with torch.no_grad():
            x_n, v_n = native.native_frame_dynamics(*args)
            x_t, v_t = frame_dynamics(*args)
            csim, x, v, head, _ = make_case("all", scenes=2)
            world = resolve_world_poses(csim.colliders, head, None)
            got = native.native_collisions(csim.model, csim.config, x, v, head, world)
            want = collisions(csim.model, csim.config, x, v, head, ())
    rel = max(((x_n - x_t).norm() / x_t.norm()).item(), ((v_n - v_t).norm() / v_t.norm()).item())
    ours = [w for w in caught if issubclass(w.category, build.NativeBuildWarning)]
    st = build.native_status()
    print(json.dumps(dict(rel=rel, warnings=len(ours), built=st["cpu"]["built"],
                          reason=st["cpu"]["reason"],
                          available=native.native_frame_available("cpu", torch.float64)
                          or native.native_collisions_available("cpu", torch.float64),
                          collide_same=bool(torch.equal(got[0], want[0]) and torch.equal(got[1], want[1])))))
    """
)


def test_fallback_without_native(tmp_path):
    """AMS_TORCH_NATIVE=0: both entry points (frame and collisions) give the torch path, nothing is
    built, one warning."""
    env = dict(os.environ, AMS_TORCH_CACHE=str(tmp_path / "cache"), PYTHONPATH=str(REPO))
    proc = subprocess.run([sys.executable, "-c", _FALLBACK_SCRIPT.format(tests=str(REPO / "tests"))], env=env,
                          capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr[-4000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["rel"] <= 1e-15 and out["collide_same"], out
    assert not out["built"] and not out["available"] and "AMS_TORCH_NATIVE" in out["reason"], out
    assert out["warnings"] == 1, out
    assert not (tmp_path / "cache").exists() or not any((tmp_path / "cache").iterdir())


# ---------------------------------------------------------------------------------------
# CUDA (skipped without a GPU)
# ---------------------------------------------------------------------------------------

@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
@pytest.mark.parametrize("case", ["default", "nonhookean", "one_particle_angular", "three_pins"])
@pytest.mark.parametrize("dtype", [F64, F32])
def test_cuda_matches_cpu(cpu_ops, case, dtype):
    """The CUDA kernel runs frame.h's arithmetic: equal to the CPU kernel to rounding, and the
    assembled system too."""
    ns_cuda = native_ns("cuda")
    out = {}
    for device in ("cpu", "cuda"):
        sim, state, pose1, coeffs = case_scene(case, dtype=dtype, device=device, scenes=2, strands=37)
        args = frame_args(sim, state, pose1, coeffs)
        ns = cpu_ops if device == "cpu" else ns_cuda
        out[device] = native_frame(ns, *args), native_system(ns, *args[:10], 1)
    tol = 1e-12 if dtype == F64 else 1e-5
    (xc, vc), (bc, rc) = out["cpu"]
    (xg, vg), (bg, rg) = out["cuda"]
    assert rel(xg, xc) <= tol and rel(vg, vc) <= tol and rel(bg, bc) <= tol and rel(rg, rc) <= tol


def test_python_tables_match_the_binding():
    """The op's model list (``native.MODEL_LAYOUT``) and settings (``FrameSettings``) are read by the
    C++ binding positionally: their order must be the binding's (``kModelNames`` of
    ``csrc/frame/frame_binding.h``; the settings' X-macro ``AMS_FRAME_SETTINGS`` of ``csrc/frame/frame.h``,
    from which the C++ struct, schemas and parameters are made). Two same-shape fields swapped on
    one side would pass every shape check; this catches it."""
    import re

    from ams_torch.sim.op_support import FrameSettings

    text = (_native.CSRC_ROOT / "frame" / "frame_binding.h").read_text()
    names = re.search(r"kModelNames\[kModelCount\]\s*=\s*\{(.*?)\};", text, re.S).group(1)
    assert tuple(re.findall(r'"(\w+)"', names)) == native.MODEL_FIELDS
    settings = (_native.CSRC_ROOT / "frame" / "frame.h").read_text()
    listed = re.search(r"#define AMS_FRAME_SETTINGS\(X\)(.*?)\n\n", settings, re.S).group(1)
    types = {"float": "double", "int": "int64_t", "bool": "bool"}  # the schema type's C++ parameter
    rows = re.findall(r'X\((\w+), (\w+), (\w+), "(\w+)"\)', listed)
    assert [r[1] for r in rows] == list(FrameSettings._fields)
    assert all(types[r[3]] == r[2] for r in rows), rows


def test_frame_settings_round_trip_config():
    """FrameSettings.of(config).config() is the config's frame settings (integrity model by name)."""
    from ams_torch.sim.op_support import FrameSettings
    from ams_torch.sim.state import Config

    cfg = Config(dt=0.02, substeps=3, integrity_model="nonhookean", angular=False, geometric_stiffness=True,
                 ftl_damping=0.7)
    s = FrameSettings.of(cfg)
    assert s.integrity_model == 2 and s.substeps == 3 and s.geometric_stiffness is True
    back = s.config()
    assert all(getattr(back, f) == getattr(cfg, f) for f in FrameSettings._fields)
