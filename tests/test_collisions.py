"""Hair–solid collisions (SPEC §8): analytic σ, the Coulomb response, poses, mesh colliders."""
import math

import numpy as np
import pytest
import torch
import trimesh

from ams_torch.stages.collide import (
    CapsuleCollider,
    HollowSphereCollider,
    MeshCollider,
    PlaneCollider,
    SphereCollider,
    collide,
    collider_distances,
    resolve_world_poses,
)
from ams_torch.grooms.head import default_head
from ams_torch.geometry.pose import Pose, axis_angle_to_matrix

DT = 0.02


@pytest.fixture(scope="session")
def head_collider(head_sdf):
    pytest.importorskip("point_cloud_utils")
    return MeshCollider(head_sdf, friction=0.5)


def analytic_colliders(mu=0.3):
    return [
        SphereCollider((0.01, 0.02, -0.01), 0.1, friction=mu),
        CapsuleCollider((-0.05, 0.0, 0.0), (0.08, 0.03, 0.01), 0.04, friction=mu),
        PlaneCollider((0.0, -0.03, 0.0), (0.2, 1.0, -0.1), friction=mu),
        HollowSphereCollider((0.0, 0.0, 0.0), 0.12, 0.04, cut_height=0.05, axis=(0.3, 1.0, 0.0), friction=mu),
    ]


def random_pose(gen, dtype=torch.float64, moving=True):
    rv = torch.randn(3, generator=gen, dtype=dtype)
    t = 0.05 * torch.randn(3, generator=gen, dtype=dtype)
    lin = torch.randn(3, generator=gen, dtype=dtype) if moving else None
    ang = 5 * torch.randn(3, generator=gen, dtype=dtype) if moving else None
    return Pose(axis_angle_to_matrix(rv), t, lin, ang)


# ---------------------------------------------------------------------------------------
# analytic signed distances
# ---------------------------------------------------------------------------------------
def test_analytic_sdf_values_and_normals():
    gen = torch.Generator().manual_seed(0)
    p = 0.2 * torch.randn(1000, 3, generator=gen, dtype=torch.float64)
    sph, cap, pla, _ = analytic_colliders()
    c = torch.tensor([0.01, 0.02, -0.01], dtype=torch.float64)
    torch.testing.assert_close(sph.distance(p), (p - c).norm(dim=-1) - 0.1)
    # capsule against a dense sampling of its axis segment
    a = torch.tensor([-0.05, 0.0, 0.0], dtype=torch.float64)
    b = torch.tensor([0.08, 0.03, 0.01], dtype=torch.float64)
    seg = a + torch.linspace(0, 1, 20001, dtype=torch.float64)[:, None] * (b - a)  # 7 µm apart
    ref = torch.cdist(p, seg).min(-1).values - 0.04
    torch.testing.assert_close(cap.distance(p), ref, atol=4e-6, rtol=0)
    nrm = torch.tensor([0.2, 1.0, -0.1], dtype=torch.float64)
    torch.testing.assert_close(pla.distance(p), (p - torch.tensor([0.0, -0.03, 0.0], dtype=torch.float64)) @ nrm / nrm.norm())
    # every normal is the unit gradient of σ (central differences, away from kinks)
    for col in analytic_colliders():
        sigma, n = col.distance_and_normal(p)
        torch.testing.assert_close(n.norm(dim=-1), torch.ones(len(p), dtype=torch.float64))
        eps = 1e-6
        grad = torch.stack([(col.distance(p + eps * e) - col.distance(p - eps * e)) / (2 * eps)
                            for e in torch.eye(3, dtype=torch.float64)], -1)
        smooth = (grad.norm(dim=-1) - 1).abs() < 1e-4  # drop the rare samples sitting on a kink
        assert smooth.float().mean() > 0.99
        torch.testing.assert_close(n[smooth], grad[smooth], atol=1e-5, rtol=0)


