"""The benchmark's plug-in protocol and built-in methods on synthetic samples (no dataset)."""
import sys
import types

import pytest
import torch

from ams_torch.geometry.pose import Pose, axis_angle_to_matrix
from ams_torch.grooms.simple import sphere_groom
from ams_torch.stages.collide import SphereCollider
from baselines import select_guides
from baselines.methods import push_out
from baselines.protocol import (BUILTINS, Interpolator, MethodError, check_prediction, resolve_method, stream)

D = torch.float64


def _sample(t=5, s=60, n=10, g=12, colliders=(), seed=0):
    """A groom moved rigidly by a shaking head: the guides are the rigidly moved rest guides."""
    rest = sphere_groom(s, n, radius=0.1, length=0.2, dtype=D)
    gi = select_guides(rest[:, 0], g)
    angles = torch.linspace(0.0, 0.6, t, dtype=D)
    rots = torch.stack([axis_angle_to_matrix(torch.tensor([0.2, 1.0, 0.1], dtype=D) * a) for a in angles])
    trans = torch.stack([torch.tensor([0.01, -0.02, 0.03], dtype=D) * a for a in angles])
    world = torch.einsum("tij,snj->tsni", rots, rest) + trans[:, None, None]
    cols = list(colliders)
    poses = [Pose(rots, trans, check=False) if c.follow_head else Pose(torch.eye(3, dtype=D).expand(t, 3, 3),
                                                                          torch.zeros(t, 3, dtype=D), check=False)
             for c in cols]
    return {"guide_positions": world[:, gi], "rotations": rots, "translations": trans, "rest_positions": rest,
            "guide_index": gi, "num_pinned": torch.full((s,), 2), "colliders": cols, "collider_poses": poses,
            "head_collider": 0 if cols and cols[0].follow_head else -1, "dt": 1 / 60, "sequence": 0,
            "start": 0}, world


@pytest.mark.parametrize("name", ["rigid", "skinning", "blend", "skinning+pushout"])
def test_rigid_motion_is_reproduced_exactly(name):
    sample, world = _sample()
    method = resolve_method(name, {"device": torch.device("cpu")})
    out = check_prediction(name, method.predict(sample), sample)
    assert torch.allclose(out, world, atol=1e-12)
    assert torch.allclose(stream(method, sample), out, atol=1e-12)  # causal streaming = predict


def test_nearest_reproduces_guides_and_streams():
    sample, world = _sample()
    method = resolve_method("nearest")
    out = method.predict(sample)
    assert torch.allclose(out[:, sample["guide_index"]], sample["guide_positions"], atol=1e-12)
    assert torch.allclose(out, world, atol=1e-12)  # rigid motion: offsets carried by the head
    assert torch.allclose(stream(method, sample), out, atol=1e-12)


def test_blend_reproduces_guides_is_nearest_at_k1_and_is_a_weighted_mean():
    sample, world = _sample()
    # the guides bend (each guide vertex i displaced by d_g,i): blend moves a strand by Σ w_k d_k,i
    g = torch.Generator().manual_seed(1)
    d = 0.01 * torch.randn(sample["guide_positions"].shape, generator=g, dtype=D)
    bent = dict(sample, guide_positions=sample["guide_positions"] + d)
    blend = resolve_method("blend")
    out = blend.predict(bent)
    assert torch.allclose(out[:, sample["guide_index"]], bent["guide_positions"], atol=1e-12)  # guides exact
    w, idx = blend._weights, blend._index
    want = world + (w[None, :, :, None, None] * d[:, idx]).sum(2)
    assert torch.allclose(out, want, atol=1e-12)
    one = resolve_method("blend", k=1).predict(bent)
    assert torch.allclose(one, resolve_method("nearest").predict(bent), atol=1e-12)
    assert torch.allclose(stream(blend, bent), out, atol=1e-12)


def test_pushout_removes_penetration_and_keeps_the_rest():
    head = SphereCollider(radius=0.1, follow_head=True).to(dtype=D)
    ball = SphereCollider(radius=0.05, center=(0.0, 0.12, 0.0)).to(dtype=D)  # cuts through the hair
    sample, world = _sample(colliders=[head, ball])
    skin = resolve_method("skinning").predict(sample)
    out = resolve_method("skinning+pushout").predict(sample)
    sd = torch.stack([c.distance(p.to_local(out.reshape(out.shape[0], -1, 3)))
                      for c, p in zip(sample["colliders"], sample["collider_poses"])]).reshape((2,) + out.shape[:-1])
    free = torch.arange(out.shape[2])[None, :] >= 2
    assert bool((sd.amin(0)[:, :, free[0]] > -1e-9).all())  # nothing free inside either sphere
    inside_before = torch.stack([c.distance(p.to_local(skin.reshape(skin.shape[0], -1, 3)))
                                 for c, p in zip(sample["colliders"], sample["collider_poses"])]).amin(0)
    moved = (out - skin).norm(dim=-1).reshape(inside_before.shape) > 0
    assert bool(moved.any()) and not bool((moved & (inside_before > 0)).any())  # only inside vertices move
    assert torch.equal(out[:, :, :2], skin[:, :, :2])  # pinned vertices untouched
    with pytest.raises(ValueError, match=r"free must be \(S, N\)"):
        push_out(out, [head], sample["collider_poses"][:1], torch.ones(3, 3, dtype=torch.bool))


def test_check_prediction_names_the_problem():
    sample, world = _sample()
    with pytest.raises(MethodError, match="mine.*shape .*expected \\(5, 60, 10, 3\\)"):
        check_prediction("mine", world[:, :10], sample)
    with pytest.raises(MethodError, match="returned list"):
        check_prediction("mine", [1], sample)
    bad = world.clone()
    bad[0, 0, 0, 0] = float("nan")
    with pytest.raises(MethodError, match="NaN"):
        check_prediction("mine", bad, sample)


class _Shift(Interpolator):
    name = "shift"

    def __init__(self, offset=0.0):
        self.offset = offset

    def predict(self, sample):
        return resolve_method("rigid").predict(sample) + self.offset


def make_shift(offset: float = 0.0, device=None):
    return _Shift(offset)


def test_plugins_by_module_factory_and_errors(monkeypatch):
    mod = types.ModuleType("my_interp_plugin")
    mod.make_shift, mod.not_callable, mod.wrong = make_shift, 3, (lambda: object())
    monkeypatch.setitem(sys.modules, "my_interp_plugin", mod)
    m = resolve_method("my_interp_plugin:make_shift", {"device": "cpu", "checkpoint": "x.pt"}, offset=0.5)
    assert isinstance(m, _Shift) and m.offset == 0.5  # context keywords it does not take are not passed
    with pytest.raises(MethodError, match="takes no option"):
        resolve_method("my_interp_plugin:make_shift", steps=3)
    with pytest.raises(MethodError, match="not callable"):
        resolve_method("my_interp_plugin:not_callable")
    with pytest.raises(MethodError, match="no fit/predict"):
        resolve_method("my_interp_plugin:wrong")
    with pytest.raises(MethodError, match="has no attribute"):
        resolve_method("my_interp_plugin:missing")
    with pytest.raises(MethodError, match="cannot import"):
        resolve_method("no_such_module_xyz:f")
    assert {"rigid", "nearest", "skinning", "skinning+pushout"} <= set(BUILTINS)
    with pytest.raises(MethodError, match="not causal"):
        m.reset({})
