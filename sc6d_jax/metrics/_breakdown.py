"""Pose-error breakdown: where the error of a set of estimates lies (rotation, depth, image centre).

AR says how many targets are correct; the breakdown says how wrong the others are. Per target
(the BOP19 targets: ground truths of a target object with visible fraction >= ``visib_gt_min``)
three errors of the paired estimate:

- ``rot_deg``: symmetry-aware rotation error in degrees, the smallest geodesic angle between
  ``R_est`` and ``R_gt @ R_s`` over the object's symmetry rotations ``R_s`` (from
  ``models_info.json`` via :func:`symmetry_transformations`, continuous symmetries discretised,
  so a pose rotated about a continuous axis scores at most half a discretisation step);
- ``depth_rel``: relative depth error ``|t_est_z - t_gt_z| / t_gt_z`` (0.05 = 5 %);
- ``centre_px``: distance in pixels between the projections of the object origin ``t`` under
  ``K`` for the estimate and the ground truth;
- next to them, ``depth_signed`` (``(t_est_z - t_gt_z) / t_gt_z``: positive = too far),
  ``ray_deg``, the angle between the ground truth's ray ``t_gt`` and the optical axis, and
  ``extent`` (:func:`extent_ratio`): the object's extent across the view at the ground truth's
  pose over its diameter, low when it is seen along its length (foreshortened).

Pairing (:func:`breakdown_errors`): per target object of an image, the ``inst_count``
highest-scoring estimates (the ones BOP19 evaluates) are taken in order of decreasing score
(stable on ties), and each is paired with the still unpaired valid ground truth of its object
whose translation is closest (Euclidean distance of ``t``). A valid ground truth left without an
estimate is a **miss**: ``rot_deg = 180``, ``depth_rel = inf``, ``centre_px = inf``, so misses
count as failures in every fraction and push the medians up.

:func:`summarize_breakdown` turns the per-target errors into medians and the fractions of targets
*strictly* under 5 / 10 / 20 degrees and 2 % / 5 % relative depth error, and the median signed
depth error (``depth_bias_median``, over the estimated targets), overall, per object, per visible
fraction of the target (:data:`VISIBILITY_BINS`: how the errors grow with occlusion) and per angle
of the target's ray from the optical axis (:data:`RAY_BINS`: an off-axis object is seen stretched
along its ray's direction, by up to ``1/cos`` of that angle, which a depth read off the crop's
apparent size has to undo) and per extent across the view (:data:`EXTENT_BINS`: with crops cut
from exact boxes the depth code is that extent, which changes fastest with the rotation where
the object is seen along its length).
Everything here works on in-memory arrays; ``evaluate_images`` / ``evaluate_bop19`` store the
summary under the key ``"breakdown"`` of their scores.
"""

from __future__ import annotations

import math
from typing import Any, Callable, Iterable, Mapping, NamedTuple, Sequence

import numpy as np

from sc6d_jax.metrics._bop19 import (
    MAX_SYM_DISC_STEP,
    VISIB_GT_MIN,
    EvalImage,
    ObjectModel,
    _attr,
    group_estimates,
    _top_n,
    _valid_gts,
)
from sc6d_jax.metrics._pose_error import _rot
from sc6d_jax.metrics._pose_error import _vec as _vec31
from sc6d_jax.metrics._symmetry import symmetry_transformations

ROT_THRESHOLDS_DEG: tuple[float, ...] = (5.0, 10.0, 20.0)
DEPTH_THRESHOLDS_REL: tuple[float, ...] = (0.02, 0.05)
MISS: dict[str, float] = {"rot_deg": 180.0, "depth_rel": math.inf, "centre_px": math.inf}
"""The errors recorded for a target without an estimate."""

VISIBILITY_BINS: tuple[tuple[str, float, float], ...] = (
    ("<50%", 0.0, 0.5), ("50-80%", 0.5, 0.8), ("80-95%", 0.8, 0.95), (">=95%", 0.95, math.inf),
)
"""(label, low, high) of the visible-fraction groups of :func:`summarize_breakdown` (low <= v < high)."""

RAY_BINS: tuple[tuple[str, float, float], ...] = (
    ("<10deg", 0.0, 10.0), ("10-20deg", 10.0, 20.0), (">=20deg", 20.0, math.inf),
)
"""(label, low, high) in degrees of the ray-angle groups of :func:`summarize_breakdown`."""

