"""Square crops: crop box, training jitter, image->crop transform T, K_B, PE map, warping.

Pixel convention (OpenCV/BOP): integer pixel coordinates are pixel centres, so an image of
width W covers ``[-0.5, W - 0.5]``. The crop box of centre ``c`` and side ``s_B`` covers
``[c - s_B/2, c + s_B/2]`` and is mapped onto the ``S x S`` crop covering ``[-0.5, S - 0.5]``::

    T = [[r, 0, (S - 1)/2 - r c_x],
         [0, r, (S - 1)/2 - r c_y],
         [0, 0, 1]],        r = S / s_B,

so the box centre lands on the crop centre ``(S - 1)/2`` (the authors' K_B instead maps the box
centre to 0; only the constant differs). ``warp_crop`` hands ``T`` to ``cv2.warpAffine``, which
samples crop pixel ``p`` at image point ``T^-1 p`` with the same pixel-centre convention.
"""

from __future__ import annotations

from functools import partial
from typing import Literal

import cv2
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.typing import ArrayLike

from sc6d_jax.geometry._rotations import _as_float
from sc6d_jax.geometry._validate import (
    _check_trailing,
    _is_concrete,
    validate_boxes,
    validate_K,
    validate_positive,
    validate_size,
)


def crop_box(box_xywh: ArrayLike, pad: float = 1.5) -> tuple[Array, Array]:
    """Square crop around a box: ``center[..., 2] = (x + w/2, y + h/2)``, ``side[...] = pad * max(w, h)``."""
    _check_trailing(box_xywh, (4,), "box_xywh")
    if _is_concrete(box_xywh, pad):
        validate_boxes(box_xywh, name="box_xywh")
        validate_positive(pad, "pad")
    return _crop_box(box_xywh, pad)


@jax.jit
def _crop_box(box_xywh: ArrayLike, pad: float) -> tuple[Array, Array]:
    box = _as_float(box_xywh)
    center = box[..., :2] + box[..., 2:] / 2
    side = jnp.asarray(pad, box.dtype) * jnp.maximum(box[..., 2], box[..., 3])
    return center, side


def jitter_box(
    key: Array, box_xywh: ArrayLike, shift: float = 0.25, scale: tuple[float, float] = (0.75, 1.25)
) -> Array:
    """The authors' training box jitter (dynamic zoom-in), per box independently.

    The centre moves by ``u * (w, h)`` with ``u`` uniform in ``[-shift, shift]^2``, and ``w``, ``h``
    are both multiplied by one factor uniform in ``scale``; returns the jittered ``(x, y, w, h)``.
    Apply :func:`crop_box` (padding 1.5) afterwards.
    """
    _check_trailing(box_xywh, (4,), "box_xywh")
    if _is_concrete(box_xywh):
        validate_boxes(box_xywh, name="box_xywh")
    if _is_concrete(shift, *scale) and (not (0 < scale[0] <= scale[1]) or shift < 0):
        raise ValueError(f"jitter needs shift >= 0 and 0 < scale[0] <= scale[1], got {shift}, {scale}")
    return _jitter_box(key, box_xywh, shift, scale[0], scale[1])


@jax.jit
def _jitter_box(key: Array, box_xywh: ArrayLike, shift: float, lo: float, hi: float) -> Array:
    box = _as_float(box_xywh)
    k1, k2 = jax.random.split(key)
    lead = box.shape[:-1]
    u = jax.random.uniform(k1, lead + (2,), box.dtype, -shift, shift)
    f = jax.random.uniform(k2, lead + (1,), box.dtype, lo, hi)
    wh = box[..., 2:]
    center = box[..., :2] + wh / 2 + u * wh
    new_wh = wh * f
    return jnp.concatenate([center - new_wh / 2, new_wh], axis=-1)


