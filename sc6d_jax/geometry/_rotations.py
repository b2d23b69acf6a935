"""Rotation conversions, SO(3) projection and geodesic distance (jnp, batched, dtype-preserving).

Conventions: ``x_cam = R @ x_model + t``; quaternions are ``(w, x, y, z)`` with ``w >= 0`` on
output; axis-angle vectors are ``angle * unit_axis`` with ``angle`` in ``[0, pi]``; the 6D
representation (Zhou et al. 2019) is the first two *columns* of ``R`` concatenated,
``(R[:, 0], R[:, 1])``. All functions take leading batch axes and are jit-able.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import Array
from jax.typing import ArrayLike

from sc6d_jax.geometry._validate import _check_trailing


def _as_float(x: ArrayLike) -> Array:
    """``jnp.asarray`` that promotes integer/bool input to the default float dtype."""
    a = jnp.asarray(x)
    if not jnp.issubdtype(a.dtype, jnp.floating):
        a = a.astype(jnp.result_type(float))
    return a


def _safe_norm(v: Array, axis: int = -1) -> tuple[Array, Array]:
    """(norm, is_positive) with a finite gradient at zero."""
    sq = jnp.sum(v * v, axis=axis)
    pos = sq > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, sq, 1)), 0), pos


@jax.jit
def skew(v: ArrayLike) -> Array:
    """Cross-product matrix ``[v]_x`` with ``[v]_x @ u = v x u``; ``v[..., 3] -> [..., 3, 3]``."""
    v = _as_float(v)
    _check_trailing(v, (3,), "v")
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    o = jnp.zeros_like(x)
    return jnp.stack(
        [jnp.stack([o, -z, y], -1), jnp.stack([z, o, -x], -1), jnp.stack([-y, x, o], -1)], -2
    )


@jax.jit
def quat_to_matrix(q: ArrayLike) -> Array:
    """Quaternion ``(w, x, y, z)`` (need not be unit; it is normalised) -> rotation matrix."""
    q = _as_float(q)
    _check_trailing(q, (4,), "q")
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    s = 2.0 / jnp.sum(q * q, axis=-1)
    xx, yy, zz = s * x * x, s * y * y, s * z * z
    xy, xz, yz = s * x * y, s * x * z, s * y * z
    wx, wy, wz = s * w * x, s * w * y, s * w * z
    rows = [
        jnp.stack([1 - yy - zz, xy - wz, xz + wy], -1),
        jnp.stack([xy + wz, 1 - xx - zz, yz - wx], -1),
        jnp.stack([xz - wy, yz + wx, 1 - xx - yy], -1),
    ]
    return jnp.stack(rows, -2)


@jax.jit
def matrix_to_quat(R: ArrayLike) -> Array:
    """Rotation matrix -> unit quaternion ``(w, x, y, z)`` with ``w >= 0``.

    Uses the best-conditioned of the four Shepperd candidates, so it is accurate near 0 and pi.
    """
    R = _as_float(R)
    _check_trailing(R, (3, 3), "R")
    m00, m01, m02 = R[..., 0, 0], R[..., 0, 1], R[..., 0, 2]
    m10, m11, m12 = R[..., 1, 0], R[..., 1, 1], R[..., 1, 2]
    m20, m21, m22 = R[..., 2, 0], R[..., 2, 1], R[..., 2, 2]
    four = jnp.stack(
        [1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1
    )
    pos = four > 0
    q_abs = jnp.where(pos, jnp.sqrt(jnp.where(pos, four, 1)), 0)  # gradient-safe at 0
    cands = jnp.stack(
        [
            jnp.stack([four[..., 0], m21 - m12, m02 - m20, m10 - m01], -1),
            jnp.stack([m21 - m12, four[..., 1], m10 + m01, m02 + m20], -1),
            jnp.stack([m02 - m20, m10 + m01, four[..., 2], m12 + m21], -1),
            jnp.stack([m10 - m01, m20 + m02, m21 + m12, four[..., 3]], -1),
        ],
        -2,
    )
    cands = cands / (2 * jnp.maximum(q_abs, 0.1)[..., None])
    best = jnp.argmax(q_abs, axis=-1)
    q = jnp.take_along_axis(cands, best[..., None, None], axis=-2)[..., 0, :]
    q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    return jnp.where(q[..., :1] < 0, -q, q)


@jax.jit
def axis_angle_to_matrix(aa: ArrayLike) -> Array:
    """Axis-angle vector ``angle * axis`` -> rotation matrix (Rodrigues; Taylor series near 0)."""
    aa = _as_float(aa)
    _check_trailing(aa, (3,), "aa")
    th2 = jnp.sum(aa * aa, axis=-1)
    small = th2 < 1e-6
    th = jnp.sqrt(jnp.where(small, 1.0, th2))
    a = jnp.where(small, 1 - th2 / 6 + th2 * th2 / 120, jnp.sin(th) / th)
    half = jnp.sin(th / 2) / th
    b = jnp.where(small, 0.5 - th2 / 24 + th2 * th2 / 720, 2 * half * half)
    Kx = skew(aa)
    eye = jnp.eye(3, dtype=aa.dtype)
    return eye + a[..., None, None] * Kx + b[..., None, None] * (Kx @ Kx)


@jax.jit
def matrix_to_axis_angle(R: ArrayLike) -> Array:
    """Rotation matrix -> axis-angle vector with angle in ``[0, pi]`` (via the quaternion).

    At exactly pi the sign of the axis is arbitrary (both represent the same rotation).
    """
    q = matrix_to_quat(R)
    w, v = q[..., 0], q[..., 1:]
    n, pos = _safe_norm(v)
    small = n < 1e-6
    n_safe = jnp.where(small, 1.0, n)
    w_safe = jnp.where(small, jnp.maximum(w, 0.5), 1.0)
    factor = jnp.where(
        small, 2 / w_safe * (1 - n * n / (3 * w_safe * w_safe)), 2 * jnp.arctan2(n_safe, w) / n_safe
    )
    return v * factor[..., None]


@jax.jit
def sixd_to_matrix(x: ArrayLike) -> Array:
    """6D representation ``(a1, a2)`` -> rotation whose first two columns are Gram-Schmidt of a1, a2."""
    x = _as_float(x)
    _check_trailing(x, (6,), "x")
    a1, a2 = x[..., :3], x[..., 3:]
    b1 = a1 / jnp.linalg.norm(a1, axis=-1, keepdims=True)
    b2 = a2 - jnp.sum(b1 * a2, axis=-1, keepdims=True) * b1
    b2 = b2 / jnp.linalg.norm(b2, axis=-1, keepdims=True)
    b3 = jnp.cross(b1, b2)
    return jnp.stack([b1, b2, b3], axis=-1)


@jax.jit
def matrix_to_sixd(R: ArrayLike) -> Array:
    """Rotation matrix -> 6D representation: its first two columns ``(R[:, 0], R[:, 1])``."""
    R = _as_float(R)
    _check_trailing(R, (3, 3), "R")
    return jnp.concatenate([R[..., :, 0], R[..., :, 1]], axis=-1)


@jax.jit
def project_to_so3(M: ArrayLike) -> Array:
    """Nearest rotation (Frobenius norm) to a 3x3 matrix: ``U diag(1, 1, d) V^T`` from the SVD."""
    M = _as_float(M)
    _check_trailing(M, (3, 3), "M")
    U, _, Vh = jnp.linalg.svd(M)
    d = jnp.where(jnp.linalg.det(U @ Vh) < 0, -1.0, 1.0).astype(M.dtype)
    U = U.at[..., :, 2].multiply(d[..., None])
    return U @ Vh


@jax.jit
def geodesic_angle(R1: ArrayLike, R2: ArrayLike) -> Array:
    """Rotation angle of ``R1^T R2`` in ``[0, pi]``.

    Computed as ``atan2(sin, cos)`` with ``sin`` from the skew part and ``cos`` from the trace,
    which is accurate near both 0 and pi (``arccos`` of the trace is not).
    """
    R1, R2 = _as_float(R1), _as_float(R2)
    _check_trailing(R1, (3, 3), "R1")
    _check_trailing(R2, (3, 3), "R2")
    Rr = jnp.swapaxes(R1, -1, -2) @ R2
    cos = (Rr[..., 0, 0] + Rr[..., 1, 1] + Rr[..., 2, 2] - 1) / 2
    vee = jnp.stack(
        [Rr[..., 2, 1] - Rr[..., 1, 2], Rr[..., 0, 2] - Rr[..., 2, 0], Rr[..., 1, 0] - Rr[..., 0, 1]], -1
    )
    sin, _ = _safe_norm(vee)
    return jnp.arctan2(sin / 2, cos)


def _axis_rot(a: ArrayLike, i: int, j: int) -> Array:
    a = _as_float(a)
    c, s = jnp.cos(a), jnp.sin(a)
    R = jnp.broadcast_to(jnp.eye(3, dtype=a.dtype), a.shape + (3, 3))
    R = R.at[..., i, i].set(c).at[..., j, j].set(c)
    return R.at[..., i, j].set(-s).at[..., j, i].set(s)


@jax.jit
def rot_x(a: ArrayLike) -> Array:
    """Rotation by angle ``a`` (radians, any shape) about the x axis."""
    return _axis_rot(a, 1, 2)


@jax.jit
def rot_y(a: ArrayLike) -> Array:
    """Rotation by angle ``a`` (radians, any shape) about the y axis."""
    return _axis_rot(a, 2, 0)


@jax.jit
def rot_z(a: ArrayLike) -> Array:
    """Rotation by angle ``a`` (radians, any shape) about the z axis."""
    return _axis_rot(a, 0, 1)


def _perpendicular(a: Array) -> Array:
    """A unit vector perpendicular to ``a`` (crossed with the least-aligned coordinate axis)."""
    idx = jnp.argmin(jnp.abs(a), axis=-1)
    e = (jnp.arange(3) == idx[..., None]).astype(a.dtype)
    p = jnp.cross(a, e)
    return p / jnp.linalg.norm(p, axis=-1, keepdims=True)


@jax.jit
def rotation_between(a: ArrayLike, b: ArrayLike) -> Array:
    """Minimal rotation ``R`` with ``R @ a_hat = b_hat`` (``a``, ``b`` need not be unit).

    For ``c = a.b >= 0`` this is ``I + [v]x + [v]x^2 / (1 + c)`` with ``v = a x b``; for
    ``c < 0`` the equivalent Rodrigues form about the axis ``v`` made exactly perpendicular
    to ``a`` is used, so it stays accurate up to the antiparallel case, where it returns the
    rotation by pi about a fixed perpendicular axis (the minimal rotation is not unique there).
    Zero vectors are not allowed (NaN).
    """
    a, b = _as_float(a), _as_float(b)
    _check_trailing(a, (3,), "a")
    _check_trailing(b, (3,), "b")
    a = a / jnp.linalg.norm(a, axis=-1, keepdims=True)
    b = b / jnp.linalg.norm(b, axis=-1, keepdims=True)
    a, b = jnp.broadcast_arrays(a, b)
    v = jnp.cross(a, b)
    c = jnp.sum(a * b, axis=-1)
    eye = jnp.eye(3, dtype=a.dtype)
    # branch c >= 0
    Vx = skew(v)
    pos = c >= 0
    inv1c = 1 / jnp.where(pos, 1 + c, 1.0)
    R_pos = eye + Vx + (Vx @ Vx) * inv1c[..., None, None]
    # branch c < 0: axis from v, re-orthogonalised against a; sin = |v|, 1 - cos = 1 - c
    u = v - jnp.sum(v * a, axis=-1, keepdims=True) * a
    un, _ = _safe_norm(u)
    ok = un > 1e-30
    u = jnp.where(ok[..., None], u / jnp.where(ok, un, 1.0)[..., None], _perpendicular(a))
    sin, _ = _safe_norm(v)
    Ux = skew(u)
    R_neg = eye + sin[..., None, None] * Ux + (1 - c)[..., None, None] * (Ux @ Ux)
    return jnp.where(pos[..., None, None], R_pos, R_neg)