def test_hollow_sphere_against_brute_force():
    # The cut shell is the set of points within thickness/2 of a spherical arc (revolved):
    # σ = distance to the arc − thickness/2. Brute force over a dense arc in the (ρ, y) plane.
    r, th, h = 0.12, 0.04, 0.05
    col = HollowSphereCollider((0.0, 0.0, 0.0), r, th, cut_height=h, axis=(0.0, 1.0, 0.0))
    gen = torch.Generator().manual_seed(1)
    p = 0.2 * torch.randn(1000, 3, generator=gen, dtype=torch.float64)
    phi_max = math.atan2(math.sqrt(r * r - h * h), -h)  # angle from −y to the rim
    phi = torch.linspace(0, phi_max, 50001, dtype=torch.float64)  # 5 µm apart
    arc = torch.stack((r * torch.sin(phi), -r * torch.cos(phi)), -1)
    q = torch.stack((p[:, [0, 2]].norm(dim=-1), p[:, 1]), -1)
    ref = torch.cdist(q, arc).min(-1).values - th / 2
    torch.testing.assert_close(col.distance(p), ref, atol=3e-6, rtol=0)
    # the opening is open, the wall is solid, the inside of the ball is free space
    pts = torch.tensor([[0.0, 0.119, 0.0], [0.0, -0.12, 0.0], [0.0, 0.0, 0.0], [0.12, 0.0, 0.0]], dtype=torch.float64)
    s = col.distance(pts)
    assert s[0] > 0 and s[1] < 0 and s[2] > 0 and s[3] < 0
    # the axis argument turns the opening
    turned = HollowSphereCollider((0.0, 0.0, 0.0), r, th, cut_height=h, axis=(1.0, 0.0, 0.0))
    swapped = p[:, [1, 0, 2]]  # (x, y, z) → (y, x, z): maps the +y opening onto +x
    torch.testing.assert_close(turned.distance(swapped), col.distance(p), atol=1e-12, rtol=0)


# ---------------------------------------------------------------------------------------
# the response
# ---------------------------------------------------------------------------------------
def plane_case(v, mu, depth=1e-3, dt=DT, pose=None):
    plane = PlaneCollider((0.0, 0.0, 0.0), (0.0, 1.0, 0.0), friction=mu)
    x = torch.tensor([[[0.3, -depth, 0.1]]], dtype=torch.float64)
    v = torch.tensor([[v]], dtype=torch.float64)
    return collide(x, v, dt, [plane], [pose])


def test_friction_zero_keeps_tangential_velocity():
    x, v = plane_case([1.0, -2.0, 0.5], mu=0.0)
    torch.testing.assert_close(v[0, 0], torch.tensor([1.0, 0.0, 0.5], dtype=torch.float64))
    assert x[0, 0, 1] >= 0  # on or above the surface


def test_coulomb_friction_scales_and_stops_tangential_velocity():
    # Δv_N = 2 m/s removed; |v_T| = 1 m/s: μ = 0.25 keeps 1 − 0.25·2/1 = 0.5 of v_T
    _, v = plane_case([1.0, -2.0, 0.0], mu=0.25)
    torch.testing.assert_close(v[0, 0], torch.tensor([0.5, 0.0, 0.0], dtype=torch.float64))
    _, v = plane_case([1.0, -2.0, 0.0], mu=10.0)
    torch.testing.assert_close(v[0, 0], torch.zeros(3, dtype=torch.float64))


def test_separating_particle_keeps_its_velocity_and_static_friction_holds():
    # inside but already moving out: nothing is removed, no friction impulse
    x, v = plane_case([1.0, 0.3, 0.0], mu=10.0)
    torch.testing.assert_close(v[0, 0], torch.tensor([1.0, 0.3, 0.0], dtype=torch.float64))
    # sticking: the position is made consistent with v' (x + Δt (v' − v)), no creep
    x, v = plane_case([1.0, -1.0, 0.0], mu=10.0, depth=1e-3, dt=0.01)
    torch.testing.assert_close(x[0, 0], torch.tensor([0.3 - 0.01, -1e-3 + 0.01, 0.1], dtype=torch.float64))
    # dt = 0: pure projection onto the surface
    x, v = plane_case([1.0, -1.0, 0.0], mu=0.0, depth=2e-3, dt=0.0)
    torch.testing.assert_close(x[0, 0], torch.tensor([0.3, 0.0, 0.1], dtype=torch.float64))


