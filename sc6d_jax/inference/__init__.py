"""Inference: rotation library, jitted predictor (TTA, refinement), Estimator, export."""

from sc6d_jax.inference._estimator import Estimator, PosePrediction, bucket_size
from sc6d_jax.inference._export import export_predictor, load_exported
from sc6d_jax.inference._library import (
    LIBRARY_GRIDS,
    RotationLibrary,
    library_grid,
    library_key,
    load_or_build_library,
    pack_library,
)
from sc6d_jax.inference._matching import (
    MatchResult,
    auto_block,
    ipdf_match_blocks,
    match,
    match_blocks,
    match_dense,
    pad_library,
)
from sc6d_jax.inference._predictor import predict_crops, rotate_crops, rz90
from sc6d_jax.inference._refine import refine_rotation, refine_rotations

__all__ = [
    "LIBRARY_GRIDS",
    "Estimator",
    "MatchResult",
    "PosePrediction",
    "RotationLibrary",
    "auto_block",
    "bucket_size",
    "export_predictor",
    "library_grid",
    "load_exported",
    "library_key",
    "load_or_build_library",
    "match",
    "ipdf_match_blocks",
    "match_blocks",
    "match_dense",
    "pack_library",
    "pad_library",
    "predict_crops",
    "refine_rotation",
    "refine_rotations",
    "rotate_crops",
    "rz90",
]
