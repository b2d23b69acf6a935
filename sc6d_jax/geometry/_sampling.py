"""SO(3) sampling: Fibonacci viewpoints, the inference grid, uniform rotations, InfoNCE negatives.

Measured covering radii of :func:`so3_grid` (the default 480,000-rotation library: 2.87 deg)
are tabulated in its docstring; :func:`covering_radius` measures them in memory-safe chunks.
"""

from __future__ import annotations

import math
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.typing import ArrayLike

from sc6d_jax.geometry._rotations import _as_float, geodesic_angle, quat_to_matrix, rot_z, rotation_between
from sc6d_jax.geometry._validate import _check_trailing, _is_concrete, validate_size

_GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))


def fibonacci_sphere(n: int) -> np.ndarray:
    """``(n, 3)`` float64 unit vectors, near-uniform on the sphere (Fibonacci lattice).

    Point ``i`` has ``z = 1 - (2 i + 1) / n`` and azimuth ``i * pi * (3 - sqrt 5)``. Deterministic.
    """
    n = validate_size(n, "n")
    i = np.arange(n, dtype=np.float64)
    z = 1.0 - (2.0 * i + 1.0) / n
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    phi = i * _GOLDEN_ANGLE
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1)


@jax.jit
def viewpoint_rotation(v: ArrayLike, roll: ArrayLike) -> Array:
    """Object-to-camera rotation of a camera looking at the object origin from direction ``v``.

    ``v[..., 3]`` is the viewpoint in the object frame (need not be unit); the result ``R``
    satisfies ``R @ v_hat = -z`` (that side of the object faces the camera), built as
    ``rot_z(roll) @ rotation_between(v, -z)``: ``roll[...]`` is the in-plane rotation about
    the optical axis. ``v`` and ``roll`` broadcast against each other.
    """
    v = _as_float(v)
    _check_trailing(v, (3,), "v")
    roll = jnp.asarray(roll, v.dtype)
    minus_z = jnp.zeros((3,), v.dtype).at[2].set(-1)
    return rot_z(roll) @ rotation_between(v, minus_z)


def so3_grid(n_views: int = 4000, n_inplane: int = 120, seed: int = 0) -> np.ndarray:
    """Inference rotation library: ``(n_views * n_inplane, 3, 3)`` float32, view-major order.

    Viewpoints are :func:`fibonacci_sphere` ``(n_views)``; viewpoint ``i`` gets in-plane angles
    ``(k + 1) / (n_inplane + 1) * 2 pi + o_i`` for ``k = 0 .. n_inplane - 1``, where ``o_i`` is a
    roll offset drawn uniformly in ``[0, 2 pi)`` by ``numpy.random.default_rng(seed)`` (the
    authors' construction with 121 -> ``n_inplane + 1``; note that it leaves one in-plane gap of
    two steps). Computed in float64, deterministic for a given ``(n_views, n_inplane, seed)``.

    Covering radius (largest geodesic distance from 10,000 uniform random rotations to the
    nearest grid rotation, :func:`covering_radius` with ``jax.random.key(0)``, seed 0; a
    Monte-Carlo lower estimate of the true radius), next to the volume lower bound that any
    grid of that size must exceed (``N (rho - sin rho) / pi >= 1``); sizes are the paper's
    SO(3) table, with ``n_inplane ~ sqrt(pi n_views)`` so view and in-plane spacing match:

    ==========================  =========  ==============  ==================
    grid (views x in-plane)     size       radius (deg)    volume bound (deg)
    ==========================  =========  ==============  ==================
    ``so3_grid(500, 40)``       20,000     8.67            5.62
    ``so3_grid(1000, 60)``      60,000     5.97            3.90
    ``so3_grid(2250, 80)``      180,000    4.20            2.70
    ``so3_grid(4000, 120)``     480,000    2.87            1.95
    ``so3_grid(8000, 180)``     1,440,000  1.95            1.35
    ==========================  =========  ==============  ==================

    An upper bound follows from the construction: ``radius <= rho_views + 2 pi / (n_inplane + 1)``
    with ``rho_views`` the covering radius of the viewpoints on the sphere (tested).
    """
    n_views = validate_size(n_views, "n_views")
    n_inplane = validate_size(n_inplane, "n_inplane")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
        raise ValueError(f"seed must be an int, got {seed!r}")
    views = fibonacci_sphere(n_views)
    offsets = np.random.default_rng(int(seed)).uniform(0.0, 2.0 * np.pi, size=n_views)
    k = np.arange(n_inplane, dtype=np.float64)
    angles = (k + 1.0) / (n_inplane + 1.0) * 2.0 * np.pi
    rolls = angles[None, :] + offsets[:, None]  # (n_views, n_inplane)
    base = _viewpoint_rotation_np(views)  # (V, 3, 3), equals viewpoint_rotation(views, 0)
    c, s = np.cos(rolls), np.sin(rolls)
    Rz = np.zeros(rolls.shape + (3, 3))
    Rz[..., 0, 0], Rz[..., 0, 1], Rz[..., 1, 0], Rz[..., 1, 1], Rz[..., 2, 2] = c, -s, s, c, 1.0
    R = Rz @ base[:, None]
    return R.reshape(n_views * n_inplane, 3, 3).astype(np.float32)


