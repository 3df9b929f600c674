"""Scene files: every shipped scene runs (scaled down) without NaN; only the named stages are
built; bad files fail with a message naming the key; trimming shortens strands."""
import glob
import os
from pathlib import Path

import numpy as np
import pytest
import torch

import ams_torch as at
from ams_torch.apps.scene import SCENE_DIR, SceneError, build, load_scene, parse_scene, simulate, trim_strands

SCENES = sorted(glob.glob(os.path.join(SCENE_DIR, "*.toml")))


def test_scene_dir_has_the_paper_scenes():
    names = {os.path.splitext(os.path.basename(p))[0] for p in SCENES}
    assert {"default", "single_strand", "wisp_comparison", "wig_in_wind", "hollow_sphere", "asymmetric_style",
            "beard", "roller_coaster", "hand_interaction", "digital_trimming"} <= names


@pytest.mark.parametrize("path", SCENES, ids=lambda p: os.path.basename(p))
def test_every_scene_runs_a_few_frames(path):
    """Every shipped scene runs (scaled down) and keeps the physical property it is about
    (:func:`_check_scene_physics`)."""
    if "shared/assets" in Path(path).read_text() and not (Path(__file__).resolve().parents[2] / "shared" / "assets").is_dir():
        pytest.skip("the scene reads real assets from ../shared/assets, which is not here")
    scene = load_scene(path, {"frames": 3})
    strands = scene["groom"].get("strands", 1000)
    scene["scale"] = min(1.0, 12.0 / strands)
    if "hair_hair" in scene:
        scene["hair_hair"]["resolution"] = 16
    if "trim" in scene:
        scene["trim"]["frame"] = 2
    scene["head"]["subdivisions"] = min(scene["head"]["subdivisions"], 3)
    scene["head"]["sdf_resolution"] = 32
    run = build(scene)
    contact = []  # the lowest signed distance of a free particle to any collider, per frame (m)

    def on_frame(k, state):
        if run.sim.colliders:
            contact.append(_lowest_clearance(run, state, (k + 1) * run.sim.params.dt))

    res = simulate(run, on_frame=on_frame)
    pos = res["positions"]
    assert pos.shape[0] == 3 and np.isfinite(pos).all()
    assert (run.sim.hair_hair_grid is not None) == scene["stages"]["hair_hair"]
    assert bool(run.sim.colliders) == scene["stages"]["collisions"]
    assert set(res["ms_per_frame"]) >= {"solve", "total"}
    if scene["colliders"]:  # world poses of the scene's colliders, for drawing
        assert res["collider_translations"].shape == (3, len(scene["colliders"]), 3)
    _check_scene_physics(scene, run, res, contact)


def _lowest_clearance(run, state, t: float) -> float:
    """min over free particles and colliders of σ(x) (m, negative inside) at the end of a frame."""
    from ams_torch.stages.collide import collider_distances, resolve_world_poses

    cols = list(run.sim.model.colliders)
    cposes = [None if m is None else m(t, device=state.x.device, dtype=state.x.dtype) for m in run.collider_motions]
    poses = resolve_world_poses(cols, state.pose, cposes if any(p is not None for p in cposes) else None)
    sigma = collider_distances(state.x, cols, poses)  # (C, S, N)
    free = torch.arange(state.x.shape[-2])[None, :] >= run.sim.model.num_pinned[:, None]
    return float(torch.where(free, sigma, torch.full_like(sigma, float("inf"))).min())


