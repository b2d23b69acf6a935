"""The jitted pose predictor: crops in, poses out (network, library matching, TTA, refinement).

:func:`predict_crops` is a pure function of the parameters, the packed rotation library and a
batch of crops; everything that changes the computation (model config, flags, library size) is
static. It is shared by :class:`sc6d_jax.Estimator` and by the exported predictor.

Test-time augmentation follows the authors: each crop is rotated by 0/90/180/270 degrees
(one batch of 4B; the PE map is NOT rotated, unless the model was trained with
``pe_turns``: then it turns with each copy, ``turn_pe``). Rotating the crop content by ``np.rot90(crop,
k=-k)`` (clockwise on screen, since image y points down) is what the camera sees when the object
turns by ``Rz(90k)`` about the optical axis, i.e. the training augmentation
``R_allo <- Rz(90k) R_allo``, ``delta_xy <- Rz2(90k) delta_xy``. The delta_xy are rotated back
and averaged, the delta_z averaged. The rotation, by ``tta_mode``:

- ``"best"`` (the authors'): each copy's top-1 rotation is rotated back (``Rz(-90k) R``) and the
  one of the copy with the highest cosine is taken.
- ``"fuse"`` (the default): each copy's top ``tta_candidates`` rotations, rotated back, are pooled
  (4 x tta_candidates per crop) and each candidate R is scored by all four copies at once, the
  mean over k of ``cos(f_k, g(Rz(90k) R))``; the best candidate wins (and is what ``refine``
  refines, on the same mean). Its ``score`` is that mean cosine, its ``prob`` the mean over the
  copies of its softmax probability over the library. Four looks at the object vote on every candidate instead of one
  look choosing alone: on 390 rendered targets of the built-in objects AR 0.433 without TTA,
  0.453 with "best", 0.490 with "fuse" (README, "Test-time augmentation"). A model with the
  rotation's priors (``model.z_rot``, ``model.xy_rot``) decodes each copy's depth and centre with
  the fused rotation turned into the copy's frame, not the copy's own top-1 match: with
  ``xy_rot``, the one-hour 14-object model gains +0.008 +- 0.002 (390 targets) and +0.019 +- 0.007
  (the demo's 60), paired.
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp

from sc6d_jax.geometry import allocentric_to_egocentric, crop_transform, decode_translation, pe_map, turn_pe
from sc6d_jax.inference._matching import match_library
from sc6d_jax.inference._refine import refine_rotations

_RZ90 = ((0.0, -1.0, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0))


def rz90(k: int, dtype=jnp.float32) -> jax.Array:
    """Exact ``Rz(90 k degrees)`` (3x3)."""
    R = jnp.eye(3, dtype=dtype)
    for _ in range(k % 4):
        R = jnp.asarray(_RZ90, dtype) @ R
    return R


def rotate_crops(rgb: jax.Array, k: int) -> jax.Array:
    """Crops (B,S,S,C) as seen after the object turns by ``Rz(90k)`` (``rot90`` clockwise k times)."""
    return jnp.rot90(rgb, k=-k, axes=(1, 2))


TTA_MODES = ("fuse", "best")


def _fuse_copies(head: dict, mcfg: Any, emb: jax.Array, R_cand: jax.Array, log_z: jax.Array, tau: float,
                 obj_idx: jax.Array, top_k: int, refine: bool) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Fused TTA: ``emb`` (4,B,E) the copies' crop embeddings, ``R_cand`` (4,B,M,3,3) each copy's
    top-M library rotations in its own frame, ``log_z`` (4,B) each copy's log softmax normaliser
    over the library. Returns the top_k allocentric rotations (B,k,3,3) among the 4M pooled
    candidates (in the crop's frame) by the copies' mean cosine, those means (B,k), and the mean
    over the copies of each one's softmax probability over the library (B,k); with ``refine``, the
    best one refined by BFGS on the same mean (its probability from the library pick)."""
    C, B, M = R_cand.shape[:3]
    undo = jnp.stack([rz90(-k) for k in range(C)])
    redo = jnp.stack([rz90(k) for k in range(C)])
    cand = jnp.swapaxes(undo[:, None, None] @ R_cand, 0, 1).reshape(B, C * M, 3, 3)
    from sc6d_jax.model import encode_rotations

    mean_cos, mean_prob = 0.0, 0.0
    for k in range(C):
        g = encode_rotations(head, mcfg, redo[k] @ cand, obj_idx[:, None])  # (B,CM,E)
        cos_k = jnp.einsum("bme,be->bm", g, emb[k].astype(g.dtype))
        mean_cos = mean_cos + cos_k / C
        mean_prob = mean_prob + jnp.exp(cos_k / tau - log_z[k][:, None]) / C
    score, j = jax.lax.top_k(mean_cos, top_k)
    prob = jnp.take_along_axis(mean_prob, j, axis=1)
    R_k = jnp.take_along_axis(cand, j[:, :, None, None], axis=1)
    if refine:  # the concatenated copies' embeddings, scaled to unit norm: their dot is the mean cosine
        scale = 1.0 / jnp.sqrt(jnp.float32(C))
        embed = lambda R, o: scale * jnp.concatenate([encode_rotations(head, mcfg, redo[k] @ R, o) for k in range(C)])
        query = scale * jnp.swapaxes(emb, 0, 1).reshape(B, -1)
        R1, c1 = refine_rotations(embed, query, R_k[:, 0], obj_idx)
        R_k, score = R_k.at[:, 0].set(R1), score.at[:, 0].set(c1)
    return R_k, score, prob