def test_moving_plane_pushes_and_drags():
    lift = Pose(torch.eye(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64),
                torch.tensor([0.0, 2.0, 0.0], dtype=torch.float64), torch.zeros(3, dtype=torch.float64))
    _, v = plane_case([0.0, 0.0, 0.0], mu=0.0, pose=lift)
    torch.testing.assert_close(v[0, 0], torch.tensor([0.0, 2.0, 0.0], dtype=torch.float64))
    conveyor = Pose(torch.eye(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64),
                    torch.tensor([3.0, 0.0, 0.0], dtype=torch.float64), torch.zeros(3, dtype=torch.float64))
    _, v = plane_case([0.0, -1.0, 0.0], mu=10.0, pose=conveyor)  # pressed on a moving belt: dragged along
    torch.testing.assert_close(v[0, 0], torch.tensor([3.0, 0.0, 0.0], dtype=torch.float64))
    _, v = plane_case([0.0, -1.0, 0.0], mu=0.0, pose=conveyor)  # frictionless belt: stays put
    torch.testing.assert_close(v[0, 0], torch.zeros(3, dtype=torch.float64))


def test_spinning_sphere_drags_with_its_surface_velocity():
    omega = torch.tensor([0.0, 10.0, 0.0], dtype=torch.float64)
    centre = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    pose = Pose(axis_angle_to_matrix(torch.tensor([0.0, 0.7, 0.0], dtype=torch.float64)), centre,
                torch.zeros(3, dtype=torch.float64), omega)
    ball = SphereCollider((0.0, 0.0, 0.0), 0.1, friction=100.0)
    x = (centre + torch.tensor([0.0, 0.0, 0.099], dtype=torch.float64))[None, None]
    v = torch.tensor([[[0.0, 0.0, -0.5]]], dtype=torch.float64)
    x2, v2 = collide(x, v, DT, [ball], [pose])
    torch.testing.assert_close(v2[0, 0], torch.linalg.cross(omega, x[0, 0] - centre))
    assert collider_distances(x2, [ball], [pose]).min() >= -1e-12


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_no_penetration_and_no_inward_velocity_analytic(dtype, device):
    gen = torch.Generator().manual_seed(3)
    S, N = 400, 8
    free = (torch.arange(N) >= 2).to(device)
    for col in analytic_colliders(mu=0.4):
        col = col.to(device)
        pose = random_pose(gen)
        x = (pose.translation + 0.15 * torch.randn(S, N, 3, generator=gen, dtype=torch.float64)).to(device, dtype)
        v = torch.randn(S, N, 3, generator=gen, dtype=torch.float64).to(device, dtype)
        pose_d = pose.to(device=device, dtype=dtype)
        before = collider_distances(x, [col], [pose_d])[0]
        assert (before[:, 2:] < 0).sum() > 20, type(col).__name__  # the test really has contacts
        x2, v2 = collide(x, v, DT, [col], [pose_d], free=free)
        after = collider_distances(x2, [col], [pose_d])[0]
        assert after[:, 2:].min() >= -1e-4, (type(col).__name__, after.min())  # 0.1 mm
        # pinned particles are never touched, untouched particles keep their state bit for bit
        assert torch.equal(x2[:, :2], x[:, :2]) and torch.equal(v2[:, :2], v[:, :2])
        outside = before >= 0
        assert torch.equal(x2[outside], x[outside]) and torch.equal(v2[outside], v[outside])
        # in contact: normal relative velocity (normal and v_c at the contact point) not inward
        hit = (before < 0) & free
        local = pose_d.to_local(x[hit][None])[0]
        _, n_local = col.distance_and_normal(local)
        n = pose_d.rotate(n_local[None])[0]
        vc = pose_d.velocity_at(x[hit][None])[0]
        vn_after = ((v2[hit] - vc) * n).sum(-1)
        assert vn_after.min() >= -1e-5 * (1 + v2[hit].norm(dim=-1).max())
        # and the tangential relative speed never grows
        vrel0, vrel1 = v[hit] - vc, v2[hit] - vc
        vt0 = vrel0 - (vrel0 * n).sum(-1, keepdim=True) * n
        vt1 = vrel1 - (vrel1 * n).sum(-1, keepdim=True) * n
        assert (vt1.norm(dim=-1) <= vt0.norm(dim=-1) * (1 + 1e-5) + 1e-6).all()


