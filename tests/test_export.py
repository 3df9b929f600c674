"""Animated USD out (ams_torch.apps.export): time samples against the HDF5 frames, transforms
of the head and the colliders, tessellations on the analytic surfaces, and the USD validators."""
import numpy as np
import pytest
import torch

pxr = pytest.importorskip("pxr")
h5py = pytest.importorskip("h5py")

from pxr import Gf, Usd, UsdGeom  # noqa: E402

from ams_torch.apps.cli import write_sequence  # noqa: E402
from ams_torch.apps.export import PLANE_SIZE, collider_mesh, export_usd, export_usd_arrays  # noqa: E402
from ams_torch.geometry.pose import axis_angle_to_matrix  # noqa: E402
from ams_torch.sim.params import Params  # noqa: E402

COLLIDERS = [
    {"type": "sphere", "center": [0.0, -0.3, 0.1], "radius": 0.05},
    {"type": "capsule", "a": [0.1, 0.0, 0.0], "b": [0.1, 0.2, 0.05], "radius": 0.03, "follow_head": True},
    {"type": "plane", "point": [0.0, -0.5, 0.0], "normal": [0.0, 1.0, 0.2]},
    {"type": "hollow_sphere", "center": [0.0, 0.0, 0.0], "radius": 0.3, "thickness": 0.02, "cut_height": 0.15,
     "axis": [0.0, 1.0, 0.0]},
]


def rotations(frames, seed):
    rng = np.random.default_rng(seed)
    return axis_angle_to_matrix(torch.as_tensor(rng.normal(size=(frames, 3)) * 0.3)).numpy()


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    """A sequence file as ``ams-torch simulate`` writes it (synthetic frames)."""
    rng = np.random.default_rng(0)
    f, s, n, c = 7, 5, 6, len(COLLIDERS)
    result = {
        "positions": (rng.normal(size=(f, s, n, 3)) * 0.1).astype(np.float32),
        "rotations": rotations(f, 1),
        "translations": rng.normal(size=(f, 3)) * 0.05,
        "collider_rotations": rotations(f * c, 2).reshape(f, c, 3, 3),
        "collider_translations": rng.normal(size=(f, c, 3)) * 0.05,
        "ms_per_frame": {"total": 1.0},
    }
    scene = {"name": "export-test", "head": {"mesh": "sphere", "radius": 0.1}, "colliders": COLLIDERS}
    params = Params()
    path = str(tmp_path_factory.mktemp("seq") / "sequence.h5")
    write_sequence(path, result, scene, params, result["positions"][0])
    return path, result, float(params.dt)


def validation_errors(stage):
    from pxr import UsdValidation

    registry = UsdValidation.ValidationRegistry()
    validators = registry.GetOrLoadAllValidators()
    errors = UsdValidation.ValidationContext(validators).Validate(stage)
    return len(validators), [str(e.GetMessage()) for e in errors]


def test_export_time_samples_transforms_and_validators(sequence, tmp_path):
    path, result, dt = sequence
    out = str(tmp_path / "anim.usdc")
    assert export_usd(path, out, every=2) == out
    stage = Usd.Stage.Open(out)
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0 and UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y
    assert stage.GetTimeCodesPerSecond() == pytest.approx(1 / dt) and stage.GetFramesPerSecond() == pytest.approx(1 / dt)
    assert stage.GetStartTimeCode() == 1 and stage.GetEndTimeCode() == 7  # frames 0, 2, 4, 6 → codes 1, 3, 5, 7
    hair = UsdGeom.BasisCurves(stage.GetPrimAtPath("/World/Hair"))
    assert hair.GetTypeAttr().Get() == "linear" and hair.GetWrapAttr().Get() == "nonperiodic"
    assert list(hair.GetCurveVertexCountsAttr().Get()) == [6] * 5
    assert list(hair.GetWidthsAttr().Get()) == [pytest.approx(7e-5)] and hair.GetWidthsInterpolation() == "constant"
    assert hair.GetPointsAttr().GetTimeSamples() == [1.0, 3.0, 5.0, 7.0]
    for k in (0, 2, 4, 6):
        tc = Usd.TimeCode(k + 1)
        pts = np.asarray(hair.GetPointsAttr().Get(tc))
        np.testing.assert_array_equal(pts, result["positions"][k].reshape(-1, 3))  # exact float32
        lo, hi = np.asarray(hair.GetExtentAttr().Get(tc))
        assert np.all(lo <= pts.min(0)) and np.all(hi >= pts.max(0))
        np.testing.assert_allclose(hi - pts.max(0), 3.5e-5, rtol=1e-3)  # half the width
    # head: the mesh in its frame, moved by the head pose at every sample
    head = UsdGeom.Mesh(stage.GetPrimAtPath("/World/Head"))
    local = np.asarray(head.GetPointsAttr().Get(), dtype=np.float64)
    np.testing.assert_allclose(np.linalg.norm(local, axis=1), 0.1, rtol=1e-6)  # the scene's sphere head
    for k in (0, 4):
        m = np.asarray(UsdGeom.Xformable(head).ComputeLocalToWorldTransform(Usd.TimeCode(k + 1)))
        world = local @ m[:3, :3] + m[3, :3]
        r, t = (result[key][k].astype(np.float32).astype(np.float64) for key in ("rotations", "translations"))
        np.testing.assert_allclose(world, local @ r.T + t, atol=1e-12)  # the file stores float32 poses
    # colliders: one Mesh each, transform = the recorded world pose
    kids = stage.GetPrimAtPath("/World/Colliders").GetChildren()
    assert [p.GetName() for p in kids] == ["sphere_0", "capsule_1", "plane_2", "hollow_sphere_3"]
    for c, prim in enumerate(kids):
        m = np.asarray(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(Usd.TimeCode(7)))
        np.testing.assert_array_equal(m[:3, :3].T, result["collider_rotations"][6, c].astype(np.float32))
        np.testing.assert_array_equal(m[3, :3], result["collider_translations"][6, c].astype(np.float32))
    count, errors = validation_errors(stage)
    assert count >= 30 and errors == [], errors