def crop_transform(center: ArrayLike, side: ArrayLike, out_size: int) -> Array:
    """``T[..., 3, 3]`` mapping image pixel coordinates to crop pixel coordinates (see module doc)."""
    out_size = validate_size(out_size, "out_size")
    _check_trailing(center, (2,), "center")
    if _is_concrete(center, side):
        validate_positive(side, "side")
        if not np.all(np.isfinite(np.asarray(center))):
            raise ValueError("center contains NaN or inf")
    return _crop_transform(center, side, out_size)


@partial(jax.jit, static_argnames="out_size")
def _crop_transform(center: ArrayLike, side: ArrayLike, out_size: int) -> Array:
    center = _as_float(center)
    side = jnp.asarray(side, center.dtype)
    r = out_size / side
    off = (out_size - 1) / 2
    lead = jnp.broadcast_shapes(center.shape[:-1], side.shape)
    r = jnp.broadcast_to(r, lead)
    tx = jnp.broadcast_to(off - r * center[..., 0], lead)
    ty = jnp.broadcast_to(off - r * center[..., 1], lead)
    o, one = jnp.zeros(lead, center.dtype), jnp.ones(lead, center.dtype)
    return jnp.stack(
        [jnp.stack([r, o, tx], -1), jnp.stack([o, r, ty], -1), jnp.stack([o, o, one], -1)], -2
    )


def crop_intrinsics(K: ArrayLike, T: ArrayLike) -> Array:
    """``K_B = T @ K``: the intrinsics of the crop (batched)."""
    _check_trailing(K, (3, 3), "K")
    _check_trailing(T, (3, 3), "T")
    if _is_concrete(K):
        validate_K(K)
    return _crop_intrinsics(K, T)


@jax.jit
def _crop_intrinsics(K: ArrayLike, T: ArrayLike) -> Array:
    K, T = _as_float(K), _as_float(T)
    return T @ K


def pe_map(K: ArrayLike, T: ArrayLike, out_size: int) -> Array:
    """Positional-encoding map ``[..., S, S, 2]`` (row = v, column = u of the crop).

    Crop pixel ``p = (u, v)`` came from image point ``(x, y) = T^-1 p``; its entry is that
    pixel's normalised camera ray ``((x - c_x) / f_x, (y - c_y) / f_y)`` (the authors'
    "normalised" PE; computed as ``K^-1 T^-1 p``, which equals it for zero skew). Never rotated.
    """
    out_size = validate_size(out_size, "out_size")
    _check_trailing(K, (3, 3), "K")
    _check_trailing(T, (3, 3), "T")
    if _is_concrete(K):
        validate_K(K)
    return _pe_map(K, T, out_size)


@partial(jax.jit, static_argnames="out_size")
def _pe_map(K: ArrayLike, T: ArrayLike, out_size: int) -> Array:
    K, T = _as_float(K), _as_float(T)
    dtype = jnp.result_type(K.dtype, T.dtype)
    M = jnp.linalg.inv(K.astype(dtype)) @ jnp.linalg.inv(T.astype(dtype))  # crop px -> ray
    s = jnp.arange(out_size, dtype=dtype)
    u = jnp.broadcast_to(s[None, :], (out_size, out_size))
    v = jnp.broadcast_to(s[:, None], (out_size, out_size))
    M = M[..., None, None, :, :]
    ray = M[..., 0] * u[..., None] + M[..., 1] * v[..., None] + M[..., 2]  # [..., S, S, 3]
    return ray[..., :2] / ray[..., 2:3]