def _z_decode(out: dict, lcfg: Any, z_range: tuple[float, float], K: jax.Array) -> jax.Array:
    from sc6d_jax.model import decode_delta_z

    return decode_delta_z(out, lcfg, z_range, K)


@functools.partial(
    jax.jit,
    static_argnames=("mcfg", "lcfg", "z_range", "n_valid", "tta", "top_k", "refine", "tau", "tta_mode",
                     "tta_candidates"),
)
def predict_crops(
    params: dict,
    lib_blocks: jax.Array,
    lib_R: jax.Array,
    rgb: jax.Array,
    K: jax.Array,
    center: jax.Array,
    side: jax.Array,
    obj_idx: jax.Array,
    *,
    mcfg: Any,
    lcfg: Any,
    z_range: tuple[float, float],
    n_valid: int,
    tta: bool = False,
    top_k: int = 1,
    refine: bool = False,
    tau: float = 0.1,
    tta_mode: str = "fuse",
    tta_candidates: int = 8,
) -> dict[str, jax.Array]:
    """Poses for B crops.

    Args:
        params: model parameters.
        lib_blocks: per-object library blocks ``(O, nb, E, block)`` (:func:`pack_library`), or for an
            Implicit-PDF model the rotations' encodings ``(1, nb, D, block)``; lib_R ``(N,3,3)``.
        rgb: uint8 crops ``(B,S,S,3)`` warped with ``T = crop_transform(center, side, S)``.
        K: ``(B,3,3)`` image intrinsics; center ``(B,2)``, side ``(B,)``: the crop boxes.
        obj_idx: ``(B,)`` object index of the model.
        tta: 4-fold in-plane test-time augmentation; ``tta_mode`` "fuse" (pooled candidates
            scored by all copies, ``tta_candidates`` per copy) or "best" (the authors': the copy
            with the highest top-1 cosine); see the module docstring.

    Returns:
        dict with ``R`` (B,3,3) egocentric, ``t`` (B,3) mm, ``score`` (B,) cosine of the best
        rotation, ``prob`` (B,) its softmax probability over the library, ``R_topk`` (B,k,3,3)
        egocentric, ``score_topk`` / ``prob_topk`` (B,k), ``R_allo`` (B,3,3), ``delta_xy``,
        ``delta_z``.
    """
    if tta_mode not in TTA_MODES:
        raise ValueError(f"tta_mode must be one of {TTA_MODES}, got {tta_mode!r}")
    fuse = bool(tta) and tta_mode == "fuse"
    if fuse and mcfg.rot_head == "ipdf":
        raise ValueError("tta_mode='fuse' needs the SO(3) encoder (rot_head='so3'); this model has an "
                         "Implicit-PDF head: use tta_mode='best'")
    if fuse and not 1 <= tta_candidates <= n_valid:
        raise ValueError(f"tta_candidates must be in [1, {n_valid}], got {tta_candidates!r}")
    S = mcfg.crop_size
    B = rgb.shape[0]
    f32 = jnp.float32
    K, center, side = K.astype(f32), center.astype(f32), side.astype(f32)
    obj_idx = obj_idx.astype(jnp.int32)
    T = crop_transform(center, side, S)
    pe = pe_map(K, T, S)
    n_copies = 4 if tta else 1
    if tta:
        rgb_in = jnp.concatenate([rotate_crops(rgb, k) for k in range(4)], axis=0)
        # the PE map turns with each copy if the model was trained so (mcfg.pe_turns), else not
        pe_in = jnp.concatenate([turn_pe(pe, k) if mcfg.pe_turns else pe for k in range(4)], axis=0)
        obj_in = jnp.concatenate([obj_idx] * 4, axis=0)
    else:
        rgb_in, pe_in, obj_in = rgb, pe, obj_idx

    from sc6d_jax.model import apply, encode_rotations, with_rotation_priors

    out = apply(params, mcfg, rgb_in, pe_in if mcfg.use_pe else None, obj_in)
    emb = out["rot_emb"].astype(f32)
    K_in = jnp.concatenate([K] * n_copies, axis=0)
    if refine and mcfg.rot_head == "ipdf":
        raise ValueError("refine needs the SO(3) encoder (rot_head='so3'); this model has an Implicit-PDF head")
    k_match = max(top_k, tta_candidates) if fuse else top_k
    m = match_library(params["rot_head"], mcfg.rot_head, emb, lib_blocks, n_valid, k_match, tau, True, obj_in)
    # the rotation the priors (model.z_rot, xy_rot) read, in each copy's frame: the copy's own top-1
    R_prior = lib_R[m.index[:, 0]]
    idx = m.index.reshape(n_copies, B, k_match)
    score = m.score.reshape(n_copies, B, k_match)
    prob = m.prob.reshape(n_copies, B, k_match)
    emb = emb.reshape(n_copies, B, -1)

    undo = jnp.stack([rz90(-k) for k in range(n_copies)])  # (C,3,3): undo each copy's in-plane turn
    head = params["rot_head"]
    if fuse:
        # each copy's log normaliser over the library, from its top-1 cosine and probability
        log_z = score[:, :, 0] / tau - jnp.log(jnp.maximum(prob[:, :, 0], 1e-30))
        R_allo_k, score_b, prob_b = _fuse_copies(head, mcfg, emb, lib_R[idx], log_z, tau, obj_idx, top_k, refine)
        # fused, the priors read the fused rotation (the better estimate) turned into each copy's frame
        redo = jnp.swapaxes(undo, -1, -2)
        R_prior = (redo[:, None] @ R_allo_k[None, :, 0]).reshape(n_copies * B, 3, 3)
    else:
        # the best copy per crop (by top-1 cosine)
        best = jnp.argmax(score[:, :, 0], axis=0) if tta else jnp.zeros((B,), jnp.int32)
        take = lambda a: jnp.take_along_axis(a, best.reshape((1, B) + (1,) * (a.ndim - 2)), axis=0)[0]
        idx_b, score_b, prob_b, emb_b = take(idx), take(score), take(prob), take(emb)
        undo_b = undo[best]  # (B,3,3)
        R_copy = lib_R[idx_b]  # (B,k,3,3) in the best copy's frame
        if refine:
            embed = lambda R, o: encode_rotations(head, mcfg, R, o)
            R1, c1 = refine_rotations(embed, emb_b, R_copy[:, 0], obj_idx)
            R_copy = R_copy.at[:, 0].set(R1)
            score_b = score_b.at[:, 0].set(c1)
        R_allo_k = undo_b[:, None] @ R_copy  # (B,k,3,3)
    out = with_rotation_priors(params, mcfg, out, R_prior, obj_in)  # unchanged without the priors
    dxy = out["delta_xy"].astype(f32).reshape(n_copies, B, 2)
    dz = _z_decode(out, lcfg, z_range, K_in).astype(f32).reshape(n_copies, B)
    undo2 = undo[:, :2, :2]  # (C,2,2)
    dxy_mean = jnp.mean(jnp.einsum("cij,cbj->cbi", undo2, dxy), axis=0)
    dz_mean = jnp.mean(dz, axis=0)
    t = decode_translation(dxy_mean, dz_mean, K, center, side, S)
    R_topk = allocentric_to_egocentric(R_allo_k, t[:, None, :])
    return {
        "R": R_topk[:, 0],
        "t": t,
        "score": score_b[:, 0],
        "prob": prob_b[:, 0],
        "R_topk": R_topk,
        "score_topk": score_b,
        "prob_topk": prob_b,
        "R_allo": R_allo_k[:, 0],
        "delta_xy": dxy_mean,
        "delta_z": dz_mean,
    }
