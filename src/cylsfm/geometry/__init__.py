"""Camera models, rigid transforms, the seam of full panoramas and inverse warping: pure, batched, differentiable.

Nothing here knows about networks or datasets.
"""

from .cameras import Camera, CameraError, CylindricalCamera, EquirectangularCamera, PinholeCamera, load_camera
from .compass import column_shift, compass_yaw, compass_yaws, window_yaws
from .jacobian import projection_jacobian
from .place import place_descriptor, place_distance
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
    rotation_x,
    rotation_y,
    rotation_z,
    tum_to_mat,
    yaw_matrix,
    yaw_transform,
)
from .seam import (
    circular_pad,
    column_difference,
    pad_for_window,
    resize_image,
    roll_angle,
    roll_columns,
    roll_pose,
)
from .warp import inverse_warp, sample_image, transform_points

__all__ = [
    "Camera",
    "CameraError",
    "CylindricalCamera",
    "EquirectangularCamera",
    "PinholeCamera",
    "axis_angle_to_matrix",
    "circular_pad",
    "column_difference",
    "column_shift",
    "compass_yaw",
    "compass_yaws",
    "compose",
    "inverse_warp",
    "invert",
    "load_camera",
    "mat_to_pose_vec",
    "mat_to_tum",
    "matrix_to_axis_angle",
    "matrix_to_quaternion",
    "pad_for_window",
    "place_descriptor",
    "place_distance",
    "pose_vec_to_mat",
    "projection_jacobian",
    "quaternion_to_matrix",
    "relative_pose",
    "resize_image",
    "roll_angle",
    "roll_columns",
    "roll_pose",
    "rotation_x",
    "rotation_y",
    "rotation_z",
    "sample_image",
    "transform_points",
    "tum_to_mat",
    "window_yaws",
    "yaw_matrix",
    "yaw_transform",
]