def turn_pe(pe: ArrayLike, k: int) -> Array:
    """The PE map ``[..., S, S, 2]`` of a crop turned by ``k`` quarter turns clockwise
    (``rot90(crop, -k)``, the in-plane augmentation and the TTA copies), as the camera rolled by
    ``Rz(90 k)`` about its optical axis would see it: the map's pixels move with the crop and
    each ray turns with the camera, ``(x, y) -> Rz(90 k) (x, y)``. A crop turned with its PE map
    unturned shows an off-axis object's perspective stretch (radial, ``sec`` of the ray's angle)
    along the wrong image axis for its rays. Exact for square pixels (``f_x = f_y``); numpy in,
    numpy out (the stream's workers), jax in, jax out."""
    k = int(k) % 4
    xp = np if isinstance(pe, np.ndarray) else jnp
    nd = np.ndim(pe)
    if nd < 3 or pe.shape[-1] != 2:
        raise ValueError(f"pe must have shape [..., S, S, 2], got {tuple(pe.shape)}")
    out = xp.rot90(pe, -k, axes=(nd - 3, nd - 2))
    c, s = ((1, 0), (0, 1), (-1, 0), (0, -1))[k]
    x, y = out[..., 0], out[..., 1]
    return xp.stack([c * x - s * y, s * x + c * y], axis=-1).astype(pe.dtype)


_CV_DTYPES = (np.uint8, np.uint16, np.int16, np.float32, np.float64)


def supersample_transform(T: np.ndarray, factor: int) -> np.ndarray:
    """``T`` (image -> crop of ``S`` pixels) turned into image -> crop of ``factor * S`` pixels
    whose ``factor x factor`` blocks are the ``S``-crop's pixels (numpy, any leading axes).

    Pixel centres: crop pixel ``u`` covers ``[u - 0.5, u + 0.5]``, i.e. fine pixels
    ``factor u .. factor u + factor - 1``, whose centre is ``factor u + (factor - 1)/2``; so the
    fine crop's ``K`` is ``A @ T @ K`` with ``A = [[f, 0, (f-1)/2], [0, f, (f-1)/2], [0, 0, 1]]``,
    and :func:`area_downsample` of a render through it is the ``S``-crop with ``factor^2``
    samples per pixel."""
    f = int(factor)
    if f < 1:
        raise ValueError(f"factor must be a positive integer, got {factor!r}")
    A = np.array([[f, 0.0, (f - 1) / 2], [0.0, f, (f - 1) / 2], [0.0, 0.0, 1.0]])
    return A @ np.asarray(T, np.float64)


