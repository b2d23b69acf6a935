"""Rotation heads: the SO(3) encoder (paper) and an Implicit-PDF style scorer (ablation).

Both are reached through :func:`rotation_logits`, so losses and inference do not care which
head a model uses.

* ``rot_head="so3"``: R (row-major 9 values, plus sin/cos(2^k pi r) for k < so3_pe_freqs) -> FC so3_hidden -> ReLU -> FC so3_hidden ->
  ReLU -> per-object FC emb_dim, L2-normalised. logit = cos(image emb, rotation emb) / tau.
* ``rot_head="ipdf"`` (Murphy et al. 2021; the authors' ``IPDF_Encoder``): a per-object MLP
  on [image embedding, rotation encoding] -> ipdf_hidden -> ReLU -> ipdf_hidden -> ReLU -> 1.
  The first layer is split into an image part (computed once per sample) and a rotation
  part (once per candidate). The rotation encoding is the 9 matrix entries, plus
  sin/cos(2^k pi r) for k < ipdf_pe_freqs. logit = MLP output (tau is not applied: the
  scorer learns its own scale).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ._config import ModelConfig
from ._layers import dense, init_dense, split, stack_trees


def _l2n(x: jax.Array, eps: float = 1e-8) -> jax.Array:
    return x / jnp.sqrt(jnp.sum(jnp.square(x), axis=-1, keepdims=True) + eps)


def rotation_features(R: jax.Array, n_freqs: int = 0) -> jax.Array:
    """Row-major flattening of R (...,3,3) -> (...,9), plus optional sin/cos encodings."""
    x = R.reshape(*R.shape[:-2], 9)
    if n_freqs <= 0:
        return x
    freqs = (2.0 ** jnp.arange(n_freqs, dtype=x.dtype)) * jnp.pi
    ang = x[..., None, :] * freqs[:, None]
    enc = jnp.concatenate([jnp.sin(ang), jnp.cos(ang)], axis=-2).reshape(*x.shape[:-1], 18 * n_freqs)
    return jnp.concatenate([x, enc], axis=-1)


def _init_stacked_dense(key: np.random.Generator, n: int, cin: int, cout: int, scale: float = 2.0) -> dict:
    return stack_trees([init_dense(k, cin, cout, scale) for k in split(key, n)])


def init_rotation_head(key: np.random.Generator, cfg: ModelConfig) -> dict:
    k1, k2, k3 = split(key, 3)
    if cfg.rot_head == "so3":
        h = cfg.so3_hidden
        return {
            "fc1": init_dense(k1, 9 * (1 + 2 * cfg.so3_pe_freqs), h),
            "fc2": init_dense(k2, h, h),
            "out": _init_stacked_dense(k3, cfg.n_objects, h, cfg.emb_dim, scale=1.0),
        }
    h = cfg.ipdf_hidden
    d_rot = 9 * (1 + 2 * cfg.ipdf_pe_freqs)
    k4, k5 = split(k3, 2)
    rot_in = _init_stacked_dense(k1, cfg.n_objects, d_rot, h)
    img_in = _init_stacked_dense(k2, cfg.n_objects, cfg.emb_dim, h)
    return {
        "rot_in": {"w": rot_in["w"], "b": rot_in["b"]},
        "img_in": {"w": img_in["w"]},
        "hidden": _init_stacked_dense(k4, cfg.n_objects, h, h),
        "out": _init_stacked_dense(k5, cfg.n_objects, h, 1, scale=1.0),
    }


def init_rotation_prior(key: np.random.Generator, cfg: ModelConfig, out_dim: int | None = None) -> dict:
    """Per-object MLP 9 -> head_hidden -> head_hidden -> out_dim (default n_z_bins); the output
    layer starts at zero, so a fresh prior adds nothing to what it is added to."""
    k1, k2, k3 = split(key, 3)
    n, h = cfg.n_objects, cfg.head_hidden
    out = _init_stacked_dense(k3, n, h, cfg.n_z_bins if out_dim is None else out_dim, scale=1.0)
    return {"fc1": _init_stacked_dense(k1, n, 9, h), "fc2": _init_stacked_dense(k2, n, h, h),
            "out": {"w": np.zeros_like(out["w"]), "b": out["b"]}}


def rotation_prior_output(p: dict, R: jax.Array, obj_idx: jax.Array) -> jax.Array:
    """(B, out_dim) output of a rotation prior (``init_rotation_prior``) for rotations R (B,3,3) of
    objects obj_idx (B,): the depth prior's z logits (``model.z_rot``) or the centre's offset
    (``model.xy_rot``)."""
    obj = jnp.asarray(obj_idx, jnp.int32)
    sel = jax.tree.map(lambda a: a[obj], p)
    x = R.reshape(R.shape[0], 9).astype(jnp.float32)
    h = jax.nn.relu(jnp.einsum("bi,bih->bh", x, sel["fc1"]["w"]) + sel["fc1"]["b"])
    h = jax.nn.relu(jnp.einsum("bi,bih->bh", h, sel["fc2"]["w"]) + sel["fc2"]["b"])
    return jnp.einsum("bi,bih->bh", h, sel["out"]["w"]) + sel["out"]["b"]


def encode_rotations(params: dict, cfg: ModelConfig, R: jax.Array, obj_idx: jax.Array | int) -> jax.Array:
    """SO(3) encoder: unit embeddings (..., emb_dim) of rotations R (..., 3, 3) for object(s) obj_idx.

    ``obj_idx`` is an int (one object for all R) or an int array broadcastable against
    ``R.shape[:-2]`` (e.g. (B,) with R (B,3,3), or (B,1) with R (B,Q,3,3)).
    Accepts the full model params or the rotation-head params. Only for rot_head="so3".
    """
    if cfg.rot_head != "so3":
        raise ValueError("encode_rotations needs rot_head='so3' (IPDF has no rotation embedding)")
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"R must have shape (..., 3, 3), got {R.shape}")
    p = params.get("rot_head", params)
    h = _hidden(p, cfg, R)
    obj = jnp.asarray(obj_idx, jnp.int32)
    w = p["out"]["w"][obj]  # (...,h,E)
    b = p["out"]["b"][obj]
    if obj.ndim == 0:
        e = h @ w + b
    else:
        e = jnp.einsum("...h,...he->...e", h, w) + b
    return _l2n(e)


def _hidden(p: dict, cfg: ModelConfig, R: jax.Array) -> jax.Array:
    x = rotation_features(R, cfg.so3_pe_freqs)
    h = jax.nn.relu(dense(x, p["fc1"]["w"], p["fc1"]["b"]))
    return jax.nn.relu(dense(h, p["fc2"]["w"], p["fc2"]["b"]))


def rotation_logits(
    params: dict,
    cfg: ModelConfig,
    out: dict,
    R_candidates: jax.Array,
    obj_idx: jax.Array,
    tau: float = 0.1,
) -> jax.Array:
    """Logits (B, Q) of candidate rotations for each sample of a forward pass ``out``.

    R_candidates: (Q,3,3) shared by the batch, or (B,Q,3,3) per sample. so3 head: cosine
    between the image embedding and the rotation embedding divided by ``tau``; ipdf head:
    the scorer's output. For shared candidates the embeddings are computed once per object
    (when n_objects <= B) instead of once per sample.
    """
    img = out["rot_emb"]
    b = img.shape[0]
    obj_idx = jnp.asarray(obj_idx, jnp.int32)
    if R_candidates.shape[-2:] != (3, 3) or R_candidates.ndim not in (3, 4):
        raise ValueError(f"R_candidates must be (Q,3,3) or (B,Q,3,3), got {R_candidates.shape}")
    if R_candidates.ndim == 4 and R_candidates.shape[0] != b:
        raise ValueError(f"R_candidates batch {R_candidates.shape[0]} != image batch {b}")
    if obj_idx.shape != (b,):
        raise ValueError(f"obj_idx must have shape ({b},), got {obj_idx.shape}")
    p = params.get("rot_head", params)
    if cfg.rot_head == "so3":
        return _so3_logits(p, cfg, img, R_candidates, obj_idx) / tau
    return _ipdf_logits(p, cfg, img, R_candidates, obj_idx)


def _so3_logits(p: dict, cfg: ModelConfig, img: jax.Array, R: jax.Array, obj_idx: jax.Array) -> jax.Array:
    h = _hidden(p, cfg, R)  # (Q,H) or (B,Q,H)
    n_obj = cfg.n_objects
    if R.ndim == 3 and (n_obj == 1 or n_obj <= img.shape[0]):
        # embeddings of the shared set once per object, then pick each sample's object
        emb = _l2n(jnp.einsum("qh,ohe->oqe", h, p["out"]["w"]) + p["out"]["b"][:, None, :])  # (O,Q,E)
        if n_obj == 1:
            return img @ emb[0].T
        logits = jnp.einsum("be,oqe->boq", img, emb)
        return jnp.take_along_axis(logits, obj_idx[:, None, None], axis=1)[:, 0]
    w = p["out"]["w"][obj_idx]  # (B,H,E)
    bias = p["out"]["b"][obj_idx]  # (B,E)
    if R.ndim == 3:
        emb = jnp.einsum("qh,bhe->bqe", h, w)
    else:
        emb = jnp.einsum("bqh,bhe->bqe", h, w)
    emb = _l2n(emb + bias[:, None, :])
    return jnp.einsum("be,bqe->bq", img, emb)


def _ipdf_logits(p: dict, cfg: ModelConfig, img: jax.Array, R: jax.Array, obj_idx: jax.Array) -> jax.Array:
    feats = rotation_features(R, cfg.ipdf_pe_freqs)  # (Q,D) or (B,Q,D)
    if cfg.n_objects == 1:
        sel = jax.tree.map(lambda a: a[0], p)
        a_img = img @ sel["img_in"]["w"]  # (B,H)
        a_rot = feats @ sel["rot_in"]["w"] + sel["rot_in"]["b"]  # (Q,H) / (B,Q,H)
        h = jax.nn.relu(a_img[:, None, :] + a_rot)
        h = jax.nn.relu(h @ sel["hidden"]["w"] + sel["hidden"]["b"])
        return (h @ sel["out"]["w"] + sel["out"]["b"])[..., 0]
    sel = jax.tree.map(lambda a: a[obj_idx], p)  # leaves (B, ...)
    a_img = jnp.einsum("be,beh->bh", img, sel["img_in"]["w"])
    if R.ndim == 3:
        a_rot = jnp.einsum("qd,bdh->bqh", feats, sel["rot_in"]["w"])
    else:
        a_rot = jnp.einsum("bqd,bdh->bqh", feats, sel["rot_in"]["w"])
    h = jax.nn.relu(a_img[:, None, :] + a_rot + sel["rot_in"]["b"][:, None, :])
    h = jax.nn.relu(jnp.einsum("bqh,bhk->bqk", h, sel["hidden"]["w"]) + sel["hidden"]["b"][:, None, :])
    return (jnp.einsum("bqh,bho->bqo", h, sel["out"]["w"]) + sel["out"]["b"][:, None, :])[..., 0]
