"""Pose decoder (paper Fig. "pose decoder", REFERENCE section 1), shared by all objects.

features (S/4, feat_dim) ++ sigmoid(mask) -> 3x3/2 conv -> 3x3/2 conv (pose_width, S/16; with
``pose_downsample=1`` the second conv has stride 1 and what follows runs at twice the size, with
``pose_downsample=0`` both have stride 1 and it runs at S/4)
-> [itself, six 3x3 convs with dilation 2..7, global average pool broadcast] (8 * pose_width)
-> three heads, each 3x3/2 conv (pose_width) + flatten + FC head_hidden + FC out:
rotation embedding (emb_dim), delta_xy (2), z logits (n_z_bins).
GroupNorm + ReLU after every layer but the outputs (paper; the authors' code has no GN after
the hidden FC layer). The pooled branch has no parameters (paper: "global average pooling
(and expanding)").
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ._config import ModelConfig
from ._encoder import conv_gn_relu, init_conv_gn
from ._layers import conv_output_size, dense, group_norm, init_dense, init_gn, num_groups, split
from ._rotation import _init_stacked_dense

DILATIONS = (2, 3, 4, 5, 6, 7)


def block_map_size(cfg: ModelConfig) -> int:
    """Side of the dilated block's map (the features at S/4 after ``pose_downsample`` stride-2 convs)."""
    s = cfg.mask_size
    for _ in range(cfg.pose_downsample):
        s = conv_output_size(s, 3, 2, 1)
    return s


def head_map_size(cfg: ModelConfig) -> int:
    """Side of the map each head flattens (its stride-2 conv's output of the block's map)."""
    return conv_output_size(block_map_size(cfg), 3, 2, 1)


def _flat_size(cfg: ModelConfig) -> int:
    return head_map_size(cfg) ** 2 * cfg.pose_width


def init_pose_decoder(key: np.random.Generator, cfg: ModelConfig) -> dict:
    pw, hh = cfg.pose_width, cfg.head_hidden
    k = split(key, 2 + len(DILATIONS) + 3)
    params: dict = {
        "down1": init_conv_gn(k[0], 3, cfg.feat_dim + 1, pw),
        "down2": init_conv_gn(k[1], 3, pw, pw),
        "dilated": [init_conv_gn(k[2 + i], 3, pw, pw) for i in range(len(DILATIONS))],
    }
    flat = _flat_size(cfg)
    for name, out_dim, hk in zip(("rot", "xy", "z"), (cfg.emb_dim, 2, cfg.n_z_bins), k[-3:]):
        k1, k2, k3 = split(hk, 3)
        params[name] = {
            "conv": init_conv_gn(k1, 3, 8 * pw, pw),
            "fc": init_dense(k2, flat, hh),
            "fc_gn": init_gn(hh),
            "out": (_init_stacked_dense(k3, cfg.n_objects, hh, out_dim, scale=0.01) if cfg.per_object_heads
                    else init_dense(k3, hh, out_dim, scale=0.01)),
        }
    if cfg.z_size_input:
        params["z"]["size"] = init_dense(split(k[-1], 4)[3], N_SIZE_FEATURES, hh)
    if cfg.z_ray_input:
        params["z"]["ray"] = init_dense(split(k[-1], 5)[4], N_RAY_FEATURES, hh)
    if cfg.z_scale_input:
        params["z"]["scale"] = init_dense(split(k[-1], 6)[5], N_SCALE_FEATURES, hh)
    return params


#: Features of the crop's ray fed to the depth head (z_ray_input).
N_RAY_FEATURES = 5


def ray_features(pe: jax.Array) -> jax.Array:
    """(B, 5) the crop centre's ray (x, y) = the mean of its PE map (B,S,S,2) (the map is affine
    in the crop's pixels), and its second-order terms (x^2, y^2, xy), which describe the
    perspective stretch along the ray's direction (``1/cos`` of its angle, about ``1 + r r^T / 2``).
    Scaled to about unit size over a 60-degree field of view. The depth code is read off the
    object's apparent size in the crop; GroupNorm removes a near-constant input such as the ray
    from the features, so it is given explicitly."""
    r = jnp.mean(pe.astype(jnp.float32), axis=(1, 2))
    x, y = r[:, 0], r[:, 1]
    return jnp.stack([2.0 * x, 2.0 * y, 4.0 * x * x, 4.0 * y * y, 4.0 * x * y], axis=-1)


#: Features of the crop's angular size fed to the depth head (z_scale_input).
N_SCALE_FEATURES = 1

#: log angular size of a typical crop (about 0.25 rad: a 150-pixel side at f = 600), subtracted
SCALE_LOG_REF = -1.4


def scale_features(pe: jax.Array) -> jax.Array:
    """(B, 1) log of the crop's angular size: the square root of the area its PE map (B,S,S,2)
    spans (the map is affine in the crop's pixels; the area is unchanged by ``turn_pe``), centred
    on about 0.25 rad (a 150-pixel crop side at f = 600; the stream's crops span about -1 to +1).
    An object at a few diameters is seen in perspective, its near side larger than its far side,
    so its box and depth code depend on how close it is; the angular size tells that directly."""
    pe = pe.astype(jnp.float32)
    s = pe.shape[1]
    du = (pe[:, 0, -1] - pe[:, 0, 0]) * (s / (s - 1))  # along the crop's x, over its whole side
    dv = (pe[:, -1, 0] - pe[:, 0, 0]) * (s / (s - 1))
    area = jnp.abs(du[:, 0] * dv[:, 1] - du[:, 1] * dv[:, 0])
    return (0.5 * jnp.log(area + 1e-12) - SCALE_LOG_REF)[:, None]


