"""Input validation for the geometry functions (numpy, outside jit).

The core geometry functions are jit-able and so cannot raise on values; these checks are run at
public boundaries. Every failure is a ``ValueError`` whose message names the argument and the
problem. The core functions call them automatically when their inputs are concrete (not traced).
"""

from __future__ import annotations

from typing import Any

import jax
import numpy as np


def _is_concrete(*xs: Any) -> bool:
    """True when none of ``xs`` is a JAX tracer (i.e. values can be inspected)."""
    return not any(isinstance(x, jax.core.Tracer) for x in xs)


def _check_trailing(x: Any, trailing: tuple[int, ...], name: str) -> None:
    """Raise ValueError unless ``x`` has at least ``len(trailing)`` axes ending in ``trailing``."""
    shape = tuple(np.shape(x))
    k = len(trailing)
    if len(shape) < k or shape[len(shape) - k :] != trailing:
        want = "[..., " + ", ".join(str(t) for t in trailing) + "]"
        raise ValueError(f"{name} must have shape {want}, got shape {shape}")


def _as_numpy(x: Any, name: str) -> np.ndarray:
    try:
        a = np.asarray(x)
    except Exception as exc:  # pragma: no cover - exotic inputs
        raise ValueError(f"{name} could not be converted to an array: {exc}") from exc
    if a.dtype == object or not (np.issubdtype(a.dtype, np.number) or a.dtype == np.bool_):
        raise ValueError(f"{name} must be numeric, got dtype {a.dtype}")
    return a


def _check_finite(a: np.ndarray, name: str) -> None:
    if not np.all(np.isfinite(a)):
        bad = int(np.size(a) - np.count_nonzero(np.isfinite(a)))
        raise ValueError(f"{name} contains {bad} non-finite value(s) (NaN or inf)")


def validate_K(K: Any, name: str = "K") -> np.ndarray:
    """Check camera matrices ``K[..., 3, 3] = [[fx, s, cx], [0, fy, cy], [0, 0, 1]]``.

    Raises ValueError for a wrong shape, NaN/inf, a last row other than (0, 0, 1), a
    non-positive focal length, or a singular matrix. Returns ``K`` as a float64 numpy array.
    """
    _check_trailing(K, (3, 3), name)
    a = _as_numpy(K, name).astype(np.float64)
    _check_finite(a, name)
    if a.size == 0:
        return a
    if not np.allclose(a[..., 2, :], np.array([0.0, 0.0, 1.0]), atol=1e-9):
        raise ValueError(f"{name} last row must be (0, 0, 1), got e.g. {a[..., 2, :].reshape(-1, 3)[0]}")
    if np.any(np.abs(a[..., 1, 0]) > 1e-9):
        raise ValueError(f"{name}[1, 0] must be 0 (upper-triangular intrinsics)")
    fx, fy = a[..., 0, 0], a[..., 1, 1]
    if np.any(fx == 0) or np.any(fy == 0):
        raise ValueError(f"{name} is singular: focal length fx or fy is 0")
    if np.any(fx < 0) or np.any(fy < 0):
        raise ValueError(f"{name} has a negative focal length (fx={fx.min()}, fy={fy.min()})")
    det = np.linalg.det(a)
    scale = np.max(np.abs(a), axis=(-1, -2)) ** 2
    if np.any(np.abs(det) <= 1e-12 * scale):
        raise ValueError(f"{name} is singular (determinant {det.reshape(-1).min()})")
    return a


def validate_boxes(boxes: Any, image_size: tuple[int, int] | None = None, name: str = "boxes") -> np.ndarray:
    """Check 2D boxes ``(x, y, w, h)`` in pixels (pixel centres at integer coordinates).

    Raises ValueError for a wrong shape (last axis must be 4), NaN/inf, ``w <= 0`` or
    ``h <= 0``, and, when ``image_size = (width, height)`` is given, boxes lying wholly outside
    the image (the image covers ``[-0.5, width - 0.5] x [-0.5, height - 0.5]``).
    Returns the boxes as a float64 numpy array.
    """
    _check_trailing(boxes, (4,), name)
    a = _as_numpy(boxes, name).astype(np.float64)
    _check_finite(a, name)
    w, h = a[..., 2], a[..., 3]
    if np.any(w <= 0) or np.any(h <= 0):
        raise ValueError(
            f"{name} must have positive width and height, got min w={w.min() if w.size else None}, "
            f"min h={h.min() if h.size else None}"
        )
    if image_size is not None:
        if len(tuple(image_size)) != 2:
            raise ValueError(f"image_size must be (width, height), got {image_size!r}")
        width, height = (float(v) for v in image_size)
        if width <= 0 or height <= 0:
            raise ValueError(f"image_size must be positive, got {image_size!r}")
        x, y = a[..., 0], a[..., 1]
        outside = (x + w < -0.5) | (y + h < -0.5) | (x > width - 0.5) | (y > height - 0.5)
        if np.any(outside):
            idx = np.argwhere(outside)[0]
            raise ValueError(
                f"{name} has a box wholly outside the {int(width)}x{int(height)} image: "
                f"{a[tuple(idx)].tolist()} at index {idx.tolist()}"
            )
    return a


def validate_rotation(R: Any, atol: float = 1e-3, name: str = "R") -> np.ndarray:
    """Check rotation matrices ``R[..., 3, 3]``: finite, orthonormal within ``atol``, det +1.

    Returns ``R`` as a float64 numpy array.
    """
    _check_trailing(R, (3, 3), name)
    a = _as_numpy(R, name).astype(np.float64)
    _check_finite(a, name)
    if a.size == 0:
        return a
    err = np.abs(np.swapaxes(a, -1, -2) @ a - np.eye(3)).max()
    if err > atol:
        raise ValueError(f"{name} is not orthonormal: max |R^T R - I| = {err:.3g} > {atol}")
    det = np.linalg.det(a)
    if np.any(det < 0):
        raise ValueError(f"{name} has determinant -1 (a reflection, not a rotation)")
    return a


def validate_translation(t: Any, name: str = "t") -> np.ndarray:
    """Check translations ``t[..., 3]``: finite, and with positive depth ``t_z > 0``."""
    _check_trailing(t, (3,), name)
    a = _as_numpy(t, name).astype(np.float64)
    _check_finite(a, name)
    if np.any(a[..., 2] <= 0):
        raise ValueError(f"{name} must lie in front of the camera (t_z > 0), got min t_z={a[..., 2].min()}")
    return a


def validate_positive(x: Any, name: str) -> np.ndarray:
    """Check that all values are finite and strictly positive."""
    a = _as_numpy(x, name).astype(np.float64)
    _check_finite(a, name)
    if np.any(a <= 0):
        raise ValueError(f"{name} must be positive, got min {a.min()}")
    return a


def validate_size(n: Any, name: str) -> int:
    """Check a positive Python integer size (grid sizes, crop sizes, bin counts)."""
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)):
        raise ValueError(f"{name} must be a positive int, got {n!r}")
    if int(n) <= 0:
        raise ValueError(f"{name} must be a positive int, got {n}")
    return int(n)
