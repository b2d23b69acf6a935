"""SC6D networks and losses as pure functions (params are plain dict pytrees).

init(key, cfg) -> params; apply(params, cfg, rgb, pe, obj_idx) -> outputs;
rotation_logits / encode_rotations for the rotation head; LossConfig + loss_fn for training.
"""

from ._config import BACKBONES, ModelConfig
from ._layers import choose_conv_impl, conv2d, group_norm, im2col, upsample2x_bilinear
from ._network import apply, count_params, init, normalize_rgb, rot_cls_grid, with_rotation_priors
from ._losses import (
    F_REF,
    LossConfig,
    bce_with_logits,
    code_to_delta_z,
    decode_delta_z,
    gaussian_bin_targets,
    axis_ring_deltas,
    local_rotation_deltas,
    z_code,
    candidate_logits,
    cross_entropy,
    downsample_mask,
    focal_loss,
    info_nce,
    loss_fn,
    predict_z,
    view_loss,
)
from ._weights import load_resnet_weights
from ._rotation import encode_rotations, rotation_features, rotation_logits

__all__ = [
    "F_REF",
    "LossConfig",
    "code_to_delta_z",
    "decode_delta_z",
    "rot_cls_grid",
    "with_rotation_priors",
    "gaussian_bin_targets",
    "axis_ring_deltas",
    "local_rotation_deltas",
    "z_code",
    "bce_with_logits",
    "candidate_logits",
    "cross_entropy",
    "downsample_mask",
    "focal_loss",
    "info_nce",
    "loss_fn",
    "predict_z",
    "view_loss",
    "BACKBONES",
    "ModelConfig",
    "apply",
    "choose_conv_impl",
    "conv2d",
    "count_params",
    "encode_rotations",
    "group_norm",
    "im2col",
    "init",
    "load_resnet_weights",
    "normalize_rgb",
    "rotation_features",
    "rotation_logits",
    "upsample2x_bilinear",
]