#: Apparent-size features of the predicted visible mask fed to the depth head (z_size_input).
N_SIZE_FEATURES = 3


def mask_size_features(mask_logit: jax.Array) -> jax.Array:
    """(B, 3) apparent size of the soft visible mask sigmoid(logit) (B,h,w): log of its area
    fraction and log of its spatial standard deviation along x and y (crop units in [-1, 1]).
    The depth code is the object's size over its apparent size in the crop; GroupNorm and pooling
    make an absolute area hard to read from normalised features, so it is given explicitly."""
    m = jax.nn.sigmoid(mask_logit.astype(jnp.float32))
    h, w = m.shape[-2:]
    v = jnp.linspace(-1.0, 1.0, h)[:, None]
    u = jnp.linspace(-1.0, 1.0, w)[None, :]
    mass = jnp.sum(m, axis=(-2, -1)) + 1e-4
    mu = jnp.sum(m * u, axis=(-2, -1)) / mass
    mv = jnp.sum(m * v, axis=(-2, -1)) / mass
    var_u = jnp.sum(m * jnp.square(u - mu[:, None, None]), axis=(-2, -1)) / mass
    var_v = jnp.sum(m * jnp.square(v - mv[:, None, None]), axis=(-2, -1)) / mass
    area = mass / (h * w)
    return jnp.stack([jnp.log(area + 1e-4), 0.5 * jnp.log(var_u + 1e-4), 0.5 * jnp.log(var_v + 1e-4)], axis=-1)


def pose_decoder(
    params: dict, cfg: ModelConfig, feat: jax.Array, mask_logit: jax.Array, pe: jax.Array | None = None,
    return_hidden: bool = False, return_map: bool = False, obj_idx: jax.Array | None = None,
) -> tuple[jax.Array, ...]:
    """Returns (raw rotation feature (B,emb_dim), delta_xy (B,2), z logits (B,n_z_bins)), and with
    ``return_hidden`` also the rotation head's hidden layer (B,head_hidden); with ``return_map``
    that layer, the map the rotation head flattens (B,m,m,pose_width), m = :func:`head_map_size`,
    and the dilated block's output that the three heads read (B,n,n,8 pose_width), n =
    :func:`block_map_size` (six outputs).
    ``pe`` (B,S,S,2): the crops' PE maps, needed with ``cfg.z_ray_input``. ``obj_idx`` (B,): the
    crops' objects, needed with ``cfg.per_object_heads`` (each head's output layer is its object's)."""
    if (cfg.z_ray_input or cfg.z_scale_input) and pe is None:
        raise ValueError("z_ray_input and z_scale_input need the PE map (use_pe=True)")
    if cfg.per_object_heads:
        if obj_idx is None:
            raise ValueError("per_object_heads needs obj_idx (each crop's object chooses the heads' output layers)")
        obj_idx = jnp.asarray(obj_idx, jnp.int32)
    x = jnp.concatenate([feat, jax.nn.sigmoid(mask_logit)[..., None]], axis=-1)
    x = conv_gn_relu(x, params["down1"], cfg, stride=2 if cfg.pose_downsample >= 1 else 1)
    x = conv_gn_relu(x, params["down2"], cfg, stride=2 if cfg.pose_downsample == 2 else 1)
    branches = [x]
    for d, p in zip(DILATIONS, params["dilated"]):
        branches.append(conv_gn_relu(x, p, cfg, dilation=d))
    branches.append(jnp.broadcast_to(jnp.mean(x, axis=(1, 2), keepdims=True), x.shape))
    x = jnp.concatenate(branches, axis=-1)
    block = x
    outs, hidden, maps = [], [], []
    for name in ("rot", "xy", "z"):
        p = params[name]
        h = conv_gn_relu(x, p["conv"], cfg, stride=2)
        maps.append(h)
        h = h.reshape(h.shape[0], -1)
        h = dense(h, p["fc"]["w"], p["fc"]["b"])
        if name == "z" and "size" in p:
            h = h + dense(mask_size_features(mask_logit), p["size"]["w"], p["size"]["b"])
        if name == "z" and "ray" in p:
            h = h + dense(ray_features(pe), p["ray"]["w"], p["ray"]["b"])
        if name == "z" and "scale" in p:
            h = h + dense(scale_features(pe), p["scale"]["w"], p["scale"]["b"])
        h = jax.nn.relu(group_norm(h, p["fc_gn"]["scale"], p["fc_gn"]["bias"], num_groups(h.shape[-1], cfg.gn_groups)))
        hidden.append(h)
        w, b = p["out"]["w"], p["out"]["b"]
        if cfg.per_object_heads:
            w, b = w[obj_idx], b[obj_idx]
        outs.append(dense(h, w, b))
    if return_map:
        return outs[0], outs[1], outs[2], hidden[0], maps[0], block
    if return_hidden:
        return outs[0], outs[1], outs[2], hidden[0]
    return outs[0], outs[1], outs[2]