def test_collider_tessellations_lie_on_the_analytic_surfaces():
    from ams_torch.apps.scene.schema import make_collider

    for spec in COLLIDERS:
        mesh = collider_mesh(spec)
        pts = torch.as_tensor(np.asarray(mesh.vertices))
        sigma = make_collider(spec).distance(pts)
        assert sigma.abs().max() < 1e-9, (spec["type"], float(sigma.abs().max()))
        if spec["type"] != "plane":
            assert mesh.is_watertight and mesh.volume > 0, spec["type"]  # closed, outward
    quad = collider_mesh(COLLIDERS[2])
    assert np.allclose(quad.face_normals @ (np.array([0, 1, 0.2]) / np.linalg.norm([0, 1, 0.2])), 1)
    assert quad.area == pytest.approx(PLANE_SIZE ** 2)
    shell = collider_mesh({"type": "hollow_sphere", "radius": 0.2, "thickness": 0.02, "cut_height": None})
    assert shell.volume == pytest.approx(4 / 3 * np.pi * (0.21 ** 3 - 0.19 ** 3), rel=0.02)


def test_export_arrays_usda_per_point_widths_and_errors(tmp_path):
    rng = np.random.default_rng(3)
    x = rng.normal(size=(3, 4, 5, 3)).astype(np.float32)
    taper = np.linspace(8e-5, 2e-5, 5)
    out = export_usd_arrays(str(tmp_path / "a.usda"), x, 0.01, scene={"head": {"mesh": "none"}}, width=taper)
    stage = Usd.Stage.Open(out)
    assert not stage.GetPrimAtPath("/World/Head")  # head "none"
    hair = UsdGeom.BasisCurves(stage.GetPrimAtPath("/World/Hair"))
    assert hair.GetWidthsInterpolation() == "vertex"
    np.testing.assert_allclose(np.asarray(hair.GetWidthsAttr().Get()).reshape(4, 5), np.tile(taper, (4, 1)), rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(hair.GetPointsAttr().Get(Usd.TimeCode(2))), x[1].reshape(-1, 3))
    assert stage.GetTimeCodesPerSecond() == pytest.approx(100.0)
    assert validation_errors(stage)[1] == []
    assert not list(tmp_path.glob(".*tmp*"))  # written under a temporary name, then moved
    with pytest.raises(ValueError, match=r"positions must be \(F, S, N, 3\); got \(4, 5, 3\)"):
        export_usd_arrays(str(tmp_path / "b.usd"), x[0], 0.01)
    with pytest.raises(ValueError, match="every must be a positive integer; got 0"):
        export_usd_arrays(str(tmp_path / "b.usd"), x, 0.01, every=0)
    with pytest.raises(ValueError, match=r"width must be a float or broadcast to \(S, N\) = \(4, 5\)"):
        export_usd_arrays(str(tmp_path / "b.usd"), x, 0.01, width=np.ones(3))
    with pytest.raises(ValueError, match=r"rotations must have shape \(3, 3, 3\); got \(2, 3, 3\)"):
        export_usd_arrays(str(tmp_path / "b.usd"), x, 0.01, rotations=np.tile(np.eye(3), (2, 1, 1)))
    with pytest.raises(ValueError, match="scene has colliders but no collider_rotations"):
        export_usd_arrays(str(tmp_path / "b.usd"), x, 0.01, scene={"head": {"mesh": "none"}, "colliders": COLLIDERS})
    with pytest.raises(ValueError, match=r"must end in \.usd, \.usda or \.usdc"):
        export_usd_arrays(str(tmp_path / "b.abc"), x, 0.01)
    assert not (tmp_path / "b.usd").exists()
    with pytest.raises(FileNotFoundError, match="no such sequence file"):
        export_usd(str(tmp_path / "missing.h5"), str(tmp_path / "c.usd"))
    with h5py.File(tmp_path / "other.h5", "w") as f:
        f["x"] = np.zeros(3)
    with pytest.raises(ValueError, match=r"other.h5: no 'positions' dataset"):
        export_usd(str(tmp_path / "other.h5"), str(tmp_path / "c.usd"))