def _viewpoint_rotation_np(views: np.ndarray) -> np.ndarray:
    """float64 numpy twin of ``viewpoint_rotation(views, 0)`` = ``rotation_between(views, -z)``
    (same formulas and branches; no compilation, so building a 480k grid takes milliseconds)."""
    a = views / np.linalg.norm(views, axis=-1, keepdims=True)
    b = np.array([0.0, 0.0, -1.0])
    v = np.cross(a, b)
    c = a @ b

    def skew_np(x: np.ndarray) -> np.ndarray:
        o = np.zeros(x.shape[:-1])
        return np.stack([np.stack([o, -x[..., 2], x[..., 1]], -1),
                         np.stack([x[..., 2], o, -x[..., 0]], -1),
                         np.stack([-x[..., 1], x[..., 0], o], -1)], -2)

    eye = np.eye(3)
    V = skew_np(v)
    pos = c >= 0
    R_pos = eye + V + (V @ V) / np.where(pos, 1 + c, 1.0)[:, None, None]
    u = v - np.sum(v * a, axis=-1, keepdims=True) * a
    un = np.linalg.norm(u, axis=-1)
    ok = un > 1e-30
    # fallback axis: a crossed with the least-aligned coordinate axis (as in rotation_between)
    e = np.eye(3)[np.argmin(np.abs(a), axis=-1)]
    perp = np.cross(a, e)
    perp /= np.linalg.norm(perp, axis=-1, keepdims=True)
    u = np.where(ok[:, None], u / np.where(ok, un, 1.0)[:, None], perp)
    U = skew_np(u)
    R_neg = eye + np.linalg.norm(v, axis=-1)[:, None, None] * U + (1 - c)[:, None, None] * (U @ U)
    return np.where(pos[:, None, None], R_pos, R_neg)


def random_rotations(key: Array, n: int, dtype: jnp.dtype = jnp.float32) -> Array:
    """``(n, 3, 3)`` rotations drawn uniformly (Haar measure), from normalised Gaussian quaternions."""
    n = validate_size(n, "n")
    return _random_rotations(key, n, jnp.dtype(dtype))


@partial(jax.jit, static_argnames=("n", "dtype"))
def _random_rotations(key: Array, n: int, dtype: jnp.dtype) -> Array:
    q = jax.random.normal(key, (n, 4), dtype=dtype)
    return quat_to_matrix(q)


def sample_rotation_deltas(key: Array, n: int, dtype: jnp.dtype = jnp.float32) -> Array:
    """The authors' InfoNCE negatives: ``(n, 3, 3)`` = viewpoint rotations of the ``n``
    Fibonacci viewpoints, each with an in-plane roll uniform in ``[0, 2 pi)`` drawn from ``key``.

    Left-multiply them onto the ground truth with :func:`rebase_negatives` (one set shared by
    the batch). ``n`` must be a static Python int; jit-able in ``key``.
    """
    n = validate_size(n, "n")
    return _sample_rotation_deltas(key, n, jnp.dtype(dtype))


@partial(jax.jit, static_argnames=("n", "dtype"))
def _sample_rotation_deltas(key: Array, n: int, dtype: jnp.dtype) -> Array:
    views = jnp.asarray(fibonacci_sphere(n), dtype=dtype)
    roll = jax.random.uniform(key, (n,), dtype=dtype, minval=0.0, maxval=2 * jnp.pi)
    return viewpoint_rotation(views, roll)


@jax.jit
def rebase_negatives(deltas: ArrayLike, R_gt: ArrayLike) -> Array:
    """Candidates ``[..., Q + 1, 3, 3]``: index 0 is ``R_gt``, index ``1 + q`` is ``deltas[q] @ R_gt``."""
    deltas, R_gt = _as_float(deltas), _as_float(R_gt)
    _check_trailing(deltas, (3, 3), "deltas")
    _check_trailing(R_gt, (3, 3), "R_gt")
    if deltas.ndim != 3:
        raise ValueError(f"deltas must have shape [Q, 3, 3], got {deltas.shape}")
    neg = deltas @ R_gt[..., None, :, :]
    return jnp.concatenate([R_gt[..., None, :, :].astype(neg.dtype), neg], axis=-3)