def test_dense_response_touches_only_particles_inside(head_collider):
    """The response is a dense masked update: particles outside every collider come back
    bit-identical, particles inside are moved out, for batched poses too."""
    gen = torch.Generator().manual_seed(4)
    poses = [random_pose(gen, dtype=torch.float32) for _ in range(2)]
    batched = Pose(torch.stack([p.rotation for p in poses]), torch.stack([p.translation for p in poses]),
                   torch.stack([p.linear_velocity for p in poses]), torch.stack([p.angular_velocity for p in poses]))
    for col in analytic_colliders() + [head_collider]:
        x = batched.translation[:, None, None] + 0.15 * torch.randn(2, 1, 3000, 3, generator=gen)  # in and out
        v = torch.randn(x.shape, generator=gen)
        inside = collider_distances(x, [col], [batched])[0] < 0
        assert inside.sum() > 20 and (~inside).sum() > 20
        x2, v2 = collide(x, v, DT, [col], [batched])
        assert torch.equal(x2[~inside], x[~inside]) and torch.equal(v2[~inside], v[~inside]), type(col).__name__
        assert (x2[inside] != x[inside]).any(-1).all(), type(col).__name__


def test_rotated_pose_matches_world_space_formula():
    # a capsule along local x, posed in the world by a rotation and translation: σ in the world
    # must equal the capsule's σ with its end points carried to the world
    gen = torch.Generator().manual_seed(5)
    cap = CapsuleCollider((-0.05, 0.0, 0.0), (0.05, 0.0, 0.0), 0.02, friction=0.0)
    pose = random_pose(gen, moving=False)
    a = pose.to_world(cap.a[None])[0]
    b = pose.to_world(cap.b[None])[0]
    world_cap = CapsuleCollider(a, b, 0.02, friction=0.0)
    x = pose.translation + 0.06 * torch.randn(1, 500, 3, generator=gen, dtype=torch.float64)
    torch.testing.assert_close(collider_distances(x, [cap], [pose]), collider_distances(x, [world_cap], [None]))
    v = torch.randn(1, 500, 3, generator=gen, dtype=torch.float64)
    x1, v1 = collide(x, v, DT, [cap], [pose])
    x2, v2 = collide(x, v, DT, [world_cap], [None])
    torch.testing.assert_close(x1, x2)
    torch.testing.assert_close(v1, v2)


def test_batched_poses_match_one_at_a_time():
    gen = torch.Generator().manual_seed(6)
    poses = [random_pose(gen) for _ in range(3)]
    batched = Pose(*(torch.stack([getattr(p, f) for p in poses]) for f in
                     ("rotation", "translation", "linear_velocity", "angular_velocity")))
    ball = SphereCollider((0.0, 0.0, 0.0), 0.08, friction=0.7)
    x = 0.1 * torch.randn(3, 50, 6, 3, generator=gen, dtype=torch.float64) + batched.translation[:, None, None]
    v = torch.randn(3, 50, 6, 3, generator=gen, dtype=torch.float64)
    xb, vb = collide(x, v, DT, [ball], [batched])
    for i in range(3):
        xi, vi = collide(x[i], v[i], DT, [ball], [poses[i]])
        torch.testing.assert_close(xb[i], xi)
        torch.testing.assert_close(vb[i], vi)
    assert not torch.equal(xb, x)
    # pose batch dims are a prefix of the particles' batch dims: (3,) poses for (3, 2) scenes
    x2 = x[:, None].expand(3, 2, 50, 6, 3)
    xc, vc = collide(x2, v[:, None].expand_as(x2), DT, [ball], [batched])
    torch.testing.assert_close(xc, xb[:, None].expand_as(xc))
    torch.testing.assert_close(vc, vb[:, None].expand_as(vc))


