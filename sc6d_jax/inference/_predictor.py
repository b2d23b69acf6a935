"""The jitted pose predictor: crops in, poses out (network, library matching, TTA, refinement).

:func:`predict_crops` is a pure function of the parameters, the packed rotation library and a
batch of crops; everything that changes the computation (model config, flags, library size) is
static. It is shared by :class:`sc6d_jax.Estimator` and by the exported predictor.

Test-time augmentation follows the authors: each crop is rotated by 0/90/180/270 degrees
(one batch of 4B; the PE map is NOT rotated). Rotating the crop content by ``np.rot90(crop,
k=-k)`` (clockwise on screen, since image y points down) is what the camera sees when the object
turns by ``Rz(90k)`` about the optical axis, i.e. the training augmentation
``R_allo <- Rz(90k) R_allo``, ``delta_xy <- Rz2(90k) delta_xy``. Each copy's top-1 rotation is
rotated back (``Rz(-90k) R``), the delta_xy are rotated back and averaged, the delta_z averaged,
and the rotation is taken from the copy with the highest cosine.
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp

from sc6d_jax.geometry import allocentric_to_egocentric, crop_transform, decode_translation, pe_map
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


def _z_decode(out: dict, lcfg: Any, z_range: tuple[float, float], K: jax.Array) -> jax.Array:
    from sc6d_jax.model import decode_delta_z

    return decode_delta_z(out, lcfg, z_range, K)


@functools.partial(
    jax.jit,
    static_argnames=("mcfg", "lcfg", "z_range", "n_valid", "tta", "top_k", "refine", "tau"),
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
) -> dict[str, jax.Array]:
    """Poses for B crops.

    Args:
        params: model parameters.
        lib_blocks: per-object library blocks ``(O, nb, E, block)`` (:func:`pack_library`), or for an
            Implicit-PDF model the rotations' encodings ``(1, nb, D, block)``; lib_R ``(N,3,3)``.
        rgb: uint8 crops ``(B,S,S,3)`` warped with ``T = crop_transform(center, side, S)``.
        K: ``(B,3,3)`` image intrinsics; center ``(B,2)``, side ``(B,)``: the crop boxes.
        obj_idx: ``(B,)`` object index of the model.

    Returns:
        dict with ``R`` (B,3,3) egocentric, ``t`` (B,3) mm, ``score`` (B,) cosine of the best
        rotation, ``prob`` (B,) its softmax probability over the library, ``R_topk`` (B,k,3,3)
        egocentric, ``score_topk`` / ``prob_topk`` (B,k), ``R_allo`` (B,3,3), ``delta_xy``,
        ``delta_z``.
    """
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
        pe_in = jnp.concatenate([pe] * 4, axis=0)  # the PE map is not rotated
        obj_in = jnp.concatenate([obj_idx] * 4, axis=0)
    else:
        rgb_in, pe_in, obj_in = rgb, pe, obj_idx

    from sc6d_jax.model import apply, encode_rotations, with_z_prior

    out = apply(params, mcfg, rgb_in, pe_in if mcfg.use_pe else None, obj_in)
    emb = out["rot_emb"].astype(f32)
    K_in = jnp.concatenate([K] * n_copies, axis=0)
    dxy = out["delta_xy"].astype(f32).reshape(n_copies, B, 2)
    if refine and mcfg.rot_head == "ipdf":
        raise ValueError("refine needs the SO(3) encoder (rot_head='so3'); this model has an Implicit-PDF head")
    m = match_library(params["rot_head"], mcfg.rot_head, emb, lib_blocks, n_valid, top_k, tau, True, obj_in)
    # each copy's depth with its own matched rotation (in the copy's frame) as the depth prior's input
    out = with_z_prior(params, mcfg, out, lib_R[m.index[:, 0]], obj_in)
    dz = _z_decode(out, lcfg, z_range, K_in).astype(f32).reshape(n_copies, B)
    idx = m.index.reshape(n_copies, B, top_k)
    score = m.score.reshape(n_copies, B, top_k)
    prob = m.prob.reshape(n_copies, B, top_k)
    emb = emb.reshape(n_copies, B, -1)

    # best copy per crop (by top-1 cosine); undo each copy's in-plane turn
    best = jnp.argmax(score[:, :, 0], axis=0) if tta else jnp.zeros((B,), jnp.int32)
    undo = jnp.stack([rz90(-k) for k in range(n_copies)])  # (C,3,3)
    take = lambda a: jnp.take_along_axis(a, best.reshape((1, B) + (1,) * (a.ndim - 2)), axis=0)[0]
    idx_b, score_b, prob_b, emb_b = take(idx), take(score), take(prob), take(emb)
    undo_b = undo[best]  # (B,3,3)
    R_copy = lib_R[idx_b]  # (B,k,3,3) in the best copy's frame
    if refine:
        head = params["rot_head"]
        embed = lambda R, o: encode_rotations(head, mcfg, R, o)
        R1, c1 = refine_rotations(embed, emb_b, R_copy[:, 0], obj_idx)
        R_copy = R_copy.at[:, 0].set(R1)
        score_b = score_b.at[:, 0].set(c1)
    R_allo_k = undo_b[:, None] @ R_copy  # (B,k,3,3)
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
