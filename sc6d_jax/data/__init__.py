"""Training data: random scenes, procedural backgrounds, colour augmentation, the crop stream."""

from sc6d_jax.data._augment import colour_augment, random_background
from sc6d_jax.data._scene import IMAGE_H, IMAGE_W, SamplePose, hull_vertices, jitter, project_box, random_intrinsics, sample_pose
from sc6d_jax.data._stream import CropStream, StreamConfig, clean_view, delta_z_range, dense_targets, derive_seed, resolve_obj_ids

__all__ = [
    "IMAGE_H",
    "IMAGE_W",
    "CropStream",
    "SamplePose",
    "StreamConfig",
    "colour_augment",
    "delta_z_range",
    "clean_view",
    "dense_targets",
    "derive_seed",
    "jitter",
    "hull_vertices",
    "project_box",
    "random_background",
    "random_intrinsics",
    "resolve_obj_ids",
    "sample_pose",
]