def test_no_colliders_is_a_no_op_and_gradients_flow():
    g = torch.Generator().manual_seed(0)  # seeded: some particles start inside the ball
    x = torch.randn(4, 5, 3, generator=g).requires_grad_()
    v = torch.randn(4, 5, 3, generator=g)
    assert (x.detach().norm(dim=-1) < 1).any()
    x2, v2 = collide(x, v, DT, [], [])
    assert x2 is x and v2 is v
    ball = SphereCollider((0.0, 0.0, 0.0), 1.0, friction=0.5)
    x3, v3 = collide(x, v, DT, [ball], [None])
    (x3.sum() + v3.sum()).backward()
    assert x.grad is not None and torch.isfinite(x.grad).all()
    assert (x.grad != 1).any()  # the response depends on where the contact is


def test_resolve_world_poses_composes_with_the_head():
    gen = torch.Generator().manual_seed(8)
    head = random_pose(gen)
    rel = random_pose(gen)
    attached = SphereCollider((0.02, 0.0, 0.0), 0.03, pose=rel, follow_head=True)
    free = SphereCollider((0.0, 0.0, 0.0), 0.03, pose=rel, follow_head=False)
    default = MeshCollider(trimesh.creation.icosphere(radius=0.05))  # follow_head by default; unbuilt
    world = resolve_world_poses([attached, free, default], head)
    assert default._grid is None  # resolving poses builds nothing
    # a local point of the collider: world position and velocity by finite differences in time
    p = torch.tensor([[0.01, -0.02, 0.03]], dtype=torch.float64)

    def at(t):
        rh = axis_angle_to_matrix(head.angular_velocity * t) @ head.rotation
        th = head.translation + head.linear_velocity * t
        rr = axis_angle_to_matrix(rel.angular_velocity * t) @ rel.rotation
        tr = rel.translation + rel.linear_velocity * t
        return (rh @ (rr @ p[0] + tr)) + th

    eps = 1e-6
    x0 = at(0.0)
    torch.testing.assert_close(world[0].to_world(p)[0], x0)
    vel_fd = (at(eps) - at(-eps)) / (2 * eps)
    torch.testing.assert_close(world[0].velocity_at(x0[None])[0], vel_fd, atol=1e-6, rtol=1e-6)
    for name in ("rotation", "translation", "linear_velocity", "angular_velocity"):  # world colliders ignore the head
        assert torch.equal(getattr(world[1], name), getattr(rel, name))
    torch.testing.assert_close(world[2].rotation, head.rotation)
    torch.testing.assert_close(world[2].translation, head.translation)
    # overrides: sequence or mapping, replacing collider.pose in its own frame
    override = Pose.identity(dtype=torch.float64)
    by_list = resolve_world_poses([attached, free], head, [None, override])
    by_dict = resolve_world_poses([attached, free], head, {1: override})
    assert by_list[1] is override and by_dict[1] is override
    torch.testing.assert_close(by_dict[0].translation, world[0].translation)
    with pytest.raises(ValueError):
        resolve_world_poses([attached, free], head, [None])
    # static head and static collider: zero velocity
    still = resolve_world_poses([SphereCollider(follow_head=True, pose=Pose(torch.eye(3), torch.zeros(3)))],
                                Pose(torch.eye(3), torch.zeros(3)))
    torch.testing.assert_close(still[0].velocity_at(torch.ones(1, 3)), torch.zeros(1, 3))


