"""BOP19 average recall (AR_VSD, AR_MSSD, AR_MSPD, AR), as the BOP toolkit computes it.

The procedure follows ``scripts/eval_bop19_pose.py`` -> ``eval_calc_errors.py`` ->
``eval_calc_scores.py`` (``pose_matching.match_poses``, ``score.calc_localization_scores``):

1. Per target ``(scene, image, object, inst_count)`` of ``test_targets_bop19.json``, the
   ``inst_count`` estimates with the highest score (stable order on ties) are kept. Each is
   compared with every ground truth of the same object in the image: MSSD (``inf`` when the
   centres are a diameter or more apart), MSPD, and VSD per tau (1 when the projected bounding
   spheres do not overlap).
2. For every threshold (and tau for VSD) the estimates are matched greedily in order of
   decreasing score, each to the valid, still unmatched ground truth with the lowest error
   strictly below the threshold. A ground truth is valid when its object is a target of the
   image and its visible fraction is at least ``visib_gt_min`` (0.1).
3. Recall = matched valid ground truths / valid ground truths, over the whole dataset; AR of one
   error = mean recall over its thresholds (100 (tau, threshold) pairs for VSD); AR = mean of the
   three. MSSD is normalised by the diameter, MSPD by ``640 / image width``.

Where the dataset has no depth images VSD is skipped: AR is then the mean of AR_MSSD and
AR_MSPD and the result says so (``vsd_available: false``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, Mapping, Sequence

import numpy as np

from sc6d_jax.metrics._pose_error import (
    RendererLike,
    mspd,
    mssd,
    overlapping_sphere_projections,
    vsd,
)
from sc6d_jax.metrics._symmetry import Symmetry, symmetry_transformations

# The toolkit's grids, produced by numpy.arange exactly as in eval_bop19_pose.py
# (so 0.15000000000000002 and 0.35000000000000003 are what they are).
VSD_TAUS: tuple[float, ...] = tuple(float(x) for x in np.arange(0.05, 0.51, 0.05))
VSD_THRESHOLDS: tuple[float, ...] = tuple(float(x) for x in np.arange(0.05, 0.51, 0.05))
MSSD_THRESHOLDS: tuple[float, ...] = tuple(float(x) for x in np.arange(0.05, 0.51, 0.05))
MSPD_THRESHOLDS: tuple[float, ...] = tuple(float(x) for x in np.arange(5, 51, 5))
VSD_DELTA = 15.0
VISIB_GT_MIN = 0.1
MAX_SYM_DISC_STEP = 0.01

ERROR_TYPES = ("vsd", "mssd", "mspd")


@dataclass(frozen=True)
class ObjectModel:
    """What the metrics need of one object: eval-model vertices [mm], diameter, symmetries."""

    obj_id: int
    diameter: float
    pts: np.ndarray
    syms: list[Symmetry]


@dataclass(frozen=True)
class GroundTruth:
    obj_id: int
    R: np.ndarray
    t: np.ndarray
    visib_fract: float


@dataclass
class EvalImage:
    """One test image with its ground truths and targets ``{obj_id: inst_count}``.

    ``depth`` is the scene depth [mm] (0 = missing) or a zero-argument callable loading it
    (called only when VSD is computed), or None when there is no depth.
    """

    scene_id: int
    im_id: int
    K: np.ndarray
    width: int
    height: int
    gts: list[GroundTruth]
    targets: dict[int, int]
    depth: np.ndarray | Callable[[], np.ndarray] | None = None


@dataclass
class EstimateErrors:
    """Errors of one evaluated estimate w.r.t. every ground truth of its object (by gt index)."""

    scene_id: int
    im_id: int
    obj_id: int
    est_id: int  # index among the estimates of (scene, image, object), in input order
    score: float
    mssd: dict[int, float] = field(default_factory=dict)
    mspd: dict[int, float] = field(default_factory=dict)
    vsd: dict[int, list[float]] = field(default_factory=dict)


def _attr(e: Any, name: str) -> Any:
    return e[name] if isinstance(e, Mapping) else getattr(e, name)


def group_estimates(estimates: Iterable[Any]) -> dict[tuple[int, int, int], list[tuple[int, Any]]]:
    """(scene, im, obj) -> [(est_id, estimate)] in input order (est_id = position in the group)."""
    groups: dict[tuple[int, int, int], list[tuple[int, Any]]] = {}
    for e in estimates:
        key = (int(_attr(e, "scene_id")), int(_attr(e, "im_id")), int(_attr(e, "obj_id")))
        g = groups.setdefault(key, [])
        g.append((len(g), e))
    return groups


def _top_n(group: list[tuple[int, Any]], n: int) -> list[tuple[int, Any]]:
    """The n highest-scoring estimates; Python's stable sort keeps file order on equal scores."""
    return sorted(group, key=lambda x: float(_attr(x[1], "score")), reverse=True)[:n]


