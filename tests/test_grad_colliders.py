"""Gradients of rollouts through contact, against central finite differences (float64).

Every collider kind (mesh, sphere, hollow sphere, capsule, plane), each with friction, and the
hair–hair grid: a few frames of a small groom shaken against the collider, a scalar loss of the
final positions and velocities, and its directional derivative along random directions of
(integrity rate, drag, friction, x₀, v₀, head translation, collider translation) by autograd
against (L(θ + h d) − L(θ − h d)) / 2h. Plus the mesh SDF's normal, whose autograd gradient was
exactly zero inside the grid box (``outside / max(|outside|, 1e-30)`` back-propagated 1e30 × an
exact zero that cancelled the grid's own gradient: rollouts with head contact were 0.1–1.2 % wrong).
"""
import pytest
import torch

import ams_torch as at
from ams_torch.geometry.pose import Pose
from ams_torch.stages import CapsuleCollider, HollowSphereCollider, PlaneCollider, SphereCollider
from ams_torch.stages.collide import MeshCollider
from ams_torch.apps.motion import Shake

from ams_torch.testing import sphere_groom

F64 = torch.float64
FRAMES = 4


def _icosphere_collider(resolution: int = 24) -> MeshCollider:
    trimesh = pytest.importorskip("trimesh")
    return MeshCollider(trimesh.creation.icosphere(3, radius=0.1), resolution=resolution)


def test_sdf_normal_gradient_matches_finite_differences():
    """distance_and_normal's σ and n: autograd Jacobian against central differences at points inside
    the grid box (near the surface, inside and outside the solid) and outside the box."""
    grid = _icosphere_collider().double().sdf
    pts = torch.tensor([[0.02, 0.09, 0.03], [0.0, 0.0, 0.105], [-0.07, 0.05, 0.04], [0.0, 0.3, 0.05]], dtype=F64)
    assert bool((grid.origin < pts[:3]).all() & (pts[:3] < grid.upper).all())
    assert not bool(((grid.origin < pts[3]) & (pts[3] < grid.upper)).all())
    for p in pts:
        jac = torch.autograd.functional.jacobian(lambda q: torch.cat(grid.distance_and_normal(q[None])
                                                                     [0][:, None].unbind(-1) +
                                                                     (grid.distance_and_normal(q[None])[1][0],)), p)
        h = 1e-6
        fd = torch.stack([(torch.cat((grid.distance_and_normal((p + h * e)[None])[0],
                                      grid.distance_and_normal((p + h * e)[None])[1][0])) -
                           torch.cat((grid.distance_and_normal((p - h * e)[None])[0],
                                      grid.distance_and_normal((p - h * e)[None])[1][0]))) / (2 * h)
                          for e in torch.eye(3, dtype=F64)], -1)
        assert float(fd[1:].abs().max()) > 0.1  # the normal turns: not a vacuous check
        torch.testing.assert_close(jac, fd, rtol=1e-5, atol=1e-6)


def _scene(kind: str):
    """(collider list, HairHair or None) of each case; every collider has friction μ = 0.5 and is
    touched by the shaken groom in the first frames."""
    if kind == "mesh":
        return [_icosphere_collider()], None
    if kind == "sphere":
        return [SphereCollider(radius=0.1, follow_head=True)], None
    if kind == "hollow_sphere":  # the groom inside a shell open at the top: the inner wall
        return [HollowSphereCollider(radius=0.14, thickness=0.03, cut_height=0.06, follow_head=True)], None
    if kind == "capsule":
        return [CapsuleCollider(a=(0.0, -0.2, -0.1), b=(0.0, 0.1, -0.1), radius=0.04)], None
    if kind == "plane":
        return [PlaneCollider(point=(0.0, -0.04, 0.0), normal=(0.2, 1.0, 0.1))], None
    if kind == "sphere_hair_hair":
        return [SphereCollider(radius=0.1, follow_head=True)], at.HairHair(resolution=8, pressure_iterations=10)
    raise ValueError(kind)