def test_export_of_a_real_simulation_with_the_default_head(tmp_path):
    """Frames from the simulator's public API, written by write_sequence, exported."""
    from ams_torch.geometry.pose import Pose
    from ams_torch.grooms.head import default_head
    from ams_torch.sim.simulator import Simulator

    rng = np.random.default_rng(4)
    rest = torch.as_tensor(np.cumsum(np.tile([0.0, -0.01, 0.0], (6, 8, 1)), 1) + rng.normal(size=(6, 1, 3)) * 0.02
                           + [0.0, 0.1, 0.0], dtype=torch.float32)
    params = Params()
    sim = Simulator(rest, params)
    state = sim.initial_state(Pose.identity())
    xs, rs, ts = [], [], []
    for k in range(3):
        pose = Pose.from_rotvec((0.0, 0.05 * (k + 1), 0.0), (0.0, 0.01 * (k + 1), 0.0))
        state = sim.step(state, pose)
        xs.append(state.x.detach().float().numpy())
        rs.append(pose.rotation.numpy())
        ts.append(pose.translation.numpy())
    result = {"positions": np.stack(xs), "rotations": np.stack(rs), "translations": np.stack(ts),
              "ms_per_frame": {"total": 0.0}}
    scene = {"name": "tiny", "head": {"mesh": "default", "subdivisions": 2}, "colliders": []}
    seq = write_sequence(str(tmp_path / "seq.h5"), result, scene, params, rest.numpy())
    out = export_usd(seq, str(tmp_path / "tiny.usd"))
    stage = Usd.Stage.Open(out)
    hair = UsdGeom.BasisCurves(stage.GetPrimAtPath("/World/Hair"))
    np.testing.assert_array_equal(np.asarray(hair.GetPointsAttr().Get(Usd.TimeCode(3))), xs[2].reshape(-1, 3))
    head = UsdGeom.Mesh(stage.GetPrimAtPath("/World/Head"))
    assert len(head.GetFaceVertexCountsAttr().Get()) == len(default_head(2).faces)
    m = np.asarray(UsdGeom.Xformable(head).ComputeLocalToWorldTransform(Usd.TimeCode(2)))
    np.testing.assert_allclose(m[:3, :3].T, rs[1], atol=1e-7)
    assert Gf.Vec3d(*m[3, :3]) == Gf.Vec3d(*ts[1].astype(np.float64))
    assert validation_errors(stage)[1] == []


def test_head_from_a_scene_file_path_with_import_keys(tmp_path):
    import trimesh

    from ams_torch.apps.export import head_mesh_for_scene

    box = trimesh.creation.box((20.0, 30.0, 10.0))  # centimetres, Z up
    box.export(tmp_path / "head.obj")
    head = {"mesh": str(tmp_path / "head.obj"), "scale": 0.01, "up_axis": "z",
            "transform": {"rotation": np.eye(3).tolist(), "translation": [0.0, 0.1, 0.0]}}  # as the schema stores it
    m = head_mesh_for_scene({"head": head})
    np.testing.assert_allclose(m.extents, [0.2, 0.1, 0.3], rtol=1e-12)
    np.testing.assert_allclose(m.bounds.mean(0), [0.0, 0.1, 0.0], atol=1e-12)
    assert head_mesh_for_scene({"head": {"mesh": "none"}}) is None
