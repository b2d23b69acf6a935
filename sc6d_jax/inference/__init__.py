"""Inference: rotation-library matching and continuous refinement."""

from sc6d_jax.inference._matching import MatchResult, match, match_blocks, match_dense, pad_library
from sc6d_jax.inference._refine import refine_rotation, refine_rotations

__all__ = ["MatchResult", "match", "match_blocks", "match_dense", "pad_library", "refine_rotation", "refine_rotations"]