def compute_errors(
    images: Iterable[EvalImage],
    estimates: Iterable[Any],
    models: Mapping[int, ObjectModel],
    *,
    renderer: RendererLike | None = None,
    vsd_delta: float = VSD_DELTA,
    vsd_taus: Sequence[float] = VSD_TAUS,
    progress: bool = False,
    n_images: int | None = None,
) -> list[EstimateErrors]:
    """Pose errors of the top-``inst_count`` estimates of every target (step 1 above).

    VSD is computed only when ``renderer`` is given and the image has depth.
    Estimates need attributes (or keys) scene_id, im_id, obj_id, score, R (3x3), t (3, mm).
    """
    groups = group_estimates(estimates)
    out: list[EstimateErrors] = []
    it: Iterable[EvalImage] = images
    if progress:
        from tqdm import tqdm

        it = tqdm(images, total=n_images, desc="eval", unit="img", leave=False)
    for img in it:
        depth: np.ndarray | None = None
        K = np.asarray(img.K, dtype=np.float64)
        for obj_id, inst_count in img.targets.items():
            group = groups.get((img.scene_id, img.im_id, obj_id), [])
            if not group:
                continue
            if obj_id not in models:
                raise ValueError(f"object {obj_id} of image {img.scene_id}/{img.im_id} has no model")
            model = models[obj_id]
            gt_ids = [i for i, g in enumerate(img.gts) if g.obj_id == obj_id]
            for est_id, est in _top_n(group, int(inst_count)):
                R_e = np.asarray(_attr(est, "R"), dtype=np.float64).reshape(3, 3)
                t_e = np.asarray(_attr(est, "t"), dtype=np.float64).reshape(3)
                rec = EstimateErrors(img.scene_id, img.im_id, obj_id, est_id, float(_attr(est, "score")))
                for gt_id in gt_ids:
                    g = img.gts[gt_id]
                    R_g = np.asarray(g.R, dtype=np.float64).reshape(3, 3)
                    t_g = np.asarray(g.t, dtype=np.float64).reshape(3)
                    if np.linalg.norm(t_e - t_g) < model.diameter:
                        rec.mssd[gt_id] = mssd(R_e, t_e, R_g, t_g, model.pts, model.syms)
                    else:
                        rec.mssd[gt_id] = math.inf
                    rec.mspd[gt_id] = mspd(R_e, t_e, R_g, t_g, K, model.pts, model.syms)
                    if renderer is not None and img.depth is not None:
                        if not overlapping_sphere_projections(0.5 * model.diameter, t_e, t_g):
                            rec.vsd[gt_id] = [1.0] * len(vsd_taus)
                        else:
                            if depth is None:
                                depth = np.asarray(img.depth() if callable(img.depth) else img.depth)
                            rec.vsd[gt_id] = vsd(
                                R_e, t_e, R_g, t_g, depth, K, vsd_delta, vsd_taus, True,
                                model.diameter, renderer, obj_id, "step",
                            )
                out.append(rec)
    return out