EXTENT_BINS: tuple[tuple[str, float, float], ...] = (
    ("<0.75", 0.0, 0.75), ("0.75-0.9", 0.75, 0.9), (">=0.9", 0.9, math.inf),
)
"""(label, low, high) of the groups by :func:`extent_ratio` of :func:`summarize_breakdown`."""

class Grouping(NamedTuple):
    """One grouping of :func:`summarize_breakdown`'s targets by a per-target value."""

    key: str  # the summary's key
    value: str  # the per-target value it groups by
    bins: tuple[tuple[str, float, float], ...]  # (label, low, high)
    valid: Callable[[float], bool]  # the value's valid range, as a test
    valid_words: str  # the same range in words (error messages)
    title: str  # the heading of its table (``sc6d eval``)


#: The groupings of :func:`summarize_breakdown`, in the order they are reported.
GROUPINGS: tuple[Grouping, ...] = (
    Grouping("per_visibility", "visib_fract", VISIBILITY_BINS, lambda v: 0.0 <= v <= 1.0, "in [0, 1]",
             "by visible fraction of the target:"),
    Grouping("per_ray_angle", "ray_deg", RAY_BINS, lambda v: 0.0 <= v <= 180.0, "in [0, 180]",
             "by angle of the target's ray from the optical axis:"),
    Grouping("per_extent", "extent", EXTENT_BINS, lambda v: v > 0.0, "a positive number",
             "by the target's extent across the view over its diameter (low: seen along its length):"),
)

SUMMARY_KEYS: tuple[str, ...] = (
    "n", "missed", "rot_median_deg", "depth_rel_median", "centre_median_px",
    "rot_under_5", "rot_under_10", "rot_under_20", "rot_over_90", "depth_under_2pct", "depth_under_5pct",
    "depth_bias_median",
)


# ----------------------------------------------------------------------------- validation
def _vec(t: Any, name: str) -> np.ndarray:
    """A translation as a flat (3,) float64 array (validated as in the pose errors)."""
    return _vec31(t, name).reshape(3)


def _sym_rotations(sym_rotations: Any) -> np.ndarray:
    if sym_rotations is None:
        return np.eye(3)[None]
    Rs = np.asarray(sym_rotations, dtype=np.float64)
    if Rs.shape == (3, 3):
        Rs = Rs[None]
    if Rs.ndim != 3 or Rs.shape[1:] != (3, 3) or Rs.shape[0] == 0:
        raise ValueError(f"sym_rotations must have shape (N, 3, 3) with N >= 1, got {np.shape(sym_rotations)}")
    if not np.isfinite(Rs).all():
        raise ValueError("sym_rotations must be finite")
    return Rs


def symmetry_rotations(model_info: Mapping[str, Any], max_sym_disc_step: float = MAX_SYM_DISC_STEP) -> np.ndarray:
    """(N, 3, 3) rotation parts of :func:`symmetry_transformations` (identity first; N = 1 if asymmetric)."""
    return np.stack([s["R"] for s in symmetry_transformations(model_info, max_sym_disc_step)])


# ----------------------------------------------------------------------------- per target
def rotation_error_deg(R_est: Any, R_gt: Any, sym_rotations: Any = None) -> float:
    """Symmetry-aware rotation error [degrees], in [0, 180].

    ``min_s angle(R_est, R_gt @ R_s)`` over the symmetry rotations ``sym_rotations`` ((N, 3, 3);
    None or the identity alone for an asymmetric object). The best ``s`` is the one with the
    largest ``trace((R_gt R_s)^T R_est)`` (all N at once); its angle is computed with ``atan2``
    of the relative rotation, accurate also near 0 and 180 degrees.
    """
    R_e = _rot(R_est, "R_est")
    R_g = _rot(R_gt, "R_gt")
    Rs = _sym_rotations(sym_rotations)
    equiv = np.einsum("ij,sjk->sik", R_g, Rs)  # (N, 3, 3): R_gt @ R_s
    tr = np.einsum("sij,ij->s", equiv, R_e)  # trace(equiv_s^T R_est)
    D = equiv[int(np.argmax(tr))].T @ R_e  # relative rotation of the best symmetric equivalent
    sin2 = math.hypot(D[2, 1] - D[1, 2], D[0, 2] - D[2, 0], D[1, 0] - D[0, 1])  # 2 sin(angle)
    cos2 = float(np.trace(D)) - 1.0  # 2 cos(angle)
    return float(math.degrees(math.atan2(sin2, cos2)))


