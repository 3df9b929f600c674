"""Hair–solid collisions (SPEC §8): collider shapes, their world poses per frame, the response.

- :mod:`~ams_torch.stages.collide.shapes`: :class:`SphereCollider`, :class:`HollowSphereCollider`,
  :class:`CapsuleCollider`, :class:`PlaneCollider` (exact σ) and :class:`MeshCollider` (an SDF grid
  of a triangle mesh, open meshes included).
- :mod:`~ams_torch.stages.collide.poses`: :func:`resolve_world_poses`.
- :mod:`~ams_torch.stages.collide.response`: :func:`collide` (the Coulomb response and push-out),
  :func:`collider_distances`.
"""
from ams_torch.stages.collide.poses import resolve_world_poses
from ams_torch.stages.collide.response import collide, collider_distances, contact_response
from ams_torch.stages.collide.shapes import (DEFAULT_FRICTION, CapsuleCollider, Collider, HollowSphereCollider,
                                             MeshCollider, PlaneCollider, SphereCollider)

__all__ = ["Collider", "SphereCollider", "HollowSphereCollider", "CapsuleCollider", "PlaneCollider", "MeshCollider",
           "DEFAULT_FRICTION", "resolve_world_poses", "collide", "collider_distances", "contact_response"]