# ---------------------------------------------------------------------------------------
# the head mesh as a collider
# ---------------------------------------------------------------------------------------
def test_mesh_collider_no_penetration(head_collider):
    mesh = default_head()
    gen = torch.Generator().manual_seed(9)
    rng = np.random.default_rng(9)
    pts, fid = trimesh.sample.sample_surface(mesh, 4000, seed=9)
    pts = pts + mesh.face_normals[fid] * rng.uniform(-0.02, 0.01, (4000, 1))
    pose = random_pose(gen)
    pose32 = pose.to(dtype=torch.float32)
    x = pose32.to_world(torch.as_tensor(pts, dtype=torch.float32)[None]).reshape(500, 8, 3)
    v = torch.randn(500, 8, 3, generator=gen).float()
    before = collider_distances(x, [head_collider], [pose32])[0]
    assert (before < 0).sum() > 1000
    x2, v2 = collide(x, v, DT, [head_collider], [pose32])
    after = collider_distances(x2, [head_collider], [pose32])[0]
    h = head_collider.sdf.voxel_size
    assert after.min() >= -0.25 * h, after.min() / h
    # checked against the exact mesh too (grid error ≤ half a voxel near the surface)
    pcu = pytest.importorskip("point_cloud_utils")
    local = pose.to_local(x2.double().reshape(1, -1, 3))[0].numpy()
    d, _, _ = pcu.closest_points_on_mesh(local, np.asarray(mesh.vertices), np.asarray(mesh.faces))
    inside = pcu.triangle_soup_fast_winding_number(np.asarray(mesh.vertices), np.asarray(mesh.faces), local) > 0.5
    assert (d[inside] <= 0.75 * h).all()
    # the normal relative velocity is not inward after the response
    hit = before < 0
    _, n_local = head_collider.distance_and_normal(pose32.to_local(x[hit][None])[0])
    n = pose32.rotate(n_local[None])[0]
    vc = pose32.velocity_at(x[hit][None])[0]
    assert (((v2[hit] - vc) * n).sum(-1) >= -1e-4).all()


# ---------------------------------------------------------------------------------------
# end to end, through the simulator
# ---------------------------------------------------------------------------------------
def test_swept_sphere_pushes_hair_aside():
    from ams_torch.sim.params import Params
    from ams_torch.sim.simulator import Simulator
    from ams_torch.testing import sphere_groom

    rest = sphere_groom(300, 16, radius=0.1, length=0.25, seed=2)
    params = Params()
    head = SphereCollider((0.0, 0.0, 0.0), 0.1, friction=0.5, follow_head=True)
    ball = SphereCollider((0.0, 0.0, 0.0), 0.04, friction=0.2)
    sim = Simulator(rest, params, colliders=[head, ball])
    still = Simulator(rest, params, colliders=[head])
    state, ref = sim.initial_state(), still.initial_state()
    speed = 1.5  # m/s along +x, through the hair hanging at the side of the head
    free = ~sim.model.pinned
    frames = 30
    worst, moved = 0.0, 0.0
    for k in range(frames):
        t = (k + 1) * params.dt
        centre = torch.tensor([-0.25 + speed * t, -0.12, 0.0])
        ball_pose = Pose(torch.eye(3), centre, torch.tensor([speed, 0.0, 0.0]), torch.zeros(3))
        state = sim.step(state, None, collider_poses=[None, ball_pose])
        ref = still.step(ref, None)
        d = collider_distances(state.x, [head, ball], resolve_world_poses([head, ball], None, [None, ball_pose]))
        worst = min(worst, float(d[..., free].min()))
        moved = max(moved, float((state.x - ref.x).norm(dim=-1).max()))
    assert worst >= -1e-4, worst  # no free particle inside either sphere after any frame
    assert moved > 0.03, moved  # the sweep really pushed strands aside (by > 3 cm)
    assert torch.isfinite(state.x).all()


def test_spinning_head_leaves_no_particle_inside(head_collider, device):
    from ams_torch.grooms.head import hanging_groom
    from ams_torch.sim.params import Params
    from ams_torch.sim.simulator import Simulator

    grid = head_collider.sdf
    rest = hanging_groom(default_head(), 1000, 32, 0.2, sdf=grid, seed=0)
    params = Params()
    sim = Simulator(rest, params, colliders=[head_collider], device=device)
    head_collider = sim.colliders[0]  # the simulator's copy, on its device
    state = sim.initial_state()
    omega = 2 * math.pi * 5.0  # 5 rev/s about the vertical axis, for 1 s
    free = ~sim.model.pinned
    frames = int(round(1.0 / params.dt))
    worst, travelled = 0.0, 0.0
    for k in range(frames):
        t = (k + 1) * params.dt
        pose = Pose.from_rotvec([0.0, omega * t, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, omega, 0.0],
                                device=device)
        prev = state.x
        state = sim.step(state, pose)
        d = collider_distances(state.x, [head_collider], resolve_world_poses([head_collider], pose))[0]
        worst = min(worst, float(d[free].min()))
        travelled += float((state.x - prev).norm(dim=-1).mean())
    assert worst >= -0.25 * grid.voxel_size, worst / grid.voxel_size
    assert travelled > 0.5  # metres: the hair really whirled around with the head
    assert torch.isfinite(state.x).all()


