"""Scale-invariant translation encoding (SC6D): ``t <-> (delta_xy, delta_z)`` and the z bins.

With the crop box of centre ``c`` and side ``s_B`` warped to ``S x S`` (``r = S / s_B``):

* ``delta_xy = (p - c) / s_B`` where ``p = proj_K(t)`` is the image projection of the origin;
* ``delta_z = t_z / r``.

Decoding is the exact inverse: ``p = c + s_B delta_xy``, ``t_z = r delta_z``,
``t = t_z K^-1 (p, 1)``. This equals the REFERENCE formula
``t = r delta_z K_B^-1 (S delta_x, S delta_y, 1)`` for the authors' ``K_B``, which maps the box
centre to crop pixel 0; with this project's ``T`` (box centre -> ``(S - 1)/2``) the crop pixel
is ``(S - 1)/2 + S delta_xy`` instead.

Depth bins: ``n_bins`` values spaced evenly over ``[d_lo, d_hi]`` *including* both ends
(``linspace``); the label is the nearest bin (clipped), the decode is the softmax expectation.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
from jax import Array
from jax.typing import ArrayLike

from sc6d_jax.geometry._rotations import _as_float
from sc6d_jax.geometry._validate import _check_trailing, _is_concrete, validate_K, validate_positive, validate_size


def _check_range(d_lo: float, d_hi: float) -> None:
    if _is_concrete(d_lo, d_hi) and not float(d_lo) < float(d_hi):
        raise ValueError(f"z range must satisfy d_lo < d_hi, got d_lo={d_lo}, d_hi={d_hi}")


def encode_translation(
    t: ArrayLike, K: ArrayLike, center: ArrayLike, side: ArrayLike, out_size: int
) -> tuple[Array, Array]:
    """``t[..., 3]`` (mm) -> ``(delta_xy[..., 2], delta_z[...])`` for the crop ``(center, side)``."""
    out_size = validate_size(out_size, "out_size")
    _check_trailing(t, (3,), "t")
    _check_trailing(K, (3, 3), "K")
    _check_trailing(center, (2,), "center")
    if _is_concrete(K, side):
        validate_K(K)
        validate_positive(side, "side")
    return _encode_translation(t, K, center, side, out_size)


@partial(jax.jit, static_argnames="out_size")
def _encode_translation(t, K, center, side, out_size: int) -> tuple[Array, Array]:
    t = _as_float(t)
    K = jnp.asarray(K, t.dtype)
    center = jnp.asarray(center, t.dtype)
    side = jnp.asarray(side, t.dtype)
    h = jnp.einsum("...ij,...j->...i", K, t)
    p = h[..., :2] / h[..., 2:3]
    delta_xy = (p - center) / side[..., None]
    delta_z = t[..., 2] * side / out_size
    return delta_xy, delta_z


def decode_translation(
    delta_xy: ArrayLike, delta_z: ArrayLike, K: ArrayLike, center: ArrayLike, side: ArrayLike, out_size: int
) -> Array:
    """Exact inverse of :func:`encode_translation`: ``(delta_xy, delta_z) -> t[..., 3]`` (mm)."""
    out_size = validate_size(out_size, "out_size")
    _check_trailing(delta_xy, (2,), "delta_xy")
    _check_trailing(K, (3, 3), "K")
    _check_trailing(center, (2,), "center")
    if _is_concrete(K, side):
        validate_K(K)
        validate_positive(side, "side")
    return _decode_translation(delta_xy, delta_z, K, center, side, out_size)


@partial(jax.jit, static_argnames="out_size")
def _decode_translation(delta_xy, delta_z, K, center, side, out_size: int) -> Array:
    delta_xy = _as_float(delta_xy)
    dt = delta_xy.dtype
    delta_z, K = jnp.asarray(delta_z, dt), jnp.asarray(K, dt)
    center, side = jnp.asarray(center, dt), jnp.asarray(side, dt)
    p = center + side[..., None] * delta_xy
    tz = delta_z * out_size / side
    ph = jnp.concatenate([p, jnp.ones_like(p[..., :1])], axis=-1)
    ray = jnp.linalg.solve(K, ph[..., None])[..., 0]
    return tz[..., None] * ray / ray[..., 2:3]


def z_bin_centers(n_bins: int, d_lo: float, d_hi: float, dtype: jnp.dtype = jnp.float32) -> Array:
    """``(n_bins,)`` depth-bin values ``linspace(d_lo, d_hi, n_bins)`` (both ends included)."""
    n_bins = validate_size(n_bins, "n_bins")
    _check_range(d_lo, d_hi)
    return jnp.linspace(d_lo, d_hi, n_bins, dtype=dtype)


def z_bin_label(delta_z: ArrayLike, n_bins: int, d_lo: float, d_hi: float) -> Array:
    """Index (int32, same shape as ``delta_z``) of the nearest bin value; out-of-range values clip."""
    n_bins = validate_size(n_bins, "n_bins")
    _check_range(d_lo, d_hi)
    return _z_bin_label(delta_z, n_bins, d_lo, d_hi)


@partial(jax.jit, static_argnames="n_bins")
def _z_bin_label(delta_z, n_bins: int, d_lo, d_hi) -> Array:
    dz = _as_float(delta_z)
    if n_bins == 1:
        return jnp.zeros(dz.shape, jnp.int32)
    x = (dz - d_lo) / (d_hi - d_lo) * (n_bins - 1)
    return jnp.clip(jnp.round(x), 0, n_bins - 1).astype(jnp.int32)


def z_expectation(logits: ArrayLike, d_lo: float, d_hi: float) -> Array:
    """Soft-argmax decode: ``sum_k softmax(logits)_k * bin_k`` over the last axis (``K`` bins)."""
    logits = _as_float(logits)
    if logits.ndim < 1 or logits.shape[-1] < 1:
        raise ValueError(f"logits must have shape [..., K] with K >= 1, got {logits.shape}")
    _check_range(d_lo, d_hi)
    return _z_expectation(logits, d_lo, d_hi)


@jax.jit
def _z_expectation(logits, d_lo, d_hi) -> Array:
    centers = jnp.linspace(d_lo, d_hi, logits.shape[-1], dtype=logits.dtype)
    return jax.nn.softmax(logits, axis=-1) @ centers