def _best_trace_scan(samples: Array, chunks: Array) -> tuple[Array, Array]:
    """For each sample, max over grid rotations of trace(S^T G) and its index; chunked scan."""
    m = samples.shape[0]
    c = chunks.shape[1]

    def step(carry, xs):
        best, idx = carry
        i, chunk = xs
        tr = samples @ chunk.T  # (m, c) = trace(S^T G) for flattened row-major 3x3
        j = jnp.argmax(tr, axis=1)
        val = jnp.take_along_axis(tr, j[:, None], axis=1)[:, 0]
        better = val > best
        return (jnp.where(better, val, best), jnp.where(better, (i * c + j).astype(jnp.int32), idx)), None

    init = (jnp.full((m,), -jnp.inf, samples.dtype), jnp.zeros((m,), jnp.int32))
    (best, idx), _ = jax.lax.scan(step, init, (jnp.arange(chunks.shape[0], dtype=jnp.int32), chunks))
    return best, idx


_best_trace_scan_jit = jax.jit(_best_trace_scan)


def nearest_rotation(grid: ArrayLike, R: ArrayLike, chunk: int = 4096) -> tuple[np.ndarray, np.ndarray]:
    """Nearest grid rotation (geodesic) for each query: ``(index[m], angle[m] radians)``.

    ``grid`` is ``(N, 3, 3)``, ``R`` is ``(m, 3, 3)``. Memory-safe for large grids: the
    grid is scanned in chunks of ``chunk`` rotations and the queries in blocks of 4096, so at
    most ``4096 * chunk`` traces are held at a time. The nearest rotation maximises
    ``trace(R^T G)``; the returned angle is recomputed with :func:`geodesic_angle`.
    """
    grid = np.asarray(grid, dtype=np.float32)
    Rq = np.asarray(R, dtype=np.float32)
    if grid.ndim != 3 or grid.shape[1:] != (3, 3) or grid.shape[0] == 0:
        raise ValueError(f"grid must have shape [N, 3, 3] with N > 0, got {grid.shape}")
    if Rq.ndim != 3 or Rq.shape[1:] != (3, 3):
        raise ValueError(f"R must have shape [m, 3, 3], got {Rq.shape}")
    if not np.all(np.isfinite(grid)):
        raise ValueError("grid contains NaN or inf")
    chunk = validate_size(chunk, "chunk")
    n = grid.shape[0]
    c = min(chunk, n)
    n_chunks = -(-n // c)
    flat = grid.reshape(n, 9)
    pad = n_chunks * c - n
    if pad:
        flat = np.concatenate([flat, np.repeat(flat[:1], pad, axis=0)], axis=0)  # duplicates: harmless
    chunks = jnp.asarray(flat.reshape(n_chunks, c, 9))
    block = 4096  # queries per scan; later partial blocks are padded to reuse one compilation
    idx_all = []
    for s in range(0, Rq.shape[0], block):
        q = Rq[s : s + block]
        m = q.shape[0]
        if s > 0 and m < block:
            q = np.concatenate([q, np.repeat(q[:1], block - m, axis=0)], axis=0)
        _, idx = _best_trace_scan_jit(jnp.asarray(q.reshape(-1, 9)), chunks)
        idx_all.append(np.asarray(idx)[:m])
    idx = np.concatenate(idx_all) if idx_all else np.zeros((0,), np.int64)
    idx = np.minimum(idx, n - 1)
    ang = np.asarray(geodesic_angle(jnp.asarray(Rq), jnp.asarray(grid[idx]))) if idx.size else np.zeros(0)
    return idx.astype(np.int64), ang.astype(np.float64)


def covering_radius(grid: ArrayLike, key: Array, n_samples: int = 10000, chunk: int = 4096) -> float:
    """Max over ``n_samples`` uniform random rotations of the geodesic distance to the nearest
    grid rotation (radians): a Monte-Carlo lower estimate of the grid's covering radius.

    Memory-safe for large grids (see :func:`nearest_rotation`); deterministic for a given key.
    """
    n_samples = validate_size(n_samples, "n_samples")
    if not _is_concrete(grid):
        raise ValueError("covering_radius needs a concrete grid (do not call it under jit)")
    samples = random_rotations(key, n_samples, jnp.float32)
    _, ang = nearest_rotation(grid, samples, chunk=chunk)
    return float(ang.max())
