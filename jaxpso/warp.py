"""Homographies, the plane-induced motion model, and image sampling.

A homography maps template pixel (x, y) to image pixel (x, y), pixel centres
at integer coordinates (the OpenCV convention, the same as the warp matrix of
`cv2.findTransformECC(template, image, ...)`).
"""

from jaxpso._src.homography import apply_to_points
from jaxpso._src.homography import compose
from jaxpso._src.homography import corner_error
from jaxpso._src.homography import corner_offsets_to_homography
from jaxpso._src.homography import homography_from_corners
from jaxpso._src.homography import homography_from_level
from jaxpso._src.homography import homography_to_corner_offsets
from jaxpso._src.homography import homography_to_level
from jaxpso._src.homography import inverse
from jaxpso._src.homography import normalize
from jaxpso._src.homography import rect_corners
from jaxpso._src.homography import scaling
from jaxpso._src.homography import square_to_quad
from jaxpso._src.homography import translation
from jaxpso._src.plane import DOF_AXES
from jaxpso._src.plane import camera_matrix
from jaxpso._src.plane import compose_poses
from jaxpso._src.plane import default_camera
from jaxpso._src.plane import expand_dof
from jaxpso._src.plane import invert_pose
from jaxpso._src.plane import params_from_pose
from jaxpso._src.plane import plane_homography
from jaxpso._src.plane import pose_from_homography
from jaxpso._src.plane import pose_from_params
from jaxpso._src.plane import rodrigues
from jaxpso._src.plane import rotation_log
from jaxpso._src.plane import template_to_frame
from jaxpso._src.sampling import gaussian_pyramid
from jaxpso._src.sampling import pyr_down
from jaxpso._src.sampling import template_grid
from jaxpso._src.sampling import warp_image
from jaxpso._src.sampling import warp_points

__all__ = (
    "DOF_AXES",
    "apply_to_points",
    "camera_matrix",
    "compose",
    "compose_poses",
    "corner_error",
    "corner_offsets_to_homography",
    "default_camera",
    "expand_dof",
    "gaussian_pyramid",
    "homography_from_corners",
    "homography_from_level",
    "homography_to_corner_offsets",
    "homography_to_level",
    "inverse",
    "invert_pose",
    "normalize",
    "params_from_pose",
    "plane_homography",
    "pose_from_homography",
    "pose_from_params",
    "pyr_down",
    "rect_corners",
    "rodrigues",
    "rotation_log",
    "scaling",
    "square_to_quad",
    "template_grid",
    "template_to_frame",
    "translation",
    "warp_image",
    "warp_points",
)
