"""RGB encoder: ResNet (BasicBlock, GroupNorm, new stem without max-pool) + asymmetric U-Net decoder.

Resolutions for a crop of side S: stem S/2, layer1 S/2, layer2 S/4, layer3 S/8, layer4 S/16.
The decoder follows the authors' ``ResNet34_AsymUNet``: 1x1 lateral convs on layer4/3/2,
bilinear 2x upsampling, a 3x3 conv at S/8 on [up(layer4), layer3] and one at S/4 on
[up(.), layer2], then a 1x1 conv to ``feat_dim + 1`` channels (features + visible-mask logit).
Deviation: BatchNorm (authors' backbone) is replaced by GroupNorm everywhere and the decoder
convs are conv + GroupNorm + ReLU (the authors use conv + bias + ReLU there), so nothing in
the model depends on batch statistics.

Decoders are per object (params stacked on a leading object axis, gathered per sample) or
shared with a learned per-object vector added to the layer4 features.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ._config import ModelConfig
from ._layers import (
    conv2d,
    group_norm,
    init_conv,
    init_gn,
    normal,
    num_groups,
    split,
    stack_trees,
    upsample2x_bilinear,
)


def conv_gn_relu(
    x: jax.Array, p: dict, cfg: ModelConfig, *, stride: int = 1, dilation: int = 1, relu: bool = True
) -> jax.Array:
    """conv (no bias) -> GroupNorm -> ReLU; ``p = {'conv': {'w'}, 'gn': {'scale','bias'}}``."""
    y = conv2d(x, p["conv"]["w"], p["conv"].get("b"), stride=stride, dilation=dilation, impl=cfg.conv_impl)
    y = group_norm(y, p["gn"]["scale"], p["gn"]["bias"], num_groups(y.shape[-1], cfg.gn_groups))
    return jax.nn.relu(y) if relu else y


def init_conv_gn(key: np.random.Generator, k: int, cin: int, cout: int) -> dict:
    return {"conv": init_conv(key, k, cin, cout), "gn": init_gn(cout)}


def _init_block(key: np.random.Generator, cin: int, cout: int, stride: int) -> dict:
    k1, k2, k3 = split(key, 3)
    p = {"conv1": init_conv_gn(k1, 3, cin, cout), "conv2": init_conv_gn(k2, 3, cout, cout)}
    # Residual branches start near zero (zero-init of the last GN scale) for stable training.
    p["conv2"]["gn"]["scale"] = np.zeros((cout,), np.float32)
    if stride != 1 or cin != cout:
        p["down"] = init_conv_gn(k3, 1, cin, cout)
    return p


def _block(x: jax.Array, p: dict, cfg: ModelConfig, stride: int) -> jax.Array:
    y = conv_gn_relu(x, p["conv1"], cfg, stride=stride)
    y = conv_gn_relu(y, p["conv2"], cfg, relu=False)
    sc = conv_gn_relu(x, p["down"], cfg, stride=stride, relu=False) if "down" in p else x
    return jax.nn.relu(y + sc)


def init_backbone(key: np.random.Generator, cfg: ModelConfig) -> dict:
    """ResNet params: {'stem': conv_gn, 'layer1'..'layer4': [block, ...]}."""
    keys = split(key, 5)
    widths = cfg.stage_widths
    params: dict = {"stem": init_conv_gn(keys[0], cfg.stem_kernel, cfg.in_channels, widths[0])}
    cin = widths[0]
    for s, (n_blocks, cout) in enumerate(zip(cfg.stage_blocks, widths)):
        bkeys = split(keys[s + 1], n_blocks)
        blocks = []
        for i in range(n_blocks):
            stride = 2 if (i == 0 and s > 0) else 1
            blocks.append(_init_block(bkeys[i], cin, cout, stride))
            cin = cout
        params[f"layer{s + 1}"] = blocks
    return params


def backbone(params: dict, cfg: ModelConfig, x: jax.Array) -> list[jax.Array]:
    """ResNet forward; returns [layer1 (S/2), layer2 (S/4), layer3 (S/8), layer4 (S/16)]."""
    x = conv_gn_relu(x, params["stem"], cfg, stride=2)
    feats = []
    for s in range(4):
        for i, bp in enumerate(params[f"layer{s + 1}"]):
            x = _block(x, bp, cfg, 2 if (i == 0 and s > 0) else 1)
        feats.append(x)
    return feats


def _init_decoder_one(key: np.random.Generator, cfg: ModelConfig) -> dict:
    _, c2, c3, c4 = cfg.stage_widths
    dw = cfg.dec_width
    k = split(key, 6)
    last = init_conv(k[5], 1, dw // 2, cfg.feat_dim + 1, bias=True)
    return {
        "lat4": init_conv_gn(k[0], 1, c4, c4),
        "lat3": init_conv_gn(k[1], 1, c3, c3),
        "lat2": init_conv_gn(k[2], 1, c2, c2),
        "up3": init_conv_gn(k[3], 3, c4 + c3, dw),
        "up2": init_conv_gn(k[4], 3, dw + c2, dw // 2),
        "last": last,
    }


def init_decoder(key: np.random.Generator, cfg: ModelConfig) -> dict:
    """U-Net decoder params. Per object: every leaf has a leading axis of size n_objects.
    Shared: one decoder plus 'obj_embed' (n_objects, C4) added to the layer4 features."""
    if cfg.dec_width < 2:
        raise ValueError(f"decoder width must be >= 2, got {cfg.dec_width}")
    if cfg.per_object_decoder:
        return stack_trees([_init_decoder_one(k, cfg) for k in split(key, cfg.n_objects)])
    k1, k2 = split(key, 2)
    p = _init_decoder_one(k1, cfg)
    p["obj_embed"] = normal(k2, (cfg.n_objects, cfg.stage_widths[-1]), 0.1)
    return p


def select_decoder(params: dict, cfg: ModelConfig, obj_idx: jax.Array) -> dict:
    """The decoder params for this batch: the object's weights gathered per sample
    (leaves (B, ...)), or the single stack entry when n_objects == 1 (leaves without the axis)."""
    if not cfg.per_object_decoder:
        return params
    if cfg.n_objects == 1:
        return jax.tree.map(lambda a: a[0], params)
    return jax.tree.map(lambda a: a[obj_idx], params)


def decoder(
    params: dict, cfg: ModelConfig, feats: list[jax.Array], obj_idx: jax.Array
) -> tuple[jax.Array, jax.Array]:
    """U-Net decoder: returns (features (B,S/4,S/4,feat_dim), mask logit (B,S/4,S/4))."""
    _, l2, l3, l4 = feats
    p = select_decoder(params, cfg, obj_idx)
    if not cfg.per_object_decoder:
        l4 = l4 + p["obj_embed"][obj_idx][:, None, None, :]
    x = conv_gn_relu(l4, p["lat4"], cfg)
    x = upsample2x_bilinear(x)
    x = jnp.concatenate([x, conv_gn_relu(l3, p["lat3"], cfg)], axis=-1)
    x = conv_gn_relu(x, p["up3"], cfg)
    x = upsample2x_bilinear(x)
    x = jnp.concatenate([x, conv_gn_relu(l2, p["lat2"], cfg)], axis=-1)
    x = conv_gn_relu(x, p["up2"], cfg)
    out = conv2d(x, p["last"]["w"], p["last"]["b"], impl=cfg.conv_impl)
    return out[..., :-1], out[..., -1]
