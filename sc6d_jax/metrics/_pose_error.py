"""Pose error functions of the BOP toolkit (``bop_toolkit_lib/pose_error.py``), reimplemented.

Arguments and units follow the toolkit: rotations 3x3, translations 3 (or 3x1) in mm, model
points (N, 3) in mm, symmetries as returned by :func:`symmetry_transformations`. Inputs are numpy
arrays, outputs Python floats (``vsd`` returns a list, one error per tau). The operations are
performed in the same order as in the toolkit so that the results agree to rounding.
"""

from __future__ import annotations

import math
from typing import Any, Mapping, Protocol, Sequence, Union

import numpy as np
from scipy import spatial

from sc6d_jax.metrics._symmetry import _stack_syms


# ----------------------------------------------------------------------------- validation
def _rot(R: Any, name: str) -> np.ndarray:
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (3, 3):
        raise ValueError(f"{name} must have shape (3, 3), got {R.shape}")
    if not np.isfinite(R).all():
        raise ValueError(f"{name} must be finite")
    return R


def _vec(t: Any, name: str) -> np.ndarray:
    t = np.asarray(t, dtype=np.float64)
    if t.size != 3 or t.shape not in ((3,), (3, 1), (1, 3)):
        raise ValueError(f"{name} must have 3 elements (shape (3,) or (3, 1)), got {t.shape}")
    if not np.isfinite(t).all():
        raise ValueError(f"{name} must be finite")
    return t.reshape(3, 1)


def _pts(pts: Any) -> np.ndarray:
    p = np.asarray(pts, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] == 0:
        raise ValueError(f"pts must have shape (N, 3) with N >= 1, got {p.shape}")
    if not np.isfinite(p).all():
        raise ValueError("pts must be finite")
    return p


def _K(K: Any) -> np.ndarray:
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise ValueError(f"K must have shape (3, 3), got {K.shape}")
    if not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"K must be finite with positive focal lengths, got {K.tolist()}")
    return K


