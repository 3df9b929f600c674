"""Builder → Model (issue 24 point 2): a complete model from the builder, Params frozen once built,
and an in-place edit of a model field either changing the next step or raising, never ignored."""
import pytest
import torch

import ams_torch as at
from ams_torch.sim import ModelBuilder, make_config, step
from ams_torch.sim.state import Config
from ams_torch.stages.collide import SphereCollider
from ams_torch.testing import sphere_groom

F64 = torch.float64


def _run(sim, frames=3):
    state = sim.initial_state()
    pose = at.Pose.from_rotvec((0.0, 0.0, 0.3), (0.01, 0.0, 0.0), dtype=sim.dtype)
    for _ in range(frames):
        state = sim.step(state, pose)
    return state.x


@pytest.mark.parametrize("material", ["per_length", "per_particle"])
def test_an_in_place_edit_of_a_material_field_changes_the_next_step(material):
    """``sim.model.drag.mul_(10)`` (and a stiffness edit) takes effect at the next step: the run
    equals one built with the edited values from the start; a later no-op ``.double()`` changes
    nothing more."""
    rest = sphere_groom(6, 8, seed=2)
    params = at.Params(drag=1.0) if material == "per_length" else at.Params.paper(num_pinned=1)
    stiff = "stretch_rigidity" if material == "per_length" else "stretch_stiffness"
    sim = at.Simulator(rest, params, dtype=F64, backend="torch")
    before = _run(sim)
    with torch.no_grad():
        sim.model.drag.mul_(10)
        getattr(sim.model, stiff).mul_(0.5)
    edited = _run(sim)
    want = _run(at.Simulator(rest, params.replace(drag=10 * params.drag, **{stiff: 0.5 * getattr(params, stiff)}),
                             dtype=F64, backend="torch"))
    assert (edited - before).abs().max() > 1e-6  # the edit changed the run
    torch.testing.assert_close(edited, want, rtol=1e-12, atol=1e-12)
    sim.double()  # a no-op conversion: nothing left to apply
    torch.testing.assert_close(_run(sim), edited, rtol=0, atol=0)
    # the pure step on the model sees the edit too (coefficients() checks the fields)
    model, config = sim.model, sim.config
    s = sim.initial_state()
    with torch.no_grad():
        model.drag.mul_(0.1)
    x = step(model, s, sim.control(s), config).x
    ref = at.Simulator(rest, params.replace(**{stiff: 0.5 * getattr(params, stiff)}), dtype=F64, backend="torch")
    s2 = ref.initial_state()
    torch.testing.assert_close(x, step(ref.model, s2, ref.control(s2), ref.config).x, rtol=1e-12, atol=1e-12)


def test_an_in_place_edit_of_the_rest_geometry_raises():
    rest = sphere_groom(4, 8, seed=3)
    for name in ("rest_positions", "edge_rest_length", "pinned"):
        sim = at.Simulator(rest, at.Params(), backend="torch")
        with torch.no_grad():
            t = getattr(sim.model, name)
            t.copy_(t if t.dtype == torch.bool else t * 1.01)
        with pytest.raises(ValueError, match=f"Model.{name} changed after the model was built"):
            sim.step(sim.initial_state())
        with pytest.raises(ValueError, match="rest geometry"):
            sim.double()  # a conversion does not silently accept it either


def test_params_are_frozen_once_built_and_the_guard_interval_is_the_simulators():
    params = at.Params(check_every=3)
    sim = at.Simulator(sphere_groom(3, 6, seed=1), params, backend="torch")
    with pytest.raises(AttributeError, match="frozen"):
        sim.params.dt = 0.1
    params.dt = 1 / 30  # the caller's own Params stay theirs
    assert sim.params.dt == pytest.approx(1 / 60) and sim.config.dt == pytest.approx(1 / 60)
    assert sim.params.replace(dt=0.01).dt == 0.01 and not sim.params.replace().is_frozen
    assert sim.check_every == 3 and sim.model.sag_free
    sim.check_every = 0  # a policy of the run: settable


def test_the_builder_makes_a_complete_model_and_the_config_holds_what_the_step_reads():
    rest = sphere_groom(5, 8, seed=4)
    params = at.Params(integrity_model="nonhookean")
    sphere = SphereCollider((0.0, 0.0, 0.0), 0.08)
    builder = ModelBuilder(rest, params, dtype=F64).set_learnable("drag")
    builder.set_hair_hair(at.HairHair(resolution=8)).add_collider(sphere)
    model = builder.finalize()
    assert len(model.colliders) == 1 and model.colliders[0] is not sphere  # its own copy
    assert model.colliders[0].center.dtype == F64 and model.hair_hair is not None
    assert isinstance(model.drag, torch.nn.Parameter) and model.params.is_frozen
    config = make_config(model, backend="torch")
    assert config.colliders == 1 and config.hair_hair and config.nonhookean
    assert {"projection_iterations", "follow_head"}.isdisjoint(Config.__dataclass_fields__)
    sim = at.Simulator(rest, params, dtype=F64, colliders=[sphere], hair_hair=at.HairHair(resolution=8),
                       learnable=("drag",), backend="torch")
    assert sim.config == config
    s = sim.initial_state()
    torch.testing.assert_close(step(model, s, sim.control(s), config).x, sim.step(s).x, rtol=0, atol=0)
    with pytest.raises(ValueError, match="collider"):
        ModelBuilder(rest).add_collider("sphere")


def test_a_study_swaps_and_wraps_stages_through_the_table():
    """The step runs the declared stages: a wrapped stage sees every frame, a replaced one runs
    instead of the library's (collisions replaced by nothing = the same scene without colliders),
    and the default table reproduces the library's step bit for bit."""
    from ams_torch.sim.stepping import STAGES, replace_stage, wrap_stage

    assert [s.name for s in STAGES] == ["dynamics", "hair_hair", "collisions", "finish", "yield"]
    rest = sphere_groom(5, 8, seed=6)
    params = at.Params(integrity_model="nonhookean", contact="frame")  # contact in the collision stage only
    ball = SphereCollider((0.0, 0.0, 0.0), 0.15)  # the strands start partly inside
    calls = []

    def count(run):
        return lambda f: calls.append(f.state.frame) or run(f)

    plain = at.Simulator(rest, params, dtype=F64, colliders=[ball], backend="torch")
    wrapped = at.Simulator(rest, params, dtype=F64, colliders=[ball], backend="torch",
                           stages=wrap_stage(STAGES, "yield", count))
    torch.testing.assert_close(_run(wrapped), _run(plain), rtol=0, atol=0)
    assert len(calls) == 3
    skipped = at.Simulator(rest, params, dtype=F64, colliders=[ball], backend="torch",
                           stages=replace_stage(STAGES, "collisions", lambda f: f))
    torch.testing.assert_close(_run(skipped), _run(at.Simulator(rest, params, dtype=F64, backend="torch")),
                               rtol=0, atol=0)
    assert (_run(skipped) - _run(plain)).abs().max() > 1e-6  # the ball mattered
    with pytest.raises(ValueError, match="no stage named"):
        replace_stage(STAGES, "collide", lambda f: f)
