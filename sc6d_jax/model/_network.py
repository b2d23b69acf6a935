"""The SC6D network: init(key, cfg) -> params, apply(params, cfg, rgb, pe, obj_idx) -> outputs."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from ._config import ModelConfig
from ._layers import dense, init_dense, make_rng, split
from ._encoder import backbone, conv_gn_relu, decoder, init_backbone, init_conv_gn, init_decoder
from ._pose_decoder import block_map_size, head_map_size, init_pose_decoder, pose_decoder
from ._rotation import _init_stacked_dense, _l2n, init_rotation_head, init_rotation_prior, rotation_prior_output

#: ImageNet statistics (torchvision), so that converted ImageNet weights see familiar inputs.
RGB_MEAN = (0.485, 0.456, 0.406)
RGB_STD = (0.229, 0.224, 0.225)
#: Channels of the dense head: surface normal (3) and depth relative to the object centre (1).
N_DENSE = 4


def init(key: jax.Array, cfg: ModelConfig) -> dict:
    """Fresh parameters: {'backbone', 'decoder', 'pose_decoder', 'rot_head'} (plain dicts/lists).

    Deterministic: the same key and config give bit-identical params (drawn with a numpy
    Generator seeded from the key, see _layers.make_rng).
    """
    if not isinstance(cfg, ModelConfig):
        raise ValueError(f"cfg must be a ModelConfig, got {type(cfg).__name__}")
    rng = make_rng(key)
    k1, k2, k3, k4 = split(rng, 4)
    params = {
        "backbone": init_backbone(k1, cfg),
        "decoder": init_decoder(k2, cfg),
        "pose_decoder": init_pose_decoder(k3, cfg),
        "rot_head": init_rotation_head(k4, cfg),
    }
    if cfg.dense_head:  # a fifth child of the generator: the other parts are drawn as without it
        params["dense_head"] = init_dense(split(rng, 1)[0], cfg.feat_dim, N_DENSE + 3 * cfg.dense_xyz, scale=1.0)
    if cfg.rot_readout:  # the next child: the parts above are drawn as without it
        params["rot_readout"] = _init_stacked_dense(split(rng, 1)[0], cfg.n_objects, cfg.emb_dim, 6, scale=1.0)
    if cfg.z_rot:  # the next child
        params["z_rot"] = init_rotation_prior(split(rng, 1)[0], cfg)
    if cfg.rot_cls:  # the next child
        n = len(rot_cls_grid(cfg.rot_cls))
        params["rot_cls"] = _init_stacked_dense(split(rng, 1)[0], cfg.n_objects, cfg.head_hidden, n, scale=0.01)
    if cfg.view_head:  # the next child
        if cfg.view_from in ("map", "block"):
            m, c = (head_map_size(cfg), cfg.pose_width) if cfg.view_from == "map" else (block_map_size(cfg), 8 * cfg.pose_width)
            if cfg.view_head % m:
                raise ValueError(f"view_from={cfg.view_from!r}: view_head {cfg.view_head} must be a multiple of the map's side {m}")
            out = 3 * (cfg.view_head // m) ** 2
        else:
            c, out = cfg.head_hidden, 3 * cfg.view_head**2
        if cfg.view_per_object:  # one decoder per object: the objects do not share the code of the map's cells
            params["view_head"] = _init_stacked_dense(split(rng, 1)[0], cfg.n_objects, c, out, scale=0.01)
        else:
            params["view_head"] = init_dense(split(rng, 1)[0], c, out, scale=0.01)
    if cfg.xy_rot:  # the next child
        params["xy_rot"] = init_rotation_prior(split(rng, 1)[0], cfg, out_dim=2)
    if cfg.xy_vote:  # the next child
        kc, ko = split(split(rng, 1)[0], 2)
        cin, c = (cfg.feat_dim, cfg.feat_dim) if cfg.xy_vote_from == "feat" else (8 * cfg.pose_width, cfg.pose_width)
        params["xy_vote"] = {"conv": init_conv_gn(kc, 3, cin, c), "out": init_dense(ko, c, 3, scale=0.01)}
    return jax.tree.map(jnp.asarray, params)


def vote_grid(n: int) -> jax.Array:
    """(n, n, 2) the centres of an n x n map's cells in crop-side units about the crop centre
    (x right, y down; delta_xy's units): cell k covers crop pixels [kS/n, (k+1)S/n) of the S-pixel
    crop that covers [-0.5, S - 0.5] (sc6d_jax.geometry crop convention), so its centre lies at
    (k + 0.5) / n - 0.5 of the side."""
    c = (jnp.arange(n, dtype=jnp.float32) + 0.5) / n - 0.5
    return jnp.stack(jnp.meshgrid(c, c, indexing="xy"), axis=-1)


def vote_delta_xy(votes: jax.Array, mask_logit: jax.Array) -> jax.Array:
    """(B, 2) delta_xy from per-cell votes (B,n,n,3) (offset x, y from the cell to the projected
    centre in crop-side units, confidence logit): the votes' positions averaged with weights
    softmax(confidence + log mask) over the cells, mask = sigmoid(mask_logit) (B,m,m) averaged
    over the m/n x m/n cells of each vote; the mask only weighs (no gradient reaches it from here)."""
    b, n = votes.shape[0], votes.shape[1]
    m = jax.nn.sigmoid(jax.lax.stop_gradient(mask_logit.astype(jnp.float32)))
    f = m.shape[1] // n
    if f > 1:
        m = m.reshape(b, n, f, n, f).mean(axis=(2, 4))
    logm = jnp.log(m + 1e-6)
    w = jax.nn.softmax((votes[..., 2].astype(jnp.float32) + logm).reshape(b, -1), axis=-1)
    pos = (vote_grid(n)[None] + votes[..., :2].astype(jnp.float32)).reshape(b, -1, 2)
    return jnp.einsum("bk,bkc->bc", w, pos)


@functools.lru_cache(maxsize=8)
def rot_cls_grid(size: int) -> np.ndarray:
    """The classes of ``ModelConfig.rot_cls``: about ``size`` rotations, float32 (N,3,3), from
    :func:`sc6d_jax.geometry.so3_grid` with its viewpoint and in-plane spacings matched
    (``n_inplane ~ (pi size)^(1/3)``, ``n_views ~ n_inplane^2 / pi``): 1,000 gives 15 x 67
    = 1,005 rotations; a random rotation lies a median 12 degrees (at most about 22) from the
    nearest."""
    from sc6d_jax.geometry import so3_grid

    if not isinstance(size, (int, np.integer)) or size < 8:
        raise ValueError(f"rot_cls_grid: size must be an int >= 8, got {size!r}")
    n_in = max(2, int(round((np.pi * size) ** (1.0 / 3.0))))
    n_views = max(4, int(round(size / n_in)))
    g = np.asarray(so3_grid(n_views, n_in), np.float32)
    g.setflags(write=False)
    return g


def normalize_rgb(rgb: jax.Array) -> jax.Array:
    """uint8 (0..255) -> float32 in [0, 1]; float input is returned as float32 unchanged."""
    if jnp.issubdtype(rgb.dtype, jnp.integer):
        return rgb.astype(jnp.float32) / 255.0
    return rgb.astype(jnp.float32)


def _check_inputs(cfg: ModelConfig, rgb: jax.Array, pe: jax.Array | None, obj_idx: jax.Array) -> None:
    s = cfg.crop_size
    if rgb.ndim != 4 or rgb.shape[1:] != (s, s, 3):
        raise ValueError(f"rgb must have shape (B, {s}, {s}, 3), got {rgb.shape}")
    b = rgb.shape[0]
    if cfg.use_pe:
        if pe is None or pe.shape != (b, s, s, 2):
            raise ValueError(f"pe must have shape ({b}, {s}, {s}, 2) when use_pe=True, got {None if pe is None else pe.shape}")
    if jnp.shape(obj_idx) != (b,):
        raise ValueError(f"obj_idx must have shape ({b},), got {jnp.shape(obj_idx)}")


def apply(
    params: dict, cfg: ModelConfig, rgb: jax.Array, pe: jax.Array | None, obj_idx: jax.Array,
    teacher_gate: tuple[jax.Array, jax.Array] | None = None,
) -> dict:
    """Forward pass.

    rgb: float32 (B,S,S,3) in [0,1] (uint8 is accepted and divided by 255); it is normalised
    inside with ImageNet mean/std. pe: (B,S,S,2) PE map (ignored, may be None, when
    cfg.use_pe is False). obj_idx: int (B,) object index in [0, n_objects).
    teacher_gate: training only, with cfg.mask_gate: ``(mask (B,S/4,S/4) in [0, 1], on (B,)
    bool)``: the samples where ``on`` is set gate their features with this (ground-truth) mask
    instead of the predicted one.

    Returns {'rot_emb' (B,emb_dim) unit-norm image embedding, 'delta_xy' (B,2),
    'z_logits' (B,n_z_bins), 'mask_logit' (B,S/4,S/4)}, and 'dense' (B,S/4,S/4,4) with
    cfg.dense_head ((B,S/4,S/4,7) with cfg.dense_xyz), 'rot_6d' (B,6) with cfg.rot_readout,
    'rot_cls_logits' (B,N) with cfg.rot_cls (N = len(rot_cls_grid(cfg.rot_cls))), 'view' (B,V,V,3)
    with cfg.view_head = V (the clean view in [0, 1] units, unbounded).
    """
    _check_inputs(cfg, rgb, pe, obj_idx)
    obj_idx = jnp.asarray(obj_idx, jnp.int32)
    x = (normalize_rgb(rgb) - jnp.asarray(RGB_MEAN)) / jnp.asarray(RGB_STD)
    if cfg.use_pe:
        x = jnp.concatenate([x, pe.astype(jnp.float32)], axis=-1)
    feats = backbone(params["backbone"], cfg, x)
    feat, mask_logit = decoder(params["decoder"], cfg, feats, obj_idx)
    extra = {}
    if cfg.dense_head:
        extra["dense"] = dense(feat, params["dense_head"]["w"], params["dense_head"]["b"])
    feat_ungated = feat
    if cfg.mask_gate:
        gate = jax.nn.sigmoid(mask_logit)
        if teacher_gate is not None:
            mask, on = teacher_gate
            gate = jnp.where(jnp.asarray(on)[:, None, None], jnp.asarray(mask, gate.dtype), gate)
        feat = feat * gate[..., None]
    rot, dxy, zl, h_rot, map_rot, block = pose_decoder(params["pose_decoder"], cfg, feat, mask_logit,
                                                pe if cfg.use_pe else None, return_hidden=True, return_map=True,
                                                obj_idx=obj_idx)
    emb = _l2n(rot)
    if cfg.rot_cls:
        rc = params["rot_cls"]
        extra["rot_cls_logits"] = jnp.einsum("bh,bhk->bk", h_rot, rc["w"][obj_idx]) + rc["b"][obj_idx]
    if cfg.view_head:
        v, V = params["view_head"], cfg.view_head
        if cfg.view_per_object:
            v = {"w": v["w"][obj_idx], "b": v["b"][obj_idx]}
        if cfg.view_from in ("map", "block"):  # each cell of the map to its patch of the view
            src = map_rot if cfg.view_from == "map" else block
            b_, m = src.shape[0], src.shape[1]
            q = V // m
            y = dense(src, v["w"], v["b"]).reshape(b_, m, m, q, q, 3)
            extra["view"] = jnp.transpose(y, (0, 1, 3, 2, 4, 5)).reshape(b_, V, V, 3)
        else:
            extra["view"] = dense(h_rot, v["w"], v["b"]).reshape(h_rot.shape[0], V, V, 3)
    if cfg.rot_readout:
        ro = params["rot_readout"]
        extra["rot_6d"] = jnp.einsum("be,bes->bs", emb, ro["w"][obj_idx]) + ro["b"][obj_idx]
    if cfg.xy_vote:  # the decoder's features before the mask gate, or the dilated block
        v, src = params["xy_vote"], feat_ungated if cfg.xy_vote_from == "feat" else block
        extra["xy_votes"] = dense(conv_gn_relu(src, v["conv"], cfg), v["out"]["w"], v["out"]["b"])
        dxy = vote_delta_xy(extra["xy_votes"], mask_logit)
    return {"rot_emb": emb, "delta_xy": dxy, "z_logits": zl, "mask_logit": mask_logit, **extra}


def with_rotation_priors(params: dict, cfg: ModelConfig, out: dict, R_allo: jax.Array, obj_idx: jax.Array) -> dict:
    """``out`` with the rotation's priors: the depth prior added to its z logits (``cfg.z_rot``)
    and the centre's offset added to its delta_xy (``cfg.xy_rot``); unchanged without them.
    R_allo (B,3,3): the allocentric rotation each crop is decoded with (the ground truth in
    training, the matched rotation at inference), in the crop's own frame."""
    if not (cfg.z_rot or cfg.xy_rot):
        return out
    out = dict(out)
    if cfg.z_rot:
        out["z_logits"] = out["z_logits"] + rotation_prior_output(params["z_rot"], R_allo, obj_idx)
    if cfg.xy_rot:
        out["delta_xy"] = out["delta_xy"] + rotation_prior_output(params["xy_rot"], R_allo, obj_idx)
    return out


def count_params(params: dict) -> int:
    """Total number of scalars in a params pytree."""
    return int(sum(x.size for x in jax.tree.leaves(params)))
