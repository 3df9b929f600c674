"""The Ratboy scene on the real TressFX files in ../shared/assets (skipped when that folder is
absent): the mohawk bound to the body mesh, which turns with a head motion."""
from pathlib import Path

import pytest
import torch

from ams_torch.apps.scene import SCENE_DIR, build, load_scene, simulate
from ams_torch.geometry.pose import Pose
from ams_torch.stages.collide import collider_distances

ASSETS = Path(__file__).resolve().parents[2] / "shared" / "assets"
pytestmark = pytest.mark.skipif(not (ASSETS / "Ratboy_body.tfxmesh").exists() or
                                not (ASSETS / "Ratboy_mohawk.tfx").exists(),
                                reason="../shared/assets with the TressFX Ratboy files is not here")


def test_ratboy_mohawk_stays_out_of_the_body_with_roots_on_it(capsys):
    scene = load_scene(f"{SCENE_DIR}/ratboy_mohawk.toml", {"frames": 6, "scale": 0.1})
    run = build(scene)
    binding = run.groom.metadata["binding"]
    assert binding["max_distance"] <= 2e-3 and run.groom.has_binding
    body = run.sim.colliders[0]
    half_voxel = 0.5 * body.sdf.voxel_size
    res = simulate(run)
    x = torch.as_tensor(res["positions"])
    worst, root_off = 0.0, 0.0
    for k in range(x.shape[0]):
        head = Pose(torch.as_tensor(res["rotations"][k]), torch.as_tensor(res["translations"][k]), check=False)
        d = collider_distances(x[k], [body], [head])[0]
        worst = min(worst, float(d[:, 2:].min()))
        root_off = max(root_off, float(d[:, 0].abs().max()))
    with capsys.disabled():
        print(f"\n[ratboy] {x.shape[1]} strands: binding median {binding['median_distance'] * 1e3:.4f} mm, max "
              f"{binding['max_distance'] * 1e3:.3f} mm; deepest particle {-worst * 1e3:.3f} mm inside (half voxel "
              f"{half_voxel * 1e3:.2f} mm); roots within {root_off * 1e3:.3f} mm of the surface")
    assert -worst <= half_voxel
    assert root_off <= half_voxel