def pose_errors(
    R_est: Any, t_est: Any, R_gt: Any, t_gt: Any, K: Any, sym_rotations: Any = None
) -> dict[str, float]:
    """The three breakdown errors of one estimate against one ground truth.

    Args:
        R_est, R_gt: (3, 3) rotations (model to camera).
        t_est, t_gt: translations (3,) in mm (any unit, the same for both); ``t_gt_z`` must be > 0.
        K: (3, 3) camera matrix (pixels, OpenCV/BOP convention).
        sym_rotations: (N, 3, 3) symmetry rotations of the object, or None (asymmetric).

    Returns:
        ``{"rot_deg": degrees, "depth_rel": |t_est_z - t_gt_z| / t_gt_z, "centre_px": pixels,
        "depth_signed": (t_est_z - t_gt_z) / t_gt_z, "ray_deg": angle of t_gt from the optical
        axis}``; ``centre_px`` is inf when the estimate's centre is not in front of the camera
        (t_z <= 0).
    """
    t_e = _vec(t_est, "t_est")
    t_g = _vec(t_gt, "t_gt")
    K = _rot(K, "K")
    if not t_g[2] > 0:
        raise ValueError(f"t_gt must be in front of the camera (t_gt_z > 0), got t_gt_z = {t_g[2]}")
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise ValueError(f"K must have positive focal lengths, got {K.tolist()}")
    rot = rotation_error_deg(R_est, R_gt, sym_rotations)
    depth = abs(t_e[2] - t_g[2]) / t_g[2]
    if t_e[2] > 0:
        uv_e, uv_g = K @ t_e, K @ t_g
        centre = float(np.linalg.norm(uv_e[:2] / uv_e[2] - uv_g[:2] / uv_g[2]))
    else:
        centre = math.inf
    return {"rot_deg": rot, "depth_rel": float(depth), "centre_px": centre,
            "depth_signed": float((t_e[2] - t_g[2]) / t_g[2]), "ray_deg": ray_angle_deg(t_g)}


def extent_ratio(pts: Any, R: Any, t: Any, K: Any, diameter: float) -> float:
    """The object's extent across the view over its diameter: the longer side of the box of its
    points ``pts`` (N, 3) projected at pose (R, t) under ``K``, times ``t_z / f`` (back to mm at
    the object's depth), over ``diameter``. About 1 when its longest axis lies across the view,
    lower when it is seen along it (a rod end-on: its thickness over its length)."""
    p = np.asarray(pts, dtype=np.float64) @ _rot(R, "R").T + _vec(t, "t")
    K = _rot(K, "K")
    if not np.all(p[:, 2] > 0):
        raise ValueError("the object must lie in front of the camera")
    uv = p @ K.T
    uv = uv[:, :2] / uv[:, 2:3]
    w, h = uv.max(0) - uv.min(0)
    f = math.sqrt(K[0, 0] * K[1, 1])
    return float(max(w, h) * float(_vec(t, "t")[2]) / (f * float(diameter)))


def ray_angle_deg(t: Any) -> float:
    """Angle in degrees between the ray to ``t`` (3,) and the optical axis (z)."""
    t = np.asarray(t, dtype=np.float64).reshape(3)
    return float(np.degrees(np.arctan2(np.hypot(t[0], t[1]), t[2])))


