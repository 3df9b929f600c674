"""``collision``: the groom-agnostic residual of ``agnostic`` with collision inputs and a
penetration loss.

Inputs added per vertex of the skinned strand (:func:`~baselines.learned.features.sdf_inputs`):
the signed distance to the nearest collider (the head, when it collides, and the scene's
colliders, at their poses of the frame), clamped to ±``reach`` and divided by it, and that
collider's outward normal in the head frame (zero farther than ``reach``). The loss adds
``penetration_weight`` × the mean squared depth inside the colliders (mm², Σ_c max(0, −σ_c)² over
the vertices past the pinned prefix) of the prediction, so the model learns to keep the hair out
of the solids, not only to follow the reference. The default weight 10 was chosen on a toy case
(sphere head, a sphere swept through 256 strands, 1,500 steps): against weight 1 it cut the mean
squared depth from 0.15 to 0.04 mm² and the deepest vertex from 27 to 16 mm for +1.4 % mean
vertex error.
"""
from __future__ import annotations

from .agnostic import NeighbourhoodMethod
from .base import register_method
from .features import penetration_mm2, sdf_inputs

__all__ = ["Collision"]


@register_method
class Collision(NeighbourhoodMethod):
    """Collision-aware residual MLP (see the module docstring).

    Model options: those of ``agnostic``, ``reach`` (m, range of the distance input) and
    ``penetration_weight`` (weight of the penetration loss against the mean squared vertex
    error, both in mm²). Training options: :data:`~baselines.learned.base.TRAIN_DEFAULTS`.
    """

    name = "collision"
    needs_scene = True
    stat_names = ("penetration_mm2", "vertex_mm2")
    MODEL_DEFAULTS = {**NeighbourhoodMethod.MODEL_DEFAULTS, "reach": 0.02, "penetration_weight": 10.0}

    def extra_dim(self, meta: dict) -> int:
        return 4 * meta["particles"]

    def extra_inputs(self, skinned_world, rot, scene):
        colliders, poses = scene
        return sdf_inputs(skinned_world, rot, colliders, poses, self.options["reach"])

    def extra_loss(self, pred_world, binding, strands, scene):
        colliders, poses = scene
        pen = penetration_mm2(pred_world, colliders, poses, binding.mask[strands])
        return self.options["penetration_weight"] * pen, {"penetration_mm2": pen.detach()}