def _check_scene_physics(scene, run, res, contact) -> None:
    """One physical property per scene, chosen by what the scene is about.

    - with collisions: **the contact holds**: after every frame no free particle is inside a
      collider by more than 0.1 mm (the collision stage ends with a push-out to σ = 0);
    - with hair–hair interaction: **the grid transfer conserves momentum**: the stage applied to the
      final state (every particle free) keeps Σ m v (to 1e-5 of Σ m |v|);
    - ``single_strand`` (released horizontally, no sag-free offset): **it falls, no faster than
      free fall**: the vertical momentum is negative and above −M g t;
    - ``wisp_comparison``: **the AMS wisp keeps its rest shape** better than its plain mass-spring
      copy (the scene's point: the MS copy sags) — rigidly aligned shape deviation.
    Every scene: the pinned roots sit on the head's rest roots carried by its pose (to 1e-5 m)."""
    state = res["state"]
    model = run.sim.model
    pinned = model.pinned
    rooted = state.pose.to_world(model.rest_positions)
    assert float((state.x - rooted).norm(dim=-1)[pinned].max()) <= 1e-5, "the pinned roots left the head"
    if run.sim.colliders:
        assert min(contact) >= -1e-4, f"a free particle ended {-min(contact) * 1e3:.3g} mm inside a collider"
    if run.sim.hair_hair_grid is not None:
        from ams_torch.sim.model import coefficients
        from ams_torch.stages.hair_hair import hair_hair_stage

        mass = coefficients(model).mass
        _, v = hair_hair_stage(run.sim.hair_hair_grid, state.x, state.v, mass, state.pose, run.sim.params.dt)
        before, after = (mass[..., None] * state.v).sum((0, 1)), (mass[..., None] * v).sum((0, 1))
        scale = float((mass * state.v.norm(dim=-1)).sum())
        assert float((after - before).norm()) <= 1e-5 * scale, "the hair–hair stage changed the momentum"
    name = scene["name"]
    if name == "single_strand":
        mass = coefficients_mass(model)
        total = float(mass.sum())
        t = 3 * run.sim.params.dt
        py = float((mass * state.v[..., 1]).sum())
        assert -total * 9.81 * t <= py < 0, f"vertical momentum {py:.3g} (free fall: {-total * 9.81 * t:.3g})"
    if name == "wisp_comparison":
        from ams_torch.testing import shape_deviation

        s = state.x.shape[0] // 2
        dev = shape_deviation(state.x, model.rest_positions, align=True)
        assert float(dev[:s].mean()) < 0.5 * float(dev[s:].mean()), (float(dev[:s].mean()), float(dev[s:].mean()))


def coefficients_mass(model):
    from ams_torch.sim.model import coefficients

    return coefficients(model).mass


def test_scene_without_stages_builds_neither():
    scene = parse_scene({"groom": {"kind": "sphere", "strands": 5, "particles": 8}, "head": {"mesh": "sphere"},
                         "frames": 2, "stages": {"hair_hair": False, "collisions": False}})
    run = build(scene)
    assert run.sim.hair_hair_grid is None and not run.sim.colliders
    res = simulate(run)
    assert set(res["ms_per_frame"]) == {"solve", "total"}


def _bad(tmp_path, text):
    p = tmp_path / "bad.toml"
    p.write_text(text)
    return str(p)


@pytest.mark.parametrize("text,key", [
    ('frames = 3\ncolour = "red"\n', "colour"),
    ('frames = "many"\n', "frames"),
    ('[head]\nmesh = "missing_head.obj"\n', "[head].mesh"),
    ('[params]\nstretch_stiffness = -1.0\n', "stretch_stiffness"),
    ('[params]\nsubsteps = 1.5\n', "substeps"),
    ('[params]\nbend_scael = 1.0\n', "bend_scael"),
    ('[groom]\npreset = "mohawk"\n', "[groom].preset"),
    ('[stages]\ncollisions = "yes"\n', "[stages].collisions"),
    ('[motion]\ntype = "shake"\nfrequncy = 2.0\n', "frequncy"),
    ('[wind]\nspeed = -3.0\n', "[wind].speed"),
    ('[stages]\ncollisions = true\n[[colliders]]\ntype = "sphere"\nradius = 0.1\ncentre = [0, 0, 0]\n', "centre"),
    ('[[colliders]]\ntype = "sphere"\n', "[stages].collisions"),
    ('[trim]\nnormal = [0, 0]\n', "[trim].normal"),
])
def test_bad_scene_names_the_key(tmp_path, text, key):
    with pytest.raises(SceneError) as err:
        load_scene(_bad(tmp_path, text))
    assert key in str(err.value) and "bad.toml" in str(err.value)


def test_missing_scene_file():
    with pytest.raises(SceneError, match="no such scene file"):
        load_scene("no/such/scene.toml")


def test_trim_shortens_crossing_strands_only():
    rest = torch.zeros(2, 11, 3)
    rest[:, :, 1] = -torch.linspace(0, 0.2, 11)  # hanging down 0.2 m
    rest[1, :, 1] *= 0.4  # the second strand ends above the plane
    pose = at.Pose.identity()
    new_rest, x, v, frac = trim_strands(rest, rest.clone(), torch.zeros_like(rest), pose, (0, -0.12, 0), (0, -1, 0))
    assert torch.allclose(frac, torch.tensor([0.6, 1.0]), atol=1e-5)
    assert torch.allclose(new_rest[0, -1, 1], torch.tensor(-0.12), atol=1e-5)
    assert torch.allclose(new_rest[1], rest[1], atol=1e-6)
    seg = (new_rest[0, 1:] - new_rest[0, :-1]).norm(dim=-1)
    assert torch.allclose(seg, torch.full_like(seg, 0.012), atol=1e-5)