# ----------------------------------------------------------------------------- helpers
def transform_pts(pts: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``(R pts^T + t)^T`` (the toolkit's ``transform_pts_Rt``)."""
    return (R.dot(pts.T) + t.reshape(3, 1)).T


def project_pts(pts: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Pinhole projection of model points (N, 3) -> (N, 2) pixels (OpenCV/BOP convention)."""
    P = K.dot(np.hstack((R, t.reshape(3, 1))))
    pts_h = np.hstack((pts, np.ones((pts.shape[0], 1))))
    im = P.dot(pts_h.T)
    im /= im[2, :]
    return im[:2, :].T


def depth_to_distance(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Depth image (Z per pixel, 0 = none) -> distance from the camera centre per pixel.

    Uses integer pixel coordinates ``(x, y)`` as in the toolkit's ``depth_im_to_dist_im_fast``.
    """
    depth = np.asarray(depth)
    if depth.ndim != 2:
        raise ValueError(f"depth must be a 2-D image, got shape {depth.shape}")
    K = _K(K)
    h, w = depth.shape
    xs, ys = np.meshgrid(np.arange(w), np.arange(h))
    pre_x = (xs - K[0, 2]) / np.float64(K[0, 0])
    pre_y = (ys - K[1, 2]) / np.float64(K[1, 1])
    return np.sqrt(
        np.multiply(pre_x, depth) ** 2 + np.multiply(pre_y, depth) ** 2 + depth.astype(np.float64) ** 2
    )


def _visib_mask(d_test: np.ndarray, d_model: np.ndarray, delta: float) -> np.ndarray:
    """BOP19 visibility: model surface in front of (or within delta of) the scene, or no depth."""
    diff = d_model.astype(np.float32) - d_test.astype(np.float32)
    return np.logical_and(np.logical_or(diff <= delta, d_test == 0), d_model > 0)


def overlapping_sphere_projections(radius: float, p1: np.ndarray, p2: np.ndarray) -> bool:
    """Whether the (approximate) image projections of two spheres of ``radius`` overlap."""
    p1 = np.asarray(p1, dtype=np.float64).reshape(3)
    p2 = np.asarray(p2, dtype=np.float64).reshape(3)
    if p1[2] == 0 or p2[2] == 0:
        return False
    d = np.linalg.norm((p1 / p1[2])[:2] - (p2 / p2[2])[:2])
    return bool(d < radius * (1.0 / p1[2] + 1.0 / p2[2]))


# ----------------------------------------------------------------------------- errors
def re(R_est: np.ndarray, R_gt: np.ndarray) -> float:
    """Rotational error [deg]: angle of ``R_est R_gt^-1``."""
    R_est, R_gt = _rot(R_est, "R_est"), _rot(R_gt, "R_gt")
    c = float(0.5 * (np.trace(R_est.dot(np.linalg.inv(R_gt))) - 1.0))
    c = min(1.0, max(-1.0, c))
    return 180.0 * math.acos(c) / np.pi


def te(t_est: np.ndarray, t_gt: np.ndarray) -> float:
    """Translational error: Euclidean distance of the translations (input units, mm)."""
    return float(np.linalg.norm(_vec(t_gt, "t_gt") - _vec(t_est, "t_est")))


def add(R_est, t_est, R_gt, t_gt, pts) -> float:
    """ADD: mean distance of corresponding model points [mm] (Hinterstoisser et al.)."""
    p = _pts(pts)
    a = transform_pts(p, _rot(R_est, "R_est"), _vec(t_est, "t_est"))
    b = transform_pts(p, _rot(R_gt, "R_gt"), _vec(t_gt, "t_gt"))
    return float(np.linalg.norm(a - b, axis=1).mean())


def adi(R_est, t_est, R_gt, t_gt, pts) -> float:
    """ADI (ADD-S): mean distance from each GT-posed point to the nearest estimated point [mm]."""
    p = _pts(pts)
    a = transform_pts(p, _rot(R_est, "R_est"), _vec(t_est, "t_est"))
    b = transform_pts(p, _rot(R_gt, "R_gt"), _vec(t_gt, "t_gt"))
    d, _ = spatial.cKDTree(a).query(b, k=1)
    return float(d.mean())


def _sym_gt_poses(R_gt: np.ndarray, t_gt: np.ndarray, syms) -> tuple[np.ndarray, np.ndarray]:
    Rs, ts = _stack_syms(syms)
    R_sym = np.matmul(R_gt[None], Rs)  # R_gt . R_s
    t_sym = np.matmul(R_gt[None], ts[:, :, None]) + t_gt[None]  # R_gt . t_s + t_gt, (S, 3, 1)
    return R_sym, t_sym


def mssd(R_est, t_est, R_gt, t_gt, pts, syms) -> float:
    """Maximum Symmetry-aware Surface Distance [mm] (BOP19).

    ``min over symmetries S of max over points of || (R_e x + t_e) - (R_g S x + t_g') ||``.
    """
    p = _pts(pts)
    R_est, t_est = _rot(R_est, "R_est"), _vec(t_est, "t_est")
    R_gt, t_gt = _rot(R_gt, "R_gt"), _vec(t_gt, "t_gt")
    pe = transform_pts(p, R_est, t_est)
    R_sym, t_sym = _sym_gt_poses(R_gt, t_gt, syms)
    best = math.inf
    chunk = max(1, 2_000_000 // max(1, p.shape[0]))
    for s0 in range(0, R_sym.shape[0], chunk):
        pg = np.matmul(R_sym[s0 : s0 + chunk], p.T) + t_sym[s0 : s0 + chunk]  # (s, 3, N)
        d = np.sqrt(((pe.T[None] - pg) ** 2).sum(axis=1)).max(axis=1)
        best = min(best, float(d.min()))
    return best


def mspd(R_est, t_est, R_gt, t_gt, K, pts, syms) -> float:
    """Maximum Symmetry-aware Projection Distance [px] (BOP19)."""
    p = _pts(pts)
    K = _K(K)
    R_est, t_est = _rot(R_est, "R_est"), _vec(t_est, "t_est")
    R_gt, t_gt = _rot(R_gt, "R_gt"), _vec(t_gt, "t_gt")
    pe = project_pts(p, K, R_est, t_est)
    R_sym, t_sym = _sym_gt_poses(R_gt, t_gt, syms)
    ph = np.hstack((p, np.ones((p.shape[0], 1)))).T  # (4, N)
    best = math.inf
    chunk = max(1, 2_000_000 // max(1, p.shape[0]))
    for s0 in range(0, R_sym.shape[0], chunk):
        P = np.matmul(K[None], np.concatenate((R_sym[s0 : s0 + chunk], t_sym[s0 : s0 + chunk]), axis=2))
        im = np.matmul(P, ph)  # (s, 3, N)
        im = im[:, :2] / im[:, 2:3]
        d = np.sqrt(((pe.T[None] - im) ** 2).sum(axis=1)).max(axis=1)
        best = min(best, float(d.min()))
    return best


# ----------------------------------------------------------------------------- VSD
class DepthRenderFn(Protocol):
    def __call__(self, obj_id: int, R: np.ndarray, t: np.ndarray, K: np.ndarray) -> np.ndarray: ...


RendererLike = Union[DepthRenderFn, Any]


def _render(renderer: RendererLike, obj_id: int, R: np.ndarray, t: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Depth [mm] of one object: a callable ``(obj_id, R, t, K)`` or a toolkit-style renderer."""
    if hasattr(renderer, "render_object"):
        out = renderer.render_object(obj_id, R, t, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
        return np.asarray(out["depth"] if isinstance(out, Mapping) else out)
    if callable(renderer):
        return np.asarray(renderer(obj_id, R, t, K))
    raise ValueError("renderer must be callable (obj_id, R, t, K) -> depth or have render_object()")


def vsd(
    R_est,
    t_est,
    R_gt,
    t_gt,
    depth_test: np.ndarray,
    K: np.ndarray,
    delta: float,
    taus: Sequence[float],
    normalized_by_diameter: bool,
    diameter: float,
    renderer: RendererLike,
    obj_id: int,
    cost_type: str = "step",
) -> list[float]:
    """Visible Surface Discrepancy (Hodan, Michel et al., ECCV'18), one error per tau.

    Args:
        depth_test: (H, W) scene depth [mm], 0 = missing.
        delta: visibility tolerance [mm] (15 in BOP19, 5 for ITODD).
        taus: misalignment tolerances (fractions of the diameter if ``normalized_by_diameter``).
        renderer: ``renderer(obj_id, R, t, K) -> (H, W) depth mm`` (0 = empty), e.g. a
            :class:`~sc6d_jax.metrics.VsdRenderer`, or a toolkit-style object with
            ``render_object(obj_id, R, t, fx, fy, cx, cy)['depth']``.
        cost_type: ``'step'`` (BOP since 2017) or ``'tlinear'``.
    """
    R_est, t_est = _rot(R_est, "R_est"), _vec(t_est, "t_est")
    R_gt, t_gt = _rot(R_gt, "R_gt"), _vec(t_gt, "t_gt")
    K = _K(K)
    depth_test = np.asarray(depth_test)
    if depth_test.ndim != 2:
        raise ValueError(f"depth_test must be a 2-D image, got shape {depth_test.shape}")
    if cost_type not in ("step", "tlinear"):
        raise ValueError(f"cost_type must be 'step' or 'tlinear', got {cost_type!r}")
    taus = [float(x) for x in taus]
    if not taus or any(not x > 0 for x in taus):
        raise ValueError(f"taus must be a non-empty list of positive numbers, got {taus}")
    if normalized_by_diameter and not (diameter and diameter > 0):
        raise ValueError(f"diameter must be positive, got {diameter!r}")

    depth_est = _render(renderer, obj_id, R_est, t_est, K)
    depth_gt = _render(renderer, obj_id, R_gt, t_gt, K)
    for name, d in (("estimate", depth_est), ("ground truth", depth_gt)):
        if d.shape != depth_test.shape:
            raise ValueError(f"rendered {name} depth has shape {d.shape}, depth_test has {depth_test.shape}")

    dist_test = depth_to_distance(depth_test, K)
    dist_gt = depth_to_distance(depth_gt, K)
    dist_est = depth_to_distance(depth_est, K)

    visib_gt = _visib_mask(dist_test, dist_gt, delta)
    visib_est = _visib_mask(dist_test, dist_est, delta)
    visib_est = np.logical_or(visib_est, np.logical_and(visib_gt, dist_est > 0))

    inter = np.logical_and(visib_gt, visib_est)
    union_count = int(np.logical_or(visib_gt, visib_est).sum())
    comp_count = union_count - int(inter.sum())
    dists = np.abs(dist_gt[inter] - dist_est[inter])
    if normalized_by_diameter:
        dists /= diameter

    if union_count == 0:
        return [1.0] * len(taus)
    errors = []
    for tau in taus:
        if cost_type == "step":
            costs = dists >= tau
        else:
            costs = np.minimum(dists / tau, 1.0)
        errors.append(float((np.sum(costs) + comp_count) / float(union_count)))
    return errors
