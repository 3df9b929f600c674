"""The optional stages of a frame (SPEC §6, §8) and external forces: hair–solid collisions,
hair–hair interaction on a grid, wind. Pure functions of their inputs; the simulator composes
them (:mod:`ams_torch.sim.stepping`) and builds only those a scene enables.

Imports only :mod:`ams_torch.geometry`.
"""
from ams_torch.stages.collide import (CapsuleCollider, Collider, HollowSphereCollider, MeshCollider, PlaneCollider,
                                      SphereCollider)
from ams_torch.stages.hair_hair import HairHair
from ams_torch.stages.wind import Wind

__all__ = ["Collider", "SphereCollider", "HollowSphereCollider", "CapsuleCollider", "PlaneCollider", "MeshCollider",
           "HairHair", "Wind"]