def breakdown_errors(
    images: Iterable[EvalImage],
    estimates: Iterable[Any],
    models: Mapping[int, ObjectModel],
    *,
    visib_gt_min: float = VISIB_GT_MIN,
) -> list[dict[str, Any]]:
    """Per-target breakdown errors of in-memory images and estimates.

    Targets are the valid ground truths (target object of the image, visible fraction >=
    ``visib_gt_min``). Per (image, object) the ``inst_count`` highest-scoring estimates, in order
    of decreasing score, each take the closest (translation distance) still free target of their
    object. A target left without an estimate is a miss with the errors :data:`MISS` (rotation
    180 deg, depth and centre errors inf).

    Args:
        images: the ``EvalImage`` s (ground truths, targets ``{obj_id: inst_count}``, K).
        estimates: objects or dicts with scene_id, im_id, obj_id, score, R (3x3), t (3, mm).
        models: ``ObjectModel`` per object id (its ``syms`` give the symmetry rotations).
        visib_gt_min: which ground truths are targets, as in ``score_errors``.

    Returns:
        one dict per valid ground truth, in image order then ground-truth order: ``scene_id``,
        ``im_id``, ``obj_id``, ``gt_id`` (index in the image's ground truths), ``est_id`` (index
        among the estimates of (scene, image, object) in input order; None for a miss),
        ``score`` (None for a miss), ``missed`` (bool), ``rot_deg``, ``depth_rel``, ``centre_px``,
        ``visib_fract`` (the ground truth's visible fraction), ``depth_signed``, ``ray_deg`` and
        ``extent`` (:func:`extent_ratio` at the ground truth's pose; None for an object without
        a model, which has no estimate either).
    """
    groups = group_estimates(estimates)
    sym_cache: dict[int, np.ndarray] = {}
    out: list[dict[str, Any]] = []
    for img in images:
        valid = _valid_gts(img, visib_gt_min)
        K = np.asarray(img.K, dtype=np.float64)
        paired: dict[int, dict[str, Any]] = {}
        for obj_id, inst_count in img.targets.items():
            group = groups.get((img.scene_id, img.im_id, obj_id), [])
            free = [i for i, g in enumerate(img.gts) if g.obj_id == obj_id and valid[i]]
            if not group or not free:
                continue
            if obj_id not in models:
                raise ValueError(f"object {obj_id} of image {img.scene_id}/{img.im_id} has no model")
            if obj_id not in sym_cache:
                sym_cache[obj_id] = np.stack([np.asarray(s["R"], dtype=np.float64) for s in models[obj_id].syms])
            for est_id, est in _top_n(group, int(inst_count)):
                if not free:
                    break
                t_e = _vec(_attr(est, "t"), f"t of estimate {est_id} of {img.scene_id}/{img.im_id}/obj {obj_id}")
                dists = [float(np.linalg.norm(t_e - np.asarray(img.gts[i].t, dtype=np.float64).reshape(3))) for i in free]
                gt_id = free.pop(int(np.argmin(dists)))
                g = img.gts[gt_id]
                errs = pose_errors(_attr(est, "R"), t_e, g.R, g.t, K, sym_cache[obj_id])
                paired[gt_id] = {"est_id": est_id, "score": float(_attr(est, "score")), "missed": False, **errs}
        for gt_id, g in enumerate(img.gts):
            if not valid[gt_id]:
                continue
            rec = paired.get(gt_id, {"est_id": None, "score": None, "missed": True, **MISS,
                                     "ray_deg": ray_angle_deg(g.t)})
            m = models.get(int(g.obj_id))
            ext = None if m is None else extent_ratio(m.pts, g.R, g.t, K, m.diameter)
            out.append({"scene_id": img.scene_id, "im_id": img.im_id, "obj_id": int(g.obj_id), "gt_id": gt_id, **rec,
                        "visib_fract": float(g.visib_fract), "extent": ext})
    return out


# ----------------------------------------------------------------------------- summary
def _summary(rot: np.ndarray, depth: np.ndarray, centre: np.ndarray, missed: int,
             signed: np.ndarray) -> dict[str, Any]:
    n = len(rot)
    if n == 0:
        return {k: (0 if k in ("n", "missed") else None) for k in SUMMARY_KEYS}
    return {
        "n": int(n),
        "missed": int(missed),
        "rot_median_deg": float(np.median(rot)),
        "depth_rel_median": float(np.median(depth)),
        "centre_median_px": float(np.median(centre)),
        "rot_under_5": float(np.mean(rot < 5.0)),
        "rot_under_10": float(np.mean(rot < 10.0)),
        "rot_under_20": float(np.mean(rot < 20.0)),
        "rot_over_90": float(np.mean(rot > 90.0)),  # turned the wrong way round (near-symmetric objects)
        "depth_under_2pct": float(np.mean(depth < 0.02)),
        "depth_under_5pct": float(np.mean(depth < 0.05)),
        "depth_bias_median": _finite_median(signed),
    }


def _finite_median(x: np.ndarray) -> float | None:
    """Median of the finite entries (None without any): the signed depth error of the estimated
    targets (a miss has none)."""
    x = x[np.isfinite(x)]
    return float(np.median(x)) if len(x) else None