def _valid_gts(img: EvalImage, visib_gt_min: float) -> list[bool]:
    """Which ground truths count: target object and visible enough (toolkit's localization mode).

    With ``visib_gt_min < 0`` the toolkit's newer default applies: per target object, the
    ``inst_count`` most visible ground truths are valid.
    """
    if visib_gt_min >= 0:
        return [g.obj_id in img.targets and g.visib_fract >= visib_gt_min for g in img.gts]
    order = sorted(range(len(img.gts)), key=lambda i: img.gts[i].visib_fract, reverse=True)
    to_add = dict(img.targets)
    valid = [False] * len(img.gts)
    for i in order:
        o = img.gts[i].obj_id
        if to_add.get(o, 0) > 0:
            valid[i] = True
            to_add[o] -= 1
    return valid


def _match(
    recs: list[EstimateErrors], errors_of: Callable[[EstimateErrors], Mapping[int, float]], th: float,
    valid: list[bool],
) -> set[int]:
    """Greedy matching of one (image, object): the set of matched (valid) gt indices."""
    matched: list[int] = []
    for rec in sorted(recs, key=lambda r: r.score, reverse=True):
        best_gt, best_err = -1, th
        for gt_id, err in errors_of(rec).items():
            if valid[gt_id] and gt_id not in matched and err < best_err:
                best_gt, best_err = gt_id, err
        if best_gt >= 0:
            matched.append(best_gt)
    return set(matched)


@dataclass
class _Counts:
    tps: int = 0
    tars: int = 0
    obj_tps: dict[int, int] = field(default_factory=dict)
    obj_tars: dict[int, int] = field(default_factory=dict)
    matched: set[tuple[int, int, int]] = field(default_factory=set)  # (scene_id, im_id, gt index)

    def recall(self) -> float:
        return self.tps / float(self.tars) if self.tars else 0.0

    def obj_recall(self, obj_id: int) -> float:
        n = self.obj_tars.get(obj_id, 0)
        return self.obj_tps.get(obj_id, 0) / float(n) if n else 0.0


