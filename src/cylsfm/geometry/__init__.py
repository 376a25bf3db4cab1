"""Camera models, rigid transforms and inverse warping: pure, batched, differentiable torch.

Nothing here knows about networks or datasets.
"""

from .cameras import Camera, CameraError, CylindricalCamera, EquirectangularCamera, PinholeCamera, load_camera
from .pose import (
    axis_angle_to_matrix,
    compose,
    invert,
    mat_to_pose_vec,
    mat_to_tum,
    matrix_to_axis_angle,
    matrix_to_quaternion,
    pose_vec_to_mat,
    quaternion_to_matrix,
    relative_pose,
    tum_to_mat,
    yaw_matrix,
)
from .warp import inverse_warp, resize_image, sample_image, transform_points

__all__ = [
    "Camera",
    "CameraError",
    "CylindricalCamera",
    "EquirectangularCamera",
    "PinholeCamera",
    "axis_angle_to_matrix",
    "compose",
    "inverse_warp",
    "invert",
    "load_camera",
    "mat_to_pose_vec",
    "mat_to_tum",
    "matrix_to_axis_angle",
    "matrix_to_quaternion",
    "pose_vec_to_mat",
    "quaternion_to_matrix",
    "relative_pose",
    "resize_image",
    "sample_image",
    "transform_points",
    "tum_to_mat",
    "yaw_matrix",
]
