"""Geometry core of sc6d-jax: rotations, SO(3) grids, crops, translation encoding, allocentric poses.

Pure ``jax.numpy`` functions, batched over leading axes, dtype-preserving and jit-able (except
the numpy helpers ``fibonacci_sphere``, ``so3_grid``, ``warp_crop``, ``supersample_transform``,
``area_downsample``, ``nearest_rotation`` and ``covering_radius``). ``validate_*`` raise ``ValueError`` naming the problem; the core
functions run them automatically whenever their inputs are concrete (outside jit).
"""

from sc6d_jax.geometry._allocentric import allocentric_to_egocentric, egocentric_to_allocentric, ray_rotation
from sc6d_jax.geometry._crops import (
    area_downsample,
    crop_box,
    crop_intrinsics,
    crop_transform,
    jitter_box,
    pe_map,
    supersample_transform,
    turn_pe,
    warp_crop,
)
from sc6d_jax.geometry._rotations import (
    axis_angle_to_matrix,
    geodesic_angle,
    matrix_to_axis_angle,
    matrix_to_quat,
    matrix_to_sixd,
    project_to_so3,
    quat_to_matrix,
    rot_x,
    rot_y,
    rot_z,
    rotation_between,
    sixd_to_matrix,
    skew,
)
from sc6d_jax.geometry._sampling import (
    covering_radius,
    fibonacci_sphere,
    nearest_rotation,
    random_rotations,
    rebase_negatives,
    sample_rotation_deltas,
    so3_grid,
    viewpoint_rotation,
)
from sc6d_jax.geometry._translation import (
    decode_translation,
    encode_translation,
    z_bin_centers,
    z_bin_label,
    z_expectation,
)
from sc6d_jax.geometry._validate import (
    validate_boxes,
    validate_K,
    validate_rotation,
    validate_translation,
)

__all__ = [
    "allocentric_to_egocentric",
    "axis_angle_to_matrix",
    "covering_radius",
    "crop_box",
    "crop_intrinsics",
    "crop_transform",
    "decode_translation",
    "egocentric_to_allocentric",
    "encode_translation",
    "fibonacci_sphere",
    "geodesic_angle",
    "jitter_box",
    "matrix_to_axis_angle",
    "matrix_to_quat",
    "matrix_to_sixd",
    "nearest_rotation",
    "pe_map",
    "project_to_so3",
    "quat_to_matrix",
    "random_rotations",
    "ray_rotation",
    "rebase_negatives",
    "rot_x",
    "rot_y",
    "rot_z",
    "rotation_between",
    "sample_rotation_deltas",
    "sixd_to_matrix",
    "skew",
    "so3_grid",
    "turn_pe",
    "validate_K",
    "validate_boxes",
    "validate_rotation",
    "validate_translation",
    "viewpoint_rotation",
    "warp_crop",
    "supersample_transform",
    "area_downsample",
    "z_bin_centers",
    "z_bin_label",
    "z_expectation",
]