def score_errors(
    images: Sequence[EvalImage],
    errors: Sequence[EstimateErrors],
    models: Mapping[int, ObjectModel],
    *,
    visib_gt_min: float = VISIB_GT_MIN,
    vsd_available: bool = True,
) -> dict[str, Any]:
    """Recalls and average recalls from pre-computed errors (steps 2-3 above).

    Returns a dict with the toolkit's key names (``bop19_average_recall``, ``..._vsd``,
    ``..._mssd``, ``..._mspd``; ``..._vsd`` is None when VSD is not available), ``vsd_available``,
    ``recalls`` (per threshold; VSD as [tau][threshold]), ``per_object`` (AR per error type and
    overall, per object id), ``counts``, ``per_target`` (``[scene_id, im_id, gt index, obj_id,
    share]`` per valid ground truth, in image order: the fraction of thresholds at which it was
    matched, averaged over the error types; AR is their mean) and
    ``average_recall_standard_error`` (their standard deviation over the square root of their
    number: AR's sampling error over targets; None below two targets). Two sets of estimates
    on the same targets compare best per target: the standard error of the mean difference of
    their shares is usually well below either AR's.
    """
    by_im_obj: dict[tuple[int, int, int], list[EstimateErrors]] = {}
    for r in errors:
        by_im_obj.setdefault((r.scene_id, r.im_id, r.obj_id), []).append(r)
    prepared = []
    n_valid = 0
    for img in images:
        valid = _valid_gts(img, visib_gt_min)
        n_valid += sum(valid)
        obj_ids = sorted({g.obj_id for g in img.gts})
        prepared.append((img, valid, obj_ids))

    def run(errors_of: Callable[[EstimateErrors], Mapping[int, float]], th: float) -> _Counts:
        c = _Counts()
        for img, valid, obj_ids in prepared:
            for i, g in enumerate(img.gts):
                if valid[i]:
                    c.tars += 1
                    c.obj_tars[g.obj_id] = c.obj_tars.get(g.obj_id, 0) + 1
            for obj_id in obj_ids:
                recs = by_im_obj.get((img.scene_id, img.im_id, obj_id))
                if not recs:
                    continue
                for gt_id in _match(recs, errors_of, th, valid):
                    c.tps += 1
                    c.matched.add((img.scene_id, img.im_id, gt_id))
                    o = img.gts[gt_id].obj_id
                    c.obj_tps[o] = c.obj_tps.get(o, 0) + 1
        return c

    widths = {(img.scene_id, img.im_id): img.width for img in images}
    counts: dict[str, list[_Counts]] = {}
    counts["mssd"] = [
        run(lambda r: {k: v / float(models[r.obj_id].diameter) for k, v in r.mssd.items()}, th)
        for th in MSSD_THRESHOLDS
    ]
    counts["mspd"] = [
        run(lambda r: {k: (640.0 / widths[(r.scene_id, r.im_id)]) * v for k, v in r.mspd.items()}, th)
        for th in MSPD_THRESHOLDS
    ]
    vsd_counts: list[list[_Counts]] = []
    if vsd_available:
        for ti in range(len(VSD_TAUS)):
            vsd_counts.append(
                [run(lambda r, ti=ti: {k: v[ti] for k, v in r.vsd.items()}, th) for th in VSD_THRESHOLDS]
            )
        counts["vsd"] = [c for row in vsd_counts for c in row]

    ar = {k: float(np.mean([c.recall() for c in v])) for k, v in counts.items()}
    used = [k for k in ERROR_TYPES if k in ar]
    total = float(np.mean([ar[k] for k in used]))

    obj_ids = sorted({g.obj_id for img in images for g in img.gts} & set(models))
    per_object: dict[int, dict[str, Any]] = {}
    for o in obj_ids:
        d: dict[str, Any] = {}
        for k in used:
            d[f"ar_{k}"] = float(np.mean([c.obj_recall(o) for c in counts[k]]))
        d["ar"] = float(np.mean([d[f"ar_{k}"] for k in used]))
        d["targets"] = counts["mssd"][0].obj_tars.get(o, 0)
        per_object[o] = d

    # Each valid ground truth's share of the AR: the fraction of thresholds it is matched at,
    # per error type, averaged over the types. AR is exactly their mean (recall = matched /
    # valid at each threshold), so their spread gives AR's standard error over targets.
    keys = [(img.scene_id, img.im_id, i, g.obj_id) for img, valid, _ in prepared
            for i, g in enumerate(img.gts) if valid[i]]
    share = np.zeros(len(keys))
    for k in used:
        for c in counts[k]:
            share += np.array([key[:3] in c.matched for key in keys], np.float64) / (len(counts[k]) * len(used))
    se = standard_error(share)

    out: dict[str, Any] = {
        "bop19_average_recall": total,
        "bop19_average_recall_vsd": ar.get("vsd"),
        "bop19_average_recall_mssd": ar["mssd"],
        "bop19_average_recall_mspd": ar["mspd"],
        "vsd_available": bool(vsd_available),
        "recalls": {
            "mssd": [c.recall() for c in counts["mssd"]],
            "mspd": [c.recall() for c in counts["mspd"]],
            "vsd": [[c.recall() for c in row] for row in vsd_counts] if vsd_available else None,
        },
        "per_object": per_object,
        "average_recall_standard_error": se,
        "per_target": [[sc, im, gt, o, float(a)] for (sc, im, gt, o), a in zip(keys, share)],
        "counts": {"targets": n_valid, "estimates_evaluated": len(errors), "images": len(images)},
    }
    if not vsd_available:
        out["note"] = "VSD skipped (no depth images or no renderer): bop19_average_recall = mean of MSSD and MSPD"
    return out


def average_time_per_image(estimates: Iterable[Any]) -> float:
    """Mean over images of the per-image time; -1 if any time is negative (the toolkit's rule).

    Raises ValueError when the estimates of one image carry times differing by more than 1 ms.
    """
    times: dict[tuple[int, int], float] = {}
    for e in estimates:
        key = (int(_attr(e, "scene_id")), int(_attr(e, "im_id")))
        t = float(_attr(e, "time"))
        if t < 0:
            return -1.0
        if key in times:
            if abs(times[key] - t) > 0.001:
                raise ValueError(f"the running time of scene {key[0]} image {key[1]} differs between its estimates")
        else:
            times[key] = t
    return float(np.mean(list(times.values()))) if times else -1.0


