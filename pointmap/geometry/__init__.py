"""Pure batched geometry: cameras, rotations, Procrustes, focal estimation (docs/conventions.md)."""

from pointmap.geometry.cameras import (
    convert_camera_axes,
    crop_intrinsics,
    depth_to_points_cam,
    depth_to_points_world,
    intrinsics,
    invert_rigid,
    is_pinhole_K,
    pixel_grid,
    project,
    scale_intrinsics,
    transform_points,
)
from pointmap.geometry.focal import focal_from_pointmap
from pointmap.geometry.procrustes import to_matrix, weighted_procrustes
from pointmap.geometry.rotations import (
    axis_angle_to_matrix,
    random_rotation,
    relative_rotation_error_deg,
    rotation_angle,
    se3_exp,
    translation_angle_deg,
)

__all__ = [
    "axis_angle_to_matrix", "convert_camera_axes", "crop_intrinsics", "depth_to_points_cam", "depth_to_points_world",
    "focal_from_pointmap", "intrinsics", "invert_rigid", "is_pinhole_K", "pixel_grid", "project", "random_rotation",
    "relative_rotation_error_deg", "rotation_angle", "scale_intrinsics", "se3_exp", "to_matrix",
    "transform_points", "translation_angle_deg", "weighted_procrustes",
]
