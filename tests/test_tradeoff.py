"""The monotone part of the speed–accuracy trade (docs/tradeoff.md), checked on a small wisp.

- Time discretisation: at fixed N the error against a float64 run with many substeps falls as
  the substeps M rise, at first order (backward Euler): log–log slope ≈ −1.
- The presets: ``Params.preset("accurate")`` with its settings is closer to a converged
  reference than ``Params.preset("fast")`` with its settings.
"""
import math

import numpy as np
import pytest
import torch

import ams_torch as at
from ams_torch.testing import wisp

F64 = torch.float64
# the head bob of datasets/scenes/wisp_comparison.toml (and of scripts/bench_tradeoff.py's wisp)
BOB = {"type": "keyframes", "times": [0.0, 0.5, 1.0, 1.5, 2.0],
       "translations": [[0.0, 0.0, 0.0], [0.0, 0.1, 0.0], [0.0, -0.1, 0.0], [0.0, 0.1, 0.0], [0.0, 0.0, 0.0]]}


@pytest.fixture(autouse=True)
def one_thread():
    """Small problems: one intra-op thread is faster and steadier on a shared 2-core machine."""
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


def bob_wisp(params: at.Params, particles: int, frames: int, dtype=F64, strands: int = 4) -> torch.Tensor:
    """Positions (frames, strands, particles, 3) m, float64, of a wisp on the bobbing head."""
    motion = at.apps.motion.make_motion(BOB)
    rest = wisp(strands, particles, dtype=F64)
    sim = at.Simulator(rest, params, dtype=dtype, pose=motion(0.0, dtype=dtype))
    state = sim.initial_state()
    xs = []
    for pose in motion.poses(frames, params.dt, dtype=dtype):
        state = sim.step(state, pose)
        xs.append(state.x.double())
    return torch.stack(xs)


def at_material_points(ref: torch.Tensor, n: int) -> torch.Tensor:
    """(F, S, N_ref, 3) → (F, S, n, 3): the reference interpolated linearly at the rest arc-length
    fractions k/(n − 1) of an n-particle strand (both uniform in arc length)."""
    u = torch.linspace(0, 1, n, dtype=F64) * (ref.shape[-2] - 1)
    i0 = u.floor().long().clamp(max=ref.shape[-2] - 2)
    w = (u - i0)[:, None]
    return ref[..., i0, :] * (1 - w) + ref[..., i0 + 1, :] * w


def rms(x: torch.Tensor, ref: torch.Tensor) -> float:
    return float((x - at_material_points(ref, x.shape[-2])).norm(dim=-1).pow(2).mean().sqrt())


def test_error_falls_at_first_order_in_substeps(capsys):
    frames, n = 20, 16
    ref = bob_wisp(at.Params(substeps=64), n, frames)
    subs = [1, 2, 4, 8]
    errs = [rms(bob_wisp(at.Params(substeps=m), n, frames), ref) for m in subs]
    slope = float(np.polyfit(np.log(subs), np.log(errs), 1)[0])
    with capsys.disabled():
        print(f"\n[tradeoff] wisp RMS error vs M = 64 (mm): "
              + ", ".join(f"M={m}: {e * 1e3:.3g}" for m, e in zip(subs, errs)) + f"; slope {slope:.2f}")
    assert all(b < a for a, b in zip(errs, errs[1:])), errs
    assert -1.4 <= slope <= -0.7, slope
    assert errs[0] > 1e-4  # the case moves enough to measure (0.1 mm at M = 1)


def test_accurate_preset_beats_fast_on_the_wisp(capsys):
    frames = 20
    ref = bob_wisp(at.Params(substeps=32), 96, frames)
    errs = {}
    for name in ("fast", "accurate"):
        extra = at.Params.preset_settings(name)
        x = bob_wisp(at.Params.preset(name), extra["particles"], frames, dtype=getattr(torch, extra["dtype"]))
        errs[name] = rms(x, ref)
    with capsys.disabled():
        print(f"\n[tradeoff] wisp RMS error vs reference (mm): fast {errs['fast'] * 1e3:.3g}, "
              f"accurate {errs['accurate'] * 1e3:.3g}")
    assert errs["accurate"] < 0.75 * errs["fast"], errs


def test_presets_are_validated_params():
    names = ("fast", "balanced", "accurate")
    subs = []
    for name in names:
        p = at.Params.preset(name)
        assert isinstance(p, at.Params)
        extra = at.Params.preset_settings(name)
        assert set(extra) == {"particles", "dtype", "hair_hair_resolution"}
        assert extra["particles"] >= 4 and extra["dtype"] in ("float32", "float64")
        subs.append(p.substeps)
    assert subs == sorted(subs)
    assert at.Params.preset("balanced", drag=2.0).drag == 2.0
    assert at.Params.preset("fast", substeps=3).substeps == 3
    with pytest.raises(ValueError, match="fast, balanced, accurate"):
        at.Params.preset("fastest")
    with pytest.raises(ValueError, match="fast, balanced, accurate"):
        at.Params.preset_settings("slow")
    with pytest.raises(ValueError, match="unknown Params field"):
        at.Params.preset("fast", stiffness=1.0)
    with pytest.raises(ValueError, match="substeps must be a positive integer"):
        at.Params.preset("accurate", substeps=0)
    assert math.isclose(at.Params.preset("accurate").substep_dt * at.Params.preset("accurate").substeps,
                        at.Params().dt)