def evaluate_images(
    images: Sequence[EvalImage],
    estimates: Sequence[Any],
    models: Mapping[int, ObjectModel],
    *,
    renderer: RendererLike | None = None,
    visib_gt_min: float = VISIB_GT_MIN,
    vsd_delta: float = VSD_DELTA,
    progress: bool = False,
) -> dict[str, Any]:
    """BOP19 scores of in-memory images and estimates (see :func:`score_errors` for the keys).

    VSD is evaluated when ``renderer`` is given and every image has depth; otherwise it is
    skipped and flagged. The scores also hold ``breakdown``: the pose-error breakdown of the same
    targets (rotation, relative depth and projected-centre errors; ``sc6d_jax.metrics._breakdown``,
    :func:`summarize_breakdown`), which does not enter any ``bop19_*`` number.
    """
    vsd_ok = renderer is not None and len(images) > 0 and all(img.depth is not None for img in images)
    errs = compute_errors(
        images, estimates, models, renderer=renderer if vsd_ok else None, vsd_delta=vsd_delta,
        progress=progress, n_images=len(images),
    )
    out = score_errors(images, errs, models, visib_gt_min=visib_gt_min, vsd_available=vsd_ok)
    out["bop19_average_time_per_image"] = average_time_per_image(estimates) if estimates and all(
        hasattr(e, "time") or (isinstance(e, Mapping) and "time" in e) for e in estimates
    ) else -1.0
    from sc6d_jax.metrics._breakdown import breakdown_errors, summarize_breakdown  # imports this module

    out["breakdown"] = summarize_breakdown(breakdown_errors(images, estimates, models, visib_gt_min=visib_gt_min))
    return out


def make_object_model(obj_id: int, model_info: Any, pts: np.ndarray, max_sym_disc_step: float = MAX_SYM_DISC_STEP) -> ObjectModel:
    """ObjectModel from a models_info entry (dict or ``sc6d_jax.bop.ModelInfo``) and vertices."""
    info = model_info.as_dict() if hasattr(model_info, "as_dict") else dict(model_info)
    diameter = float(info["diameter"])
    if not diameter > 0:
        raise ValueError(f"object {obj_id}: diameter must be positive, got {diameter}")
    pts = np.asarray(pts, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
        raise ValueError(f"object {obj_id}: points must have shape (N, 3), got {pts.shape}")
    return ObjectModel(int(obj_id), diameter, pts, symmetry_transformations(info, max_sym_disc_step))


def standard_error(values: Iterable[float]) -> float | None:
    """The standard error of the mean of ``values`` (sample standard deviation over the square
    root of their number); None below two values."""
    v = np.asarray(list(values), np.float64)
    return float(np.std(v, ddof=1) / math.sqrt(len(v))) if len(v) > 1 else None


def paired_difference(a: Mapping[str, Any], b: Mapping[str, Any], obj_ids: Iterable[int] | None = None
                      ) -> tuple[float, float | None, int]:
    """AR of ``b`` minus AR of ``a`` over the targets both scored (``score_errors``' ``per_target``;
    only objects in ``obj_ids`` when given), with the standard error of that mean difference
    (None below two targets) and the number of targets. Per target the two shares move together
    (an easy target is easy for both), so the difference is much surer than either AR alone."""
    keep = None if obj_ids is None else {int(o) for o in obj_ids}

    def shares(s: Mapping[str, Any]) -> dict[tuple[int, int, int], float]:
        return {(int(r[0]), int(r[1]), int(r[2])): float(r[4]) for r in s.get("per_target") or []
                if keep is None or int(r[3]) in keep}

    sa, sb = shares(a), shares(b)
    common = sorted(sa.keys() & sb.keys())
    if not common:
        raise ValueError("the two scores share no targets (scores without per_target, or other test sets)")
    d = np.array([sb[k] - sa[k] for k in common])
    return float(d.mean()), standard_error(d), len(d)