def summarize_breakdown(per_target: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Medians and fractions of per-target errors, overall and per object.

    Args:
        per_target: dicts with ``obj_id``, ``rot_deg`` [degrees], ``depth_rel`` [fraction],
            ``centre_px`` [pixels] (e.g. from :func:`breakdown_errors`); an optional ``missed``
            (bool) is counted, an optional ``depth_signed`` [fraction] makes the depth bias.
            Misses should carry :data:`MISS` (180, inf, inf). When every target has a
            ``visib_fract`` (a ``ray_deg``, an ``extent``), the summary is also grouped by it.

    Returns:
        ``{"overall": S, "per_object": {obj_id: S}, "per_visibility": {label: S},
        "per_ray_angle": {label: S}, "per_extent": {label: S}}`` (objects sorted by id; the groups
        of :data:`VISIBILITY_BINS`, :data:`RAY_BINS` and :data:`EXTENT_BINS` that hold targets, in
        their order; each grouping only when every target has its value),
        each ``S`` with ``n`` (targets), ``missed``, ``rot_median_deg``, ``depth_rel_median``
        (fraction, 0.05 = 5 %), ``centre_median_px`` (medians; inf when more than half are
        misses), ``rot_under_5`` / ``_10`` / ``_20`` (degrees), ``depth_under_2pct`` / ``_5pct``
        (fractions of targets with the error strictly below the threshold) and
        ``depth_bias_median`` (median ``depth_signed`` of the targets that have one; None without).
        With no targets, ``n`` is 0 and the rest None.
    """
    if isinstance(per_target, Mapping):
        raise ValueError("per_target must be a list of dicts (one per target), got a single mapping")
    obj: list[int] = []
    cols: list[list[float]] = [[], [], []]
    missed: list[bool] = []
    signed: list[float] = []
    grouped: list[list[float]] = [[] for _ in GROUPINGS]
    for i, d in enumerate(per_target):
        if not isinstance(d, Mapping):
            raise ValueError(f"per_target[{i}] must be a dict, got {type(d).__name__}")
        for k in ("obj_id", "rot_deg", "depth_rel", "centre_px"):
            if k not in d:
                raise ValueError(f"per_target[{i}] has no {k!r}")
        obj.append(int(d["obj_id"]))
        for c, k in zip(cols, ("rot_deg", "depth_rel", "centre_px")):
            v = float(d[k])
            if math.isnan(v) or v < 0:
                raise ValueError(f"per_target[{i}][{k!r}] must be a non-negative number (inf allowed), got {d[k]!r}")
            c.append(v)
        missed.append(bool(d.get("missed", False)))
        sd = d.get("depth_signed")
        signed.append(math.nan if sd is None else float(sd))
        for vals, g in zip(grouped, GROUPINGS):
            if d.get(g.value) is not None:
                v = float(d[g.value])
                if not g.valid(v):
                    raise ValueError(f"per_target[{i}][{g.value!r}] must be {g.valid_words}, got {d[g.value]!r}")
                vals.append(v)
    o = np.asarray(obj, dtype=np.int64)
    sg = np.asarray(signed, dtype=np.float64)
    rot, depth, centre = (np.asarray(c, dtype=np.float64) for c in cols)
    m = np.asarray(missed, dtype=bool)
    per_object = {}
    for oid in sorted(set(obj)):
        sel = o == oid
        per_object[oid] = _summary(rot[sel], depth[sel], centre[sel], int(m[sel].sum()), sg[sel])
    out = {"overall": _summary(rot, depth, centre, int(m.sum()), sg), "per_object": per_object}
    for vals, g in zip(grouped, GROUPINGS):
        if vals and len(vals) == len(obj):
            v = np.asarray(vals)
            out[g.key] = {
                label: _summary(rot[sel], depth[sel], centre[sel], int(m[sel].sum()), sg[sel])
                for label, lo, hi in g.bins if (sel := (v >= lo) & (v < hi)).any()
            }
    return out


def format_breakdown_line(s: Mapping[str, Any]) -> str:
    """One line of a summary ``S`` (see :func:`summarize_breakdown`; JSON None = inf/absent)."""
    if not s or not s.get("n"):
        return "pose errors: no targets"

    def num(v: Any, scale: float = 1.0, fmt: str = ".1f") -> str:
        return "inf" if v is None or not math.isfinite(float(v)) else format(float(v) * scale, fmt)

    def pct(v: Any) -> str:
        return "-" if v is None else f"{100.0 * float(v):.0f}"

    return (
        f"pose errors ({s['n']} targets, {s.get('missed', 0)} without estimate): "
        f"rotation median {num(s['rot_median_deg'])} deg, <5/10/20 deg "
        f"{pct(s['rot_under_5'])}/{pct(s['rot_under_10'])}/{pct(s['rot_under_20'])} %; "
        f"depth median {num(s['depth_rel_median'], 100.0)} %, <2/5 % "
        f"{pct(s['depth_under_2pct'])}/{pct(s['depth_under_5pct'])} %; "
        f"centre median {num(s['centre_median_px'])} px"
    )
