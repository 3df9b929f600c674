"""Geometry shared by every layer: rigid poses, signed distance grids, mesh loading.

Imports nothing else of ams_torch (the bottom layer, beside :mod:`ams_torch.native`).
"""
from ams_torch.geometry.mesh import load_mesh
from ams_torch.geometry.pose import Pose, axis_angle_to_matrix, matrix_to_axis_angle
from ams_torch.geometry.sdf import SDFGrid

__all__ = ["Pose", "SDFGrid", "load_mesh", "axis_angle_to_matrix", "matrix_to_axis_angle"]
