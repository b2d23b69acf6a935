"""BOP19 pose-error metrics (VSD, MSSD, MSPD, ADD, ADI, RE, TE) and average recall, as the BOP toolkit.

Public surface: the pose errors ``re``, ``te``, ``add``, ``adi``, ``mssd``, ``mspd``, ``vsd``
(the toolkit's arguments, mm, numpy in, float out); ``symmetry_transformations`` and
``symmetry_coverage``; ``evaluate_bop19`` (a BOP dataset + estimates -> scores with the toolkit's
key names), ``evaluate_images`` / ``compute_errors`` / ``score_errors`` (in-memory pieces; ``group_estimates``
pairs each target with its estimates as they do; per-target shares of
the AR and its standard error, ``paired_difference`` of two scorings on the same targets, ``standard_error``);
``VsdRenderer`` (depth for VSD in the toolkit's pixel convention); the threshold grids; the
pose-error breakdown (``rotation_error_deg``, ``pose_errors``, ``breakdown_errors``,
``summarize_breakdown``, ``symmetry_rotations``, ``format_breakdown_line``: median rotation,
relative depth and projected-centre errors, stored by ``evaluate_bop19`` under ``breakdown``);
``with_ground_truth`` (estimates with their rotation, translation, depth or projected centre
from the ground truth: what each head scores alone).
The ``sc6d eval`` command lives in ``sc6d_jax.metrics.cli``.
"""

from sc6d_jax.metrics._bop19 import (
    MAX_SYM_DISC_STEP,
    MSPD_THRESHOLDS,
    MSSD_THRESHOLDS,
    VISIB_GT_MIN,
    VSD_DELTA,
    VSD_TAUS,
    VSD_THRESHOLDS,
    EstimateErrors,
    EvalImage,
    GroundTruth,
    ObjectModel,
    average_time_per_image,
    compute_errors,
    evaluate_images,
    group_estimates,
    make_object_model,
    paired_difference,
    score_errors,
    standard_error,
)
from sc6d_jax.metrics._breakdown import (
    EXTENT_BINS,
    MISS,
    RAY_BINS,
    VISIBILITY_BINS,
    breakdown_errors,
    extent_ratio,
    format_breakdown_line,
    pose_errors,
    rotation_error_deg,
    summarize_breakdown,
    symmetry_rotations,
)
from sc6d_jax.metrics._evaluate import evaluate_bop19, load_eval_images, load_object_models
from sc6d_jax.metrics._pose_error import (
    add,
    adi,
    depth_to_distance,
    mspd,
    mssd,
    overlapping_sphere_projections,
    project_pts,
    re,
    te,
    transform_pts,
    vsd,
)
from sc6d_jax.metrics._oracle import ORACLE_PARTS, with_ground_truth
from sc6d_jax.metrics._symmetry import symmetry_coverage, symmetry_transformations
from sc6d_jax.metrics._vsd_renderer import VsdRenderer

__all__ = [
    "MAX_SYM_DISC_STEP",
    "MISS",
    "MSPD_THRESHOLDS",
    "MSSD_THRESHOLDS",
    "ORACLE_PARTS",
    "RAY_BINS",
    "EXTENT_BINS",
    "VISIBILITY_BINS",
    "VISIB_GT_MIN",
    "VSD_DELTA",
    "VSD_TAUS",
    "VSD_THRESHOLDS",
    "EstimateErrors",
    "EvalImage",
    "GroundTruth",
    "ObjectModel",
    "VsdRenderer",
    "add",
    "adi",
    "average_time_per_image",
    "breakdown_errors",
    "extent_ratio",
    "compute_errors",
    "depth_to_distance",
    "evaluate_bop19",
    "evaluate_images",
    "format_breakdown_line",
    "group_estimates",
    "load_eval_images",
    "load_object_models",
    "make_object_model",
    "mspd",
    "mssd",
    "overlapping_sphere_projections",
    "paired_difference",
    "pose_errors",
    "project_pts",
    "re",
    "rotation_error_deg",
    "score_errors",
    "standard_error",
    "summarize_breakdown",
    "symmetry_coverage",
    "symmetry_rotations",
    "symmetry_transformations",
    "te",
    "transform_pts",
    "vsd",
    "with_ground_truth",
]