class _Rollout:
    """A rollout of FRAMES frames of a 6 × 8 sphere groom (float64, torch definition) as a function of
    its leaves: the learnable integrity rate and drag, the collider's friction μ, offsets of x₀ and
    v₀, and shifts of the head and collider translations (all zero but μ = 0.5); a scalar loss of
    the final x and v."""

    def __init__(self, kind: str):
        self.rest = sphere_groom(6, 8, length=0.12, seed=1, dtype=F64)
        colliders, hair_hair = _scene(kind)
        self.sim = at.Simulator(self.rest, at.Params(), dtype=F64, colliders=colliders, hair_hair=hair_hair,
                                learnable=("integrity_rate", "drag"), backend="torch")
        self.free_sim = at.Simulator(self.rest, at.Params(), dtype=F64, hair_hair=hair_hair, backend="torch")
        self.poses = Shake(amplitude=0.8, frequency=2.0, translation=(0.02, 0.03, 0.0)).poses(FRAMES, 1 / 60, dtype=F64)
        g = torch.Generator().manual_seed(7)
        self.wx = torch.randn(self.rest.shape, generator=g, dtype=F64)
        self.wv = torch.randn(self.rest.shape, generator=g, dtype=F64)
        self.collider = self.sim.model.colliders[0]
        self.collider.friction = torch.tensor(0.5, dtype=F64, requires_grad=True)
        zeros = lambda *shape: torch.zeros(shape, dtype=F64, requires_grad=True)  # noqa: E731
        self.dx, self.dv, self.dh, self.dc = zeros(*self.rest.shape), zeros(*self.rest.shape), zeros(3), zeros(3)
        model = self.sim.model
        self.leaves = [model.integrity_rate, model.drag, self.collider.friction, self.dx, self.dv, self.dh, self.dc]
        self.scales = [100.0, 1.5, 0.5, 1e-3, 1e-2, 1e-3, 1e-3]  # a unit step of each: ×2, ×2, ×2, 1 mm, 1 cm/s, 1 mm, 1 mm

    def __call__(self, colliders: bool = True) -> torch.Tensor:
        sim = self.sim if colliders else self.free_sim
        s = sim.initial_state()
        s = s.replace(x=s.x + self.dx, v=s.v + self.dv)
        shift = Pose(torch.eye(3, dtype=F64), self.dc)
        for pose in self.poses:
            moved = Pose(pose.rotation, pose.translation + self.dh, pose.linear_velocity, pose.angular_velocity,
                         check=False)
            s = sim.step(s, moved, collider_poses=[shift] if colliders else None)
        return (self.wx * s.x).sum() + 1e-2 * (self.wv * s.v).sum()


def directional_errors(f: _Rollout, directions: int = 2, h: float = 1e-6, seed: int = 0):
    """[(autograd, central difference)] of f's derivative along ``directions`` random directions of
    its leaves (each scaled by its unit step), and the autograd gradients."""
    grads = torch.autograd.grad(f(), f.leaves)
    g = torch.Generator().manual_seed(seed)
    out = []
    for _ in range(directions):
        d = [torch.randn(t.shape, generator=g, dtype=F64) * s for t, s in zip(f.leaves, f.scales)]
        ad = sum(float((a * b).sum()) for a, b in zip(grads, d))
        vals = []
        with torch.no_grad():
            for sign in (1.0, -1.0):
                for t, dt in zip(f.leaves, d):
                    t.add_(sign * h * dt)
                vals.append(float(f()))
                for t, dt in zip(f.leaves, d):
                    t.sub_(sign * h * dt)
        out.append((ad, (vals[0] - vals[1]) / (2 * h)))
    return out, grads


@pytest.mark.parametrize("kind", ["mesh", "sphere", "hollow_sphere", "capsule", "plane", "sphere_hair_hair"])
def test_rollout_gradient_through_contact_matches_finite_differences(kind):
    f = _Rollout(kind)
    with torch.no_grad():  # the collider is touched: the rollout differs from one without it
        assert float((f() - f(colliders=False)).abs()) > 1e-4
    rows, grads = directional_errors(f)
    for ad, fd in rows:
        assert abs(ad) > 1e-3, rows
        assert abs(ad - fd) <= 1e-6 * max(abs(ad), abs(fd)), rows
    # every leaf reaches the loss (friction through the sliding contacts, the collider's pose)
    assert all(float(gr.abs().max()) > 0 for gr in grads), [float(gr.abs().max()) for gr in grads]
