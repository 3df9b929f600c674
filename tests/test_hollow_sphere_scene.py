"""The hollow-sphere scene is a cage open at the bottom, as its description and drawing say
(it was a bowl: cut_height = −0.12 on the default +y axis opened everything above y = −0.12)."""
import torch

from ams_torch.apps.scene import SCENE_DIR, build, load_scene, simulate
from ams_torch.geometry.pose import Pose
from ams_torch.stages.collide import HollowSphereCollider, collider_distances


def test_the_scene_collider_is_closed_above_and_open_below():
    scene = load_scene(f"{SCENE_DIR}/hollow_sphere.toml")
    spec = scene["colliders"][0]
    col = HollowSphereCollider(**{k: spec[k] for k in ("center", "radius", "thickness", "cut_height", "axis")})
    mid = spec["radius"]
    top, bottom = torch.tensor([[0.0, mid, 0.0]]), torch.tensor([[0.0, -mid, 0.0]])
    assert float(col.distance(top)) < 0  # the wall is there at the top ...
    assert float(col.distance(bottom)) > 0  # ... and the cap below is open
    bowl = HollowSphereCollider(spec["center"], spec["radius"], spec["thickness"], cut_height=-0.12)
    assert float(bowl.distance(top)) > 0  # the old parameters: no wall above y = -0.12


def test_no_free_particle_ends_outside_where_the_shell_is_closed():
    scene = load_scene(f"{SCENE_DIR}/hollow_sphere.toml", {"scale": 0.25})
    run = build(scene)
    col = run.sim.colliders[-1]
    res = simulate(run)
    x = torch.as_tensor(res["positions"]).double()
    rot = torch.as_tensor(res["collider_rotations"]).double()[:, -1]
    trans = torch.as_tensor(res["collider_translations"]).double()[:, -1]
    pinned = run.sim.model.num_pinned.max().item()
    d = x[..., pinned:, :] - trans[:, None, None, :]
    axis = (rot @ col.axis.double())[:, None, None, :]
    closed = (d * axis).sum(-1) < col.cut_height - col.thickness  # away from the opening and its rim
    outside = d.norm(dim=-1) > col.radius + col.thickness / 2
    assert int((closed & outside).sum()) == 0, "hair crossed the closed part of the shell"
    sigma = torch.stack([collider_distances(x[k].float(), [col], [Pose(rot[k].float(), trans[k].float(), check=False)])[0]
                         for k in range(x.shape[0])])
    assert float(sigma[..., pinned:].min()) > -1e-4  # and no particle inside the wall