def area_downsample(img: np.ndarray, factor: int) -> np.ndarray:
    """The mean of each ``factor x factor`` block of an ``(f S, f S[, C])`` image (same dtype,
    rounded for integers): the inverse of :func:`supersample_transform`'s refinement. Bool
    images give the block's majority (a pixel at least half covered). ``factor`` 1 returns the
    image itself."""
    f = int(factor)
    if f < 1:
        raise ValueError(f"factor must be a positive integer, got {factor!r}")
    if f == 1:
        return img
    h, w = img.shape[:2]
    if h % f or w % f:
        raise ValueError(f"image of {h}x{w} pixels is not a whole number of {f}x{f} blocks")
    if img.dtype == np.bool_:
        return area_downsample(img.astype(np.float32), f) >= 0.5
    if img.dtype in (np.uint8, np.uint16, np.float32, np.float64) and (img.ndim == 2 or img.shape[2] <= 4):
        # OpenCV's area resize at an integer factor is the block mean (integers rounded)
        out = cv2.resize(np.ascontiguousarray(img), (w // f, h // f), interpolation=cv2.INTER_AREA)
        return out[..., None] if img.ndim == 3 and out.ndim == 2 else out
    blocks = img.reshape(h // f, f, w // f, f, *img.shape[2:]).astype(np.float64).mean(axis=(1, 3))
    if np.issubdtype(img.dtype, np.integer):
        info = np.iinfo(img.dtype)
        return np.clip(np.floor(blocks + 0.5), info.min, info.max).astype(img.dtype)
    return blocks.astype(img.dtype)


def warp_crop(
    image: np.ndarray,
    T: ArrayLike,
    out_size: int,
    interpolation: Literal["linear", "nearest"] = "linear",
    border_value: float = 0.0,
    supersample: int = 1,
) -> np.ndarray:
    """Crop an image with ``cv2.warpAffine``: ``out[v, u] = image(T^-1 (u, v))`` (numpy, not jit).

    ``image`` is ``HxW`` or ``HxWxC`` (any C; bool masks allowed); use ``"linear"`` for RGB and
    ``"nearest"`` for masks. ``T`` is ``(3, 3)`` or ``(N, 3, 3)`` (then the result gets a
    leading ``N`` axis). Pixels from outside the image get ``border_value``.

    ``supersample`` ``f > 1``: each crop pixel is the mean of ``f x f`` samples spread over its
    area (the crop is cut at ``f * out_size`` through :func:`supersample_transform` and
    :func:`area_downsample`-d), against the aliasing of a crop far smaller than its box in the
    image; 1 = one sample at each pixel's centre.
    """
    out_size = validate_size(out_size, "out_size")
    if not isinstance(supersample, (int, np.integer)) or isinstance(supersample, bool) or supersample < 1:
        raise ValueError(f"supersample must be a positive integer, got {supersample!r}")
    if supersample > 1:
        Tn = np.asarray(T, dtype=np.float64)
        fine = warp_crop(image, supersample_transform(Tn, supersample), out_size * int(supersample),
                         interpolation, border_value)
        if Tn.ndim == 3:
            return np.stack([area_downsample(c, int(supersample)) for c in fine])
        return area_downsample(fine, int(supersample))
    img = np.asarray(image)
    if img.ndim not in (2, 3) or img.shape[0] == 0 or img.shape[1] == 0:
        raise ValueError(f"image must be HxW or HxWxC, got shape {img.shape}")
    flags = {"linear": cv2.INTER_LINEAR, "nearest": cv2.INTER_NEAREST}.get(interpolation)
    if flags is None:
        raise ValueError(f"interpolation must be 'linear' or 'nearest', got {interpolation!r}")
    Tn = np.asarray(T, dtype=np.float64)
    if Tn.shape[-2:] != (3, 3) or Tn.ndim not in (2, 3):
        raise ValueError(f"T must have shape (3, 3) or (N, 3, 3), got {Tn.shape}")
    if not np.all(np.isfinite(Tn)):
        raise ValueError("T contains NaN or inf")
    if not np.allclose(Tn[..., 2, :], [0.0, 0.0, 1.0]):
        raise ValueError("T must be affine (last row (0, 0, 1))")
    if np.any(np.abs(np.linalg.det(Tn)) < 1e-12):
        raise ValueError("T is singular")
    was_bool = img.dtype == np.bool_
    if was_bool:
        img = img.astype(np.uint8)
    if img.dtype not in _CV_DTYPES:
        img = img.astype(np.float32 if np.issubdtype(img.dtype, np.floating) else np.float64)

    def one(Ti: np.ndarray) -> np.ndarray:
        # Pass T^-1 with WARP_INVERSE_MAP: dst(p) = src(T^-1 p), avoiding OpenCV's own inversion.
        Minv = np.linalg.inv(Ti)[:2]
        kw = dict(flags=flags | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_CONSTANT)
        size = (out_size, out_size)
        if img.ndim == 3 and img.shape[2] > 4:
            parts = [
                cv2.warpAffine(np.ascontiguousarray(img[..., i : i + 4]), Minv, size,
                               borderValue=(border_value,) * 4, **kw)
                for i in range(0, img.shape[2], 4)
            ]
            parts = [p[..., None] if p.ndim == 2 else p for p in parts]
            return np.concatenate(parts, axis=-1)
        out = cv2.warpAffine(img, Minv, size, borderValue=(border_value,) * 4, **kw)
        if img.ndim == 3 and out.ndim == 2:
            out = out[..., None]
        return out

    res = one(Tn) if Tn.ndim == 2 else np.stack([one(t) for t in Tn])
    return res.astype(bool) if was_bool else res