# -- imported assets, rotations, tables --------------------------------------------------------
ASSETS = Path(__file__).resolve().parents[2] / "shared" / "assets"
R90Y = [[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]  # 90° about +y


def _files(tmp_path):
    (tmp_path / "head.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    (tmp_path / "hair.ply").write_text("ply\n")
    return {"head": {"mesh": "head.obj"}, "groom": {"file": "hair.ply", "strands": 10}, "frames": 2}


def test_imported_asset_keys_are_normalised(tmp_path):
    base = _files(tmp_path)
    s = parse_scene({**base, "head": {"mesh": "head.obj", "units": "cm", "up_axis": "z",
                                      "transform": {"rotation": R90Y, "translation": [0.0, 0.1, 0.0]}},
                     "groom": {"file": "hair.ply", "units": "mm", "bind": True, "max_bind_distance": 0.002}},
                    where="s.toml", base=str(tmp_path))
    assert s["head"]["mesh"] == str(tmp_path / "head.obj") and s["groom"]["file"] == str(tmp_path / "hair.ply")
    assert s["head"]["scale"] == 0.01 and "units" not in s["head"] and s["head"]["up_axis"] == "z"
    assert s["groom"]["scale"] == 0.001 and s["groom"]["up_axis"] == "y" and s["groom"]["bind"] is True
    assert s["head"]["transform"] == {"rotation": R90Y, "translation": [0.0, 0.1, 0.0]}
    m = [[0.0, 0.0, 1.0, 0.5], [0.0, 1.0, 0.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
    s = parse_scene({**base, "groom": {"file": "hair.ply", "scale": 2.0, "transform": m}}, base=str(tmp_path))
    assert s["groom"]["transform"] == {"rotation": R90Y, "translation": [0.5, 0.0, 0.0]} and s["groom"]["scale"] == 2.0
    c, sn = np.cos(0.3), np.sin(0.3)  # 7 significant digits: within 1e-5, returned as the exact nearest rotation
    r7 = [[float(f"{c:.7f}"), 0.0, float(f"{sn:.7f}")], [0.0, 1.0, 0.0], [-float(f"{sn:.7f}"), 0.0, float(f"{c:.7f}")]]
    out = np.array(parse_scene({**base, "groom": {"file": "hair.ply", "transform": {"rotation": r7}}},
                               base=str(tmp_path))["groom"]["transform"]["rotation"])
    assert np.abs(out.T @ out - np.eye(3)).max() < 1e-14 and np.abs(out - np.array(r7)).max() < 1e-6


@pytest.mark.parametrize("section,value,message", [
    ("groom", {"file": "hair.ply", "transform": {"rotation": [[1.01, 0, 0], [0, 1, 0], [0, 0, 1]]}},
     "[groom.transform].rotation is not a rotation matrix: its rows are not orthonormal (max |R^T R - I| = 0.02"),
    ("groom", {"file": "hair.ply", "transform": {"rotation": [[0.7071, 0, 0.7071], [0, 1, 0], [-0.7071, 0, 0.7071]]}},
     "tolerance 1e-05; write the entries with at least 6 significant digits"),
    ("head", {"mesh": "head.obj", "transform": [[-1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]},
     "[head].transform (its upper-left 3x3) is not a rotation matrix: det = -1 (a reflection"),
    ("head", {"mesh": "head.obj", "transform": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]]},
     "[head].transform: the last row of a 4x4 transform must be [0, 0, 0, 1]; got [0.0, 0.0, 1.0, 1.0]"),
    ("head", {"mesh": "head.obj", "transform": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]},
     "[head].transform must be a 4x4 nested list of numbers"),
    ("motion", {"type": "keyframes", "times": [0.0, 1.0], "rotations": [R90Y, [[1, 0, 0], [0, 1, 0], [0, 0, -1]]]},
     "[motion].rotations[1] is not a rotation matrix: det = -1"),
    ("motion", {"type": "keyframes", "times": [0.0, 1.0], "rotations": [R90Y], "translations": [[0, 0, 0]] * 2},
     "[motion].rotations has 1 entries; [motion].times has 2"),
    ("groom", {"preset": "straight", "units": "cm"}, "[groom].units applies to a file ([groom].file)"),
    ("groom", {"file": "hair.ply", "units": "cm", "scale": 0.01}, "[groom]: give units or scale, not both"),
    ("groom", {"file": "hair.ply", "units": "inch"}, "[groom].units must be one of ['m', 'cm', 'mm']; got 'inch'"),
    ("groom", {"preset": "straight", "bind": True}, "[groom].bind binds a groom read from a file"),
    ("groom", {"file": "hair.ply", "max_bind_distance": 0.01}, "[groom].max_bind_distance needs bind = true"),
    ("groom", {"file": "hair.ply", "bind": True, "max_bind_distance": -1.0},
     "[groom].max_bind_distance must be a finite number > 0; got -1.0"),
    ("head", {"mesh": "default", "up_axis": "z"}, "[head].up_axis applies to a file ([head].mesh = path)"),
    ("head", {"mesh": "head.obj", "up_axis": "x"}, "[head].up_axis must be one of ['y', 'z']; got 'x'"),
    ("head", {"mesh": "hair.ply2"}, "[head].mesh: 'hair.ply2' is not a mesh file (extension .ply2; known:"),
    ("groom", {"file": "head.obj"}, "[groom].file: 'head.obj' is not a groom file (extension .obj; known:"),
])
def test_import_keys_and_rotations_are_checked(tmp_path, section, value, message):
    raw = _files(tmp_path)
    raw[section] = value
    if section == "groom" and value.get("bind"):
        raw["head"] = {"mesh": "head.obj"}
    with pytest.raises(SceneError) as err:
        parse_scene(raw, where="scene.toml", base=str(tmp_path))
    assert str(err.value).startswith("scene.toml: ") and message in str(err.value), str(err.value)


def test_keyframe_rotations_become_rotvecs(tmp_path):
    s = parse_scene({"motion": {"type": "keyframes", "times": [0.0, 1.0], "rotations": [np.eye(3).tolist(), R90Y]}})
    assert "rotations" not in s["motion"] and np.allclose(s["motion"]["rotvecs"], [[0, 0, 0], [0, np.pi / 2, 0]])
    with pytest.raises(SceneError, match=r"\[groom\].bind needs a head mesh to bind to"):
        parse_scene({**_files(tmp_path), "head": {"mesh": "sphere"}, "groom": {"file": "hair.ply", "bind": True}},
                    base=str(tmp_path))


@pytest.mark.parametrize("section", ["head", "groom", "stages", "params", "hair_hair", "wind", "trim", "render",
                                     "motion", "colliders"])
def test_every_section_is_a_table_of_known_keys(section):
    raw = {"head": {"mesh": "sphere"}, "groom": {"kind": "sphere"}, "stages": {"hair_hair": True, "collisions": True}}
    table = {"motion": {"type": "shake", "colour": 1}, "colliders": [{"type": "sphere", "colour": 1}]}.get(
        section, {**raw.get(section, {}), "colour": 1})
    raw[section] = table
    with pytest.raises(SceneError) as err:
        parse_scene(raw, where="scene.toml")
    name = "colliders[0]" if section == "colliders" else section
    assert f"unknown key(s) ['colour'] in [{name}]; allowed: [" in str(err.value)


def test_the_real_ratboy_assets_parse(tmp_path):
    if not ASSETS.is_dir():
        pytest.skip("shared assets folder absent")
    s = load_scene(_bad(tmp_path, f'frames = 2\n[head]\nmesh = "{ASSETS / "Ratboy_body.tfxmesh"}"\nunits = "m"\n'
                                  f'[groom]\nfile = "{ASSETS / "Ratboy_mohawk.tfx"}"\nbind = true\n'
                                  f'max_bind_distance = 0.001\n'))
    assert s["head"]["mesh"].endswith("Ratboy_body.tfxmesh") and s["head"]["scale"] == 1.0
    assert s["groom"]["file"].endswith("Ratboy_mohawk.tfx") and s["groom"]["max_bind_distance"] == 0.001


def test_validators_are_short_functions():
    """Scene and recipe validation stays table driven: no function over 50 lines."""
    import ast

    import ams_torch.apps.recipe as recipe_pkg
    import ams_torch.apps.scene.schema as schema

    paths = [schema.__file__] + sorted(glob.glob(os.path.join(os.path.dirname(recipe_pkg.__file__), "*.py")))
    long = []
    for p in paths:
        for node in ast.walk(ast.parse(open(p).read())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node.end_lineno - node.lineno + 1 > 50:
                long.append(f"{os.path.basename(p)}:{node.name} ({node.end_lineno - node.lineno + 1} lines)")
    assert not long, long