def test_contact_does_not_leave_stretched_edges(head_collider):
    """The length restore after the collision response (Params.collision_inextensibility) keeps
    edges near their rest length under fast head contact, without letting hair back inside."""
    from ams_torch.sim.inextensibility import max_stretch
    from ams_torch.grooms.head import hanging_groom
    from ams_torch.sim.params import Params
    from ams_torch.sim.simulator import Simulator
    from ams_torch.apps.motion import Shake

    grid = head_collider.sdf
    rest = hanging_groom(default_head(), 200, 24, 0.25, sdf=grid, seed=1)
    result = {}
    for rounds in (0, 1, 2):
        sim = Simulator(rest, Params(collision_inextensibility=rounds), colliders=[head_collider])
        state = sim.initial_state()
        free = ~sim.model.pinned
        stretch, worst = 0.0, 0.0
        for pose in Shake(amplitude=1.2, frequency=2.0).poses(40, sim.params.dt):
            state = sim.step(state, pose)
            stretch = max(stretch, float(max_stretch(state.x, sim.model.edge_rest_length).max()))
            d = collider_distances(state.x, [head_collider], resolve_world_poses([head_collider], pose))[0]
            worst = min(worst, float(d[free].min()))
        result[rounds] = stretch
        assert worst >= -0.25 * grid.voxel_size, (rounds, worst / grid.voxel_size)
    print(f"\n[collisions] largest edge stretch under contact: no restore {result[0]:.3g}, "
          f"1 round {result[1]:.3g}, 2 rounds {result[2]:.3g}")
    assert result[0] > 0.05  # contact response alone stretches the edges it touches
    assert result[1] < 0.25 * result[0] and result[2] <= result[1] + 1e-6
    with pytest.raises(ValueError, match="collision_inextensibility"):
        Params(collision_inextensibility=-1)


@pytest.mark.parametrize("kind", ["sphere", "mesh", "all"])
def test_compacted_response_equals_the_masked_one(kind, monkeypatch):
    """Eager on the CPU the response runs on the inside particles only (response._compacts); the
    result is the masked dense form's for one scene and for three sharing one pose: the same
    operations per particle, so equal up to the last bit of a few values (ATen rounds the same
    operation by its vectorised loop or its scalar tail, which the gathered rows' length moves)."""
    import ams_torch.stages.collide.response as response
    from native_cases import make_case

    from ams_torch.stages.collide import collide, resolve_world_poses

    sim, x, v, head, _ = make_case(kind, scenes=None, strands=15)
    xb, vb = torch.stack([x, x + 0.003, x - 0.002]), torch.stack([v, 0.5 * v, -v])
    world = resolve_world_poses(sim.colliders, head, None)
    free = ~sim.model.pinned
    for xs, vs in ((x, v), (xb, vb)):
        assert response._compacts(xs.reshape(-1, 1, 3), world[0].rotation.reshape(1, 3, 3))
        got = collide(xs, vs, 1 / 60, list(sim.colliders), world, free=free)
        with monkeypatch.context() as m:
            m.setattr(response, "_compacts", lambda *a: False)
            want = collide(xs, vs, 1 / 60, list(sim.colliders), world, free=free)
        assert not torch.equal(want[1], vs)  # some particle is in contact
        for a, b in zip(got, want):
            assert float((a - b).abs().max()) <= 4 * torch.finfo(a.dtype).eps * float(b.abs().max())
