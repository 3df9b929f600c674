"""The Simulator API's inputs (issue 28, items 10, 11 and 14's Params/dtype/device ones): a
callable external force is checked like a tensor at every frame on both backends, its NaN blames
the input; a state whose tensors disagree on their scene dims is refused; half precision, int
dtypes, the meta device, strings for numbers, a NaN check_every, a 1e-300 s dt and values that
overflow float32 are refused naming the argument."""
import pytest
import torch

import ams_torch as at
from ams_torch.grooms.simple import sphere_groom

BACKENDS = ["torch", "auto"]  # auto: the native kernels where they build (the callable runs on the torch frame)


def _sim(backend, **kw):
    return at.Simulator(sphere_groom(6, 8, seed=3), at.Params(), backend=backend, **kw)


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_callable_force_is_checked_like_a_tensor(backend):
    sim = _sim(backend)
    s = sim.initial_state()
    shape = tuple(s.x.shape)
    cases = {  # what the callable returns -> what the error says
        "batched": (lambda x, v, t: torch.zeros((2,) + x.shape), r"returned shape \(2, 6, 8, 3\)"),
        "wrong size": (lambda x, v, t: torch.zeros(6, 7, 3), r"returned shape \(6, 7, 3\)"),
        "None": (lambda x, v, t: None, "it returned NoneType"),
        "int": (lambda x, v, t: torch.zeros(x.shape, dtype=torch.int32), "floating-point tensor; it returned torch.int32"),
        "numpy": (lambda x, v, t: x.numpy() * 0, "it returned ndarray"),
    }
    for name, (fn, said) in cases.items():
        with pytest.raises(ValueError, match=r"external_force\(x, v, t\) must return .*" + said):
            sim.step(s, external_force=fn)
    # broadcastable and float64 on a float32 simulator: converted like a tensor, the state stays float32
    push = torch.tensor([0.0, 0.0, 1e-6], dtype=torch.float64)
    a = sim.step(s, external_force=lambda x, v, t: push)
    b = sim.step(s, external_force=lambda x, v, t: push.float().expand(shape))
    assert a.x.dtype == torch.float32 and torch.equal(a.x, b.x)


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_callable_that_returns_nan_blames_the_input(backend):
    """Before: "diverged ... Try more substeps, a smaller dt or lower stiffness"."""
    sim = _sim(backend)
    s = sim.initial_state()
    bad = lambda x, v, t: torch.full_like(x, float("nan"))  # noqa: E731
    with pytest.raises(at.SimulationDiverged, match="already held NaN/Inf") as err:
        sim.step(s, external_force=bad)
    assert err.value.bad_input and "more substeps" not in str(err.value)
    for _ in range(2):  # a clean callable that diverges is still the physics' fault (flag not set)
        s = sim.step(s, external_force=lambda x, v, t: torch.zeros_like(x))
    assert int(s.diverged_frame) == -1


@pytest.mark.slow
def test_a_callable_force_traces_without_graph_breaks():
    sim = _sim("torch")
    force = lambda x, v, t: 1e-6 * torch.ones_like(x)  # noqa: E731
    explained = torch._dynamo.explain(sim.step)(sim.initial_state(), None, external_force=force)
    assert explained.graph_break_count == 0, [r.reason for r in explained.break_reasons]


@pytest.mark.slow
def test_a_callable_force_compiles_fullgraph():
    sim = _sim("torch")
    s0 = sim.initial_state()
    force = lambda x, v, t: 1e-6 * torch.ones_like(x)  # noqa: E731
    compiled = torch.compile(sim.step, fullgraph=True, backend="aot_eager")
    e = c = s0
    for _ in range(2):
        e, c = sim.step(e, external_force=force), compiled(c, external_force=force)
    torch.testing.assert_close(c.x, e.x, rtol=0, atol=0)


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_state_whose_tensors_disagree_on_scene_dims_is_refused(backend):
    """Batched ghost_rest with an unbatched x batched the state silently on the torch path and
    raised a kernel error on the native one."""
    sim = _sim(backend)
    s = sim.initial_state()
    for name in ("ghost_rest", "sag_offset"):
        batched = s.replace(**{name: getattr(s, name).expand(2, *s.x.shape).clone()})
        with pytest.raises(ValueError, match=rf"state\.{name} has shape \(2, 6, 8, 3\) but state\.x \(6, 8, 3\)"):
            sim.step(batched)


@pytest.mark.parametrize("kw,said", [
    (dict(dtype=torch.float16), "dtype must be torch.float32 or torch.float64; got torch.float16 .half precision"),
    (dict(dtype=torch.bfloat16), "got torch.bfloat16"),
    (dict(dtype=torch.int32), "got torch.int32"),
    (dict(device="meta"), "device 'meta' holds no data"),
    (dict(device="nowhere"), "device 'nowhere' is not a torch device"),
    (dict(params=at.Params(gravity=(0.0, -1e308, 0.0))), r"Params.gravity = .* does not fit in torch.float32"),
    (dict(params=at.Params(stretch_rigidity=1e300)), r"Params.stretch_rigidity = 1e\+300 does not fit"),
    (dict(params=at.Params(gravity=(0.0, -1e308, 0.0)), dtype=torch.float64), r"does not fit in torch.float64"),
])
def test_simulator_arguments_that_cannot_run_are_refused(kw, said):
    """float16 ran and "diverged, try more substeps" at frame 1; bfloat16 ran; int32 and 'meta'
    gave raw TypeErrors; 1e308 gravity diverged with "try more substeps"."""
    with pytest.raises(ValueError, match=said):
        at.Simulator(sphere_groom(4, 8, seed=1), **kw)


@pytest.mark.parametrize("field,value,said", [
    ("drag", "strong", "Params.drag must be a number or a floating-point tensor; got 'strong'"),
    ("stretch_rigidity", None, "Params.stretch_rigidity must be a number .* got None"),
    ("check_every", float("nan"), "Params.check_every must be a non-negative integer; got nan"),
    ("check_every", 2.0, "Params.check_every must be a non-negative integer"),
    ("sag_free", "yes", "Params.sag_free must be true or false"),
    ("gravity", (0.0, "down", 0.0), "Params.gravity must be three numbers"),
    ("dt", 1e-300, r"Params.dt = 1e-300 s over 1 substep\(s\) is a substep of 1e-300 s, below 1e-09 s"),
])
def test_params_of_the_wrong_kind_are_named(field, value, said):
    with pytest.raises(ValueError, match=said):
        at.Params(**{field: value})
    assert at.Params(drag=torch.tensor(2.0)).drag.item() == 2.0  # tensors stay welcome (learnable fields)
