"""Symmetry transformations of object models (BOP ``models_info.json`` convention).

A symmetry transformation ``S = (R_s, t_s)`` maps the model onto itself; the ground-truth pose
``(R, t)`` is then indistinguishable from ``(R R_s, R t_s + t)``. Continuous symmetries are
discretised exactly as the BOP toolkit does (``misc.get_symmetry_transformations``): the step
count is ``ceil(pi / max_sym_disc_step)`` over the full turn, so the vertex furthest from the
axis travels at most ``max_sym_disc_step`` times the diameter between consecutive rotations.
"""

from __future__ import annotations

import math
from typing import Any, Mapping, Sequence

import numpy as np

Symmetry = dict[str, np.ndarray]  # {"R": (3, 3) float64, "t": (3,) float64 [mm]}


def _axis_angle_matrix(angle: float, axis: np.ndarray) -> np.ndarray:
    """Rotation by ``angle`` radians about the (normalised) ``axis`` (Rodrigues' formula)."""
    d = np.asarray(axis, dtype=np.float64)
    d = d / np.linalg.norm(d)
    c, s = math.cos(angle), math.sin(angle)
    R = np.diag([c, c, c])
    R += np.outer(d, d) * (1.0 - c)
    ds = d * s
    R += np.array([[0.0, -ds[2], ds[1]], [ds[2], 0.0, -ds[0]], [-ds[1], ds[0], 0.0]])
    return R


def symmetry_transformations(
    model_info: Mapping[str, Any], max_sym_disc_step: float = 0.01
) -> list[Symmetry]:
    """The set of symmetry transformations of one object (identity first).

    Args:
        model_info: one entry of ``models_info.json`` (a dict, or a ``sc6d_jax.bop.ModelInfo``); optional keys ``symmetries_discrete``
            (list of 4x4 matrices, flat row-major 16 numbers or nested) and
            ``symmetries_continuous`` (list of ``{"axis": [3], "offset": [3]}``).
        max_sym_disc_step: maximum fraction of the diameter travelled by the vertex furthest
            from a continuous axis between consecutive discretised rotations.

    Returns:
        list of ``{"R": (3, 3), "t": (3,)}`` (float64, t in the model's units), in the BOP
        toolkit's order: for each discrete symmetry (identity first), all discretised
        continuous rotations composed with it (or the discrete one alone if there is no
        continuous symmetry).
    """
    if hasattr(model_info, "as_dict") and not isinstance(model_info, Mapping):
        model_info = model_info.as_dict()  # sc6d_jax.bop.ModelInfo
    if not isinstance(model_info, Mapping):
        raise ValueError(f"model_info must be a mapping (one models_info.json entry), got {type(model_info)}")
    if not (isinstance(max_sym_disc_step, (int, float)) and max_sym_disc_step > 0):
        raise ValueError(f"max_sym_disc_step must be a positive number, got {max_sym_disc_step!r}")

    disc: list[Symmetry] = [{"R": np.eye(3), "t": np.zeros(3)}]
    for i, sym in enumerate(model_info.get("symmetries_discrete", []) or []):
        m = np.asarray(sym, dtype=np.float64)
        if m.size != 16:
            raise ValueError(f"symmetries_discrete[{i}] must have 16 numbers (4x4), got {m.size}")
        m = m.reshape(4, 4)
        disc.append({"R": m[:3, :3].copy(), "t": m[:3, 3].copy()})

    cont: list[Symmetry] = []
    for i, sym in enumerate(model_info.get("symmetries_continuous", []) or []):
        try:
            axis = np.asarray(sym["axis"], dtype=np.float64).reshape(3)
            offset = np.asarray(sym["offset"], dtype=np.float64).reshape(3)
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"symmetries_continuous[{i}] needs 'axis' and 'offset' of 3 numbers: {exc}") from None
        if not np.linalg.norm(axis) > 0:
            raise ValueError(f"symmetries_continuous[{i}] has a zero axis")
        n_steps = int(np.ceil(np.pi / max_sym_disc_step))
        step = 2.0 * np.pi / n_steps
        for k in range(n_steps):
            R = _axis_angle_matrix(k * step, axis)
            cont.append({"R": R, "t": -R.dot(offset) + offset})

    if not cont:
        return disc
    out: list[Symmetry] = []
    for d in disc:
        for c in cont:
            out.append({"R": c["R"].dot(d["R"]), "t": c["R"].dot(d["t"]) + c["t"]})
    return out


def _stack_syms(syms: Sequence[Mapping[str, Any]]) -> tuple[np.ndarray, np.ndarray]:
    """(S, 3, 3) rotations and (S, 3) translations of a symmetry list (validated)."""
    if len(syms) == 0:
        raise ValueError("syms must hold at least one transformation (the identity)")
    try:
        Rs = np.stack([np.asarray(s["R"], dtype=np.float64).reshape(3, 3) for s in syms])
        ts = np.stack([np.asarray(s["t"], dtype=np.float64).reshape(3) for s in syms])
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"syms must be a list of {{'R': 3x3, 't': 3}} dicts: {exc}") from None
    return Rs, ts


def symmetry_coverage(
    R_topk: np.ndarray,
    R_gt: np.ndarray,
    syms: Sequence[Mapping[str, Any]],
    angle_threshold_deg: float,
) -> tuple[int, float]:
    """How many symmetric equivalents of the ground truth the top-k rotations cover.

    The equivalents are ``R_gt @ R_s`` for every symmetry in ``syms``; an equivalent is covered
    when some rotation in ``R_topk`` lies within ``angle_threshold_deg`` (geodesic) of it.
    Rotation-only (the symmetries' translations are ignored). For continuous symmetries the
    count refers to the discretised set, so the fraction is the meaningful figure.

    Returns:
        (count, fraction) with fraction = count / len(syms).
    """
    Rk = np.asarray(R_topk, dtype=np.float64)
    if Rk.ndim == 2:
        Rk = Rk[None]
    if Rk.ndim != 3 or Rk.shape[1:] != (3, 3) or Rk.shape[0] == 0:
        raise ValueError(f"R_topk must have shape (k, 3, 3) with k >= 1, got {np.shape(R_topk)}")
    Rg = np.asarray(R_gt, dtype=np.float64)
    if Rg.shape != (3, 3):
        raise ValueError(f"R_gt must have shape (3, 3), got {Rg.shape}")
    if not (np.isfinite(Rk).all() and np.isfinite(Rg).all()):
        raise ValueError("rotations must be finite")
    if not (isinstance(angle_threshold_deg, (int, float)) and angle_threshold_deg >= 0):
        raise ValueError(f"angle_threshold_deg must be a non-negative number, got {angle_threshold_deg!r}")
    Rs, _ = _stack_syms(syms)
    equiv = np.einsum("ij,sjk->sik", Rg, Rs)  # (S, 3, 3)
    # trace(A^T B) for every pair (s, k)
    tr = np.einsum("sij,kij->sk", equiv, Rk)
    ang = np.degrees(np.arccos(np.clip(0.5 * (tr - 1.0), -1.0, 1.0)))
    covered = (ang <= angle_threshold_deg).any(axis=1)
    count = int(covered.sum())
    return count, count / len(syms)
