"""Allocentric <-> egocentric rotations (REFERENCE section 1).

The allocentric rotation is the object's rotation relative to the viewing ray through its
centre: ``R_ego = R_c @ R_allo`` with ``R_c`` the minimal rotation taking the optical axis
``z = (0, 0, 1)`` onto the unit ray ``n = t / |t|``,
``R_c = I + [v]x + [v]x^2 / (1 + c)``, ``v = z x n``, ``c = z . n``.

An object at ``(R_ego, t)`` seen by the camera looks, up to the image homography of the pure
camera rotation ``R_c``, exactly like the object ``(R_allo, |t| z)`` centred on the optical
axis; so objects moved sideways at fixed allocentric rotation (and distance) present the same
view to a camera turned to look at them.

Edge cases: ``t`` along the optical axis gives ``R_c = I`` exactly; ``t`` antiparallel to the
axis (object behind the camera) gives the rotation by pi about the y axis; ``t = 0`` (no
defined ray) gives ``R_c = I``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import Array
from jax.typing import ArrayLike

from sc6d_jax.geometry._rotations import _as_float, rotation_between
from sc6d_jax.geometry._validate import _check_trailing


@jax.jit
def ray_rotation(t: ArrayLike) -> Array:
    """``R_c[..., 3, 3]``: the minimal rotation taking the optical axis onto the ray through ``t``."""
    t = _as_float(t)
    _check_trailing(t, (3,), "t")
    zero = jnp.all(t == 0, axis=-1, keepdims=True)
    z = jnp.zeros_like(t).at[..., 2].set(1)
    return rotation_between(z, jnp.where(zero, z, t))


@jax.jit
def allocentric_to_egocentric(R_allo: ArrayLike, t: ArrayLike) -> Array:
    """``R_ego = R_c(t) @ R_allo`` (batched; ``R_allo[..., 3, 3]``, ``t[..., 3]``)."""
    R_allo = _as_float(R_allo)
    _check_trailing(R_allo, (3, 3), "R_allo")
    return ray_rotation(jnp.asarray(t, R_allo.dtype)) @ R_allo


@jax.jit
def egocentric_to_allocentric(R_ego: ArrayLike, t: ArrayLike) -> Array:
    """``R_allo = R_c(t)^T @ R_ego`` (batched; ``R_ego[..., 3, 3]``, ``t[..., 3]``)."""
    R_ego = _as_float(R_ego)
    _check_trailing(R_ego, (3, 3), "R_ego")
    return jnp.swapaxes(ray_rotation(jnp.asarray(t, R_ego.dtype)), -1, -2) @ R_ego
