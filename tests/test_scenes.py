"""Scene files: every shipped scene runs (scaled down) without NaN; only the named stages are
built; bad files fail with a message naming the key; trimming shortens strands."""
import glob
import os

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
    res = simulate(run)
    pos = res["positions"]
    assert pos.shape[0] == 3 and np.isfinite(pos).all()
    assert (run.sim.hair_hair_grid is not None) == scene["stages"]["hair_hair"]
    assert bool(run.sim.colliders) == scene["stages"]["collisions"]
    assert set(res["ms_per_frame"]) >= {"solve", "total"}
    if scene["colliders"]:  # world poses of the scene's colliders, for drawing
        assert res["collider_translations"].shape == (3, len(scene["colliders"]), 3)


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
