"""Pictures: rotation distributions on a sphere, pose overlays, AR bar charts.

- :func:`rotation_distribution_figure`: the paper's overview figure. Every rotation is a point
  on a Mollweide map of the sphere at the direction the object's z axis points to in the camera
  frame (``R[:, 2]``), coloured by the in-plane angle about that axis (the twist of a
  swing-twist decomposition), sized by probability; the ground truth and its symmetric
  equivalents are rings coloured the same way.
- :func:`draw_silhouette`, :func:`draw_overlay`: estimated poses drawn on an image (the model's
  silhouette contour rendered by MuJoCo at the pose, and the box; what ``sc6d predict --overlay``
  writes).
- :func:`overlay_figures`: side-by-side pictures (image | estimated silhouettes) of a results CSV.
- :func:`ar_bar_chart`: per-object AR of a ``sc6d eval`` scores dict;
  :func:`grouped_bar_chart`: bars with error bars (the sweeps' per-row chart).
- :func:`worst_targets_figure`: the lowest-scoring targets, estimate and ground truth side by
  side.
- :func:`write_eval_figures`: all of these for a dataset + results CSV (+ run, + scores); what
  ``sc6d eval --figures DIR`` writes.

Figures are ``matplotlib.figure.Figure`` objects made without pyplot (no global state, no
display needed); :func:`save_figure` writes one as a PNG atomically.
"""

from __future__ import annotations

import io
import json
import os
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

__all__ = [
    "ar_bar_chart",
    "draw_overlay",
    "draw_silhouette",
    "grouped_bar_chart",
    "in_plane_angle",
    "lowest_scoring_targets",
    "overlay_figures",
    "rotation_distribution_figure",
    "save_figure",
    "sphere_coords",
    "worst_targets_figure",
    "write_eval_figures",
]


# ----------------------------------------------------------------------------- sphere coordinates
def _as_rotations(R: Any, name: str) -> np.ndarray:
    a = np.asarray(R, dtype=np.float64)
    if a.ndim == 2:
        a = a[None]
    if a.ndim != 3 or a.shape[1:] != (3, 3):
        raise ValueError(f"{name} must be (3, 3) or (k, 3, 3), got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} holds non-finite values")
    err = np.abs(a @ np.swapaxes(a, 1, 2) - np.eye(3)).max(initial=0.0)
    if err > 1e-2:
        raise ValueError(f"{name} is not a rotation (max |R R^T - I| = {err:.3g})")
    return a


def in_plane_angle(R: np.ndarray) -> np.ndarray:
    """Twist angle (radians, in (-pi, pi]) of ``R`` (..., 3, 3) about its own z axis.

    ``R = S @ Rz(angle)`` where ``S`` is the shortest-arc rotation taking the z axis to
    ``R[:, 2]`` (swing-twist decomposition); the angle is undefined only when ``R[:, 2]``
    points exactly along -z, where the swing about the x axis is used.
    """
    R = np.asarray(R, dtype=np.float64)
    z = R[..., :, 2]
    axis = np.stack([-z[..., 1], z[..., 0], np.zeros_like(z[..., 0])], axis=-1)  # e_z x z
    s = np.linalg.norm(axis, axis=-1, keepdims=True)
    c = np.clip(z[..., 2], -1.0, 1.0)
    axis = np.where(s > 1e-9, axis / np.maximum(s, 1e-12), np.array([1.0, 0.0, 0.0]))
    ang = np.arccos(c)
    # Rodrigues: S = I + sin(a) [k]x + (1 - cos(a)) [k]x^2
    kx = np.zeros(axis.shape[:-1] + (3, 3))
    kx[..., 0, 1], kx[..., 0, 2] = -axis[..., 2], axis[..., 1]
    kx[..., 1, 0], kx[..., 1, 2] = axis[..., 2], -axis[..., 0]
    kx[..., 2, 0], kx[..., 2, 1] = -axis[..., 1], axis[..., 0]
    S = np.eye(3) + np.sin(ang)[..., None, None] * kx + (1.0 - np.cos(ang))[..., None, None] * (kx @ kx)
    T = np.swapaxes(S, -1, -2) @ R
    return np.arctan2(T[..., 1, 0], T[..., 0, 0])


def sphere_coords(R: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(longitude, latitude, in-plane angle) in radians of rotations ``R`` (..., 3, 3): the
    direction of the object's z axis in the camera frame and the twist about it."""
    R = np.asarray(R, dtype=np.float64)
    z = R[..., :, 2]
    lon = np.arctan2(z[..., 1], z[..., 0])
    lat = np.arcsin(np.clip(z[..., 2], -1.0, 1.0))
    return lon, lat, in_plane_angle(R)


# ----------------------------------------------------------------------------- figures
def rotation_distribution_figure(
    R_gt: Any,
    rotations: Any,
    probs: Any,
    symmetries: Any = None,
    title: str = "",
    max_rings: int = 72,
):
    """The paper's overview figure: rotations as points on a Mollweide map of the sphere.

    Args:
        R_gt: ground-truth rotation (3, 3), or None.
        rotations: (k, 3, 3) rotations (e.g. a prediction's ``R_topk``).
        probs: (k,) non-negative weights (probabilities); point area is proportional.
        symmetries: optional (n, 3, 3) symmetry rotations of the object (model frame); the
            ground truth's equivalents ``R_gt @ S_i`` are drawn as rings too (at most
            ``max_rings``, evenly subsampled).
        title: axes title.

    Returns:
        a ``matplotlib.figure.Figure`` (not registered with pyplot).
    """
    from matplotlib.figure import Figure

    rots = _as_rotations(rotations, "rotations")
    p = np.asarray(probs, dtype=np.float64).reshape(-1)
    if p.shape[0] != rots.shape[0]:
        raise ValueError(f"probs has {p.shape[0]} entries for {rots.shape[0]} rotations")
    if not np.all(np.isfinite(p)) or np.any(p < 0):
        raise ValueError("probs must be finite and non-negative")
    gt = None if R_gt is None else _as_rotations(R_gt, "R_gt")
    if gt is not None and gt.shape[0] != 1:
        raise ValueError(f"R_gt must be one (3, 3) rotation, got shape {np.shape(R_gt)}")
    rings = gt
    if gt is not None and symmetries is not None:
        sym = _as_rotations(symmetries, "symmetries")
        rings = gt[0] @ sym
        if len(rings) > max_rings:
            rings = rings[np.linspace(0, len(rings) - 1, max_rings).round().astype(int)]

    fig = Figure(figsize=(8.0, 4.6), dpi=100)
    ax = fig.add_subplot(111, projection="mollweide")
    lon, lat, roll = sphere_coords(rots)
    order = np.argsort(p)  # most probable drawn last (on top)
    total = float(p.sum()) if p.size and p.sum() > 0 else 1.0
    sizes = 3.0 + np.minimum(400.0, 3000.0 * p / total)  # flat over 500 -> ~9; a 50 % mode -> 400
    sc = ax.scatter(lon[order], lat[order], s=sizes[order], c=roll[order], cmap="hsv", vmin=-np.pi, vmax=np.pi,
                    edgecolors="none", alpha=0.85)
    if rings is not None:
        glon, glat, groll = sphere_coords(rings)
        from matplotlib import colormaps

        cols = colormaps["hsv"]((groll + np.pi) / (2 * np.pi))
        ax.scatter(glon, glat, s=420, facecolors="none", edgecolors="k", linewidths=3.0, zorder=3)
        ax.scatter(glon, glat, s=420, facecolors="none", edgecolors=cols, linewidths=1.6, zorder=4,
                   label="ground truth" + (" + symmetric equivalents" if len(rings) > 1 else ""))
        ax.legend(loc="upper left", bbox_to_anchor=(-0.02, 0.02), fontsize=8, framealpha=0.8)
    ax.grid(True, alpha=0.4)
    ax.set_xticklabels([])
    cb = fig.colorbar(sc, ax=ax, orientation="horizontal", fraction=0.05, pad=0.06)
    cb.set_label("in-plane angle about the object's z axis (rad)")
    ax.set_title(title or f"{len(rots)} rotations (area ~ probability)", fontsize=10)
    return fig


def grouped_bar_chart(
    labels: Sequence[str],
    series: Mapping[str, Sequence[float]],
    errors: Mapping[str, Sequence[float]] | None = None,
    ylabel: str = "",
    title: str = "",
    ylim: tuple[float, float] | None = (0.0, 1.0),
):
    """Bars grouped by label, one colour per series, optional error bars (e.g. std over seeds)."""
    from matplotlib.figure import Figure

    labels = [str(x) for x in labels]
    if not labels or not series:
        raise ValueError("grouped_bar_chart needs at least one label and one series")
    for name, v in series.items():
        if len(v) != len(labels):
            raise ValueError(f"series {name!r} has {len(v)} values for {len(labels)} labels")
    n = len(series)
    width = 0.8 / n
    x = np.arange(len(labels))
    fig = Figure(figsize=(max(5.0, 0.9 * len(labels) * max(1, n) * 0.5 + 2.5), 4.0), dpi=100)
    ax = fig.add_subplot(111)
    for i, (name, vals) in enumerate(series.items()):
        v = np.asarray([np.nan if a is None else a for a in vals], dtype=np.float64)
        err = None
        if errors is not None and name in errors:
            err = np.nan_to_num(np.asarray([np.nan if a is None else a for a in errors[name]], np.float64))
        ax.bar(x + (i - (n - 1) / 2) * width, np.nan_to_num(v), width, yerr=err, capsize=3, label=name)
    ax.set_xticks(x)
    ax.set_xticklabels(labels, rotation=20 if max(len(s) for s in labels) > 6 else 0, ha="right" if max(len(s) for s in labels) > 6 else "center", fontsize=8)
    if ylim is not None:
        ax.set_ylim(*ylim)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=10)
    ax.grid(True, axis="y", alpha=0.3)
    if n > 1:
        ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


def ar_bar_chart(scores: Mapping[str, Any], title: str = ""):
    """Per-object AR, AR_MSSD, AR_MSPD (and AR_VSD when computed) of a ``sc6d eval`` scores dict."""
    per = scores.get("per_object") if isinstance(scores, Mapping) else None
    if not per:
        raise ValueError("scores has no per_object entries (not a sc6d eval scores JSON?)")
    ids = sorted(per, key=lambda k: int(k))
    keys = [("AR", "ar"), ("AR_MSSD", "ar_mssd"), ("AR_MSPD", "ar_mspd")]
    if any(per[k].get("ar_vsd") is not None for k in ids):
        keys.append(("AR_VSD", "ar_vsd"))
    series = {name: [per[k].get(key) for k in ids] for name, key in keys}
    ar = scores.get("bop19_average_recall")
    t = title or ("per-object average recall" + (f" (overall AR {ar:.3f})" if isinstance(ar, (int, float)) else ""))
    return grouped_bar_chart([f"obj {k}" for k in ids], series, ylabel="recall", title=t)


def save_figure(fig, path: str | os.PathLike, dpi: int | None = None) -> Path:
    """Write ``fig`` as a PNG atomically (``sc6d_jax._io``); returns the path."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from sc6d_jax._io import atomic_write_bytes

    if fig.canvas is None or not hasattr(fig.canvas, "print_png"):
        FigureCanvasAgg(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    return atomic_write_bytes(path, buf.getvalue())


# ----------------------------------------------------------------------------- pose overlays
def draw_silhouette(image: np.ndarray, mesh, K: np.ndarray, R: np.ndarray, t: np.ndarray,
                    colour: tuple[int, int, int]) -> np.ndarray:
    """Draw, in place on the RGB ``image``, the contour of ``mesh``'s silhouette at pose (R, t mm)
    seen through K (rendered with MuJoCo, the project's renderer); returns ``image``."""
    import cv2

    from sc6d_jax.render import render_depth

    H, W = image.shape[:2]
    mask = (render_depth(mesh, K, np.asarray(R), np.asarray(t), W, H) > 0).astype(np.uint8)
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    cv2.drawContours(image, contours, -1, colour, max(1, round(max(H, W) / 320)), cv2.LINE_AA)
    return image


def draw_overlay(image: np.ndarray, K: np.ndarray, preds, models_dir: str | None) -> np.ndarray:
    """RGB image with each estimate drawn: the model's silhouette contour rendered at the
    estimated pose (MuJoCo, the project's renderer) and its box; the object axes when no model
    file is available."""
    import cv2

    from sc6d_jax.bop import model_path
    from sc6d_jax.render import load_mesh

    out = image.copy()
    colors = [(255, 64, 64), (64, 255, 64), (64, 128, 255), (255, 255, 0), (255, 0, 255), (0, 255, 255)]
    for n, p in enumerate(preds):
        col = colors[n % len(colors)]
        mesh = None
        if models_dir:
            try:
                mesh = load_mesh(model_path(models_dir, p.obj_id))
            except (FileNotFoundError, ValueError):
                mesh = None
        if mesh is not None and p.t[2] > 0:
            draw_silhouette(out, mesh, K, p.R, p.t, col)
        else:  # axes, 0.5 x box size at the estimated depth
            L = 0.5 * max(p.box[2], p.box[3]) * p.t[2] / K[0, 0]
            ends = np.vstack([np.zeros(3), L * np.eye(3)]) @ p.R.T + p.t
            uv = ends @ K.T
            uv = uv[:, :2] / uv[:, 2:3]
            for a, c in zip(range(1, 4), [(255, 0, 0), (0, 255, 0), (0, 0, 255)]):
                if np.all(np.isfinite(uv)):
                    cv2.line(out, tuple(int(v) for v in uv[0]), tuple(int(v) for v in uv[a]), c, 2)
        x, y, w, h = (int(round(v)) for v in p.box)
        cv2.rectangle(out, (x, y), (x + w, y + h), col, 1)
    return out


# ----------------------------------------------------------------------------- dataset pictures
def overlay_figures(
    dataset_dir: str | os.PathLike,
    results_csv: str | os.PathLike,
    out_dir: str | os.PathLike,
    n_images: int = 4,
    split: str = "test",
) -> list[Path]:
    """Side-by-side PNGs ``poses_SCENE_IM.png`` (image | estimated poses as silhouette contours,
    :func:`draw_overlay`) for the first ``n_images`` images of the results."""
    from sc6d_jax._io import atomic_write_png
    from sc6d_jax.bop import BopDataset, bbox_extent, read_results_csv
    from sc6d_jax.inference._estimator import PosePrediction

    if not isinstance(n_images, int) or n_images < 0:
        raise ValueError(f"n_images must be a non-negative int, got {n_images!r}")
    ds = BopDataset(dataset_dir, split=split)
    ests = read_results_csv(results_csv)
    out_dir = Path(out_dir)
    written = []
    keys = sorted({(e.scene_id, e.im_id) for e in ests})[:n_images]
    for scene_id, im_id in keys:
        img = ds.load_rgb(scene_id, im_id)
        K = ds.scene_camera(scene_id)[im_id].K
        infos = ds.scene_gt_info(scene_id).get(im_id, [])
        gts = ds.scene_gt(scene_id).get(im_id, [])
        preds = []
        for e in (e for e in ests if (e.scene_id, e.im_id) == (scene_id, im_id)):
            box = next((bbox_extent(i.bbox_visib) for g, i in zip(gts, infos) if g.obj_id == e.obj_id), np.zeros(4))
            preds.append(PosePrediction(obj_id=e.obj_id, box=box, R=e.R, t=e.t, score=e.score, prob=0.0,
                                        R_topk=e.R[None], prob_topk=np.zeros(1), score_topk=np.zeros(1)))
        pic = np.concatenate([img, draw_overlay(img, K, preds, str(ds.models_dir))], axis=1)
        p = atomic_write_png(out_dir / f"poses_{scene_id:06d}_{im_id:06d}.png", pic)
        written.append(p)
    return written


def _target_crop(img: np.ndarray, box: Sequence[float], size: int) -> np.ndarray:
    """A ``size`` x ``size`` square of ``img`` around a box (x, y, w, h), 1.3x its longer side
    (zero outside the image)."""
    import cv2

    x, y, w, h = (float(v) for v in box)
    half = max(int(round(0.65 * max(w, h))) + 4, 8)
    cx, cy = int(round(x + w / 2)), int(round(y + h / 2))
    pad = np.pad(img, ((half, half), (half, half), (0, 0)))
    cy, cx = int(np.clip(cy, 0, img.shape[0])) + half, int(np.clip(cx, 0, img.shape[1])) + half
    return cv2.resize(pad[cy - half:cy + half, cx - half:cx + half], (size, size), interpolation=cv2.INTER_AREA)


def lowest_scoring_targets(dataset: Any, estimates: Sequence[Any], scores: Mapping[str, Any],
                           n: int = 12) -> list[dict[str, Any]]:
    """The ``n`` targets with the lowest share of the AR (``scores["per_target"]``, from
    ``sc6d eval``), larger rotation error first among equal shares: the rows of
    :func:`sc6d_jax.metrics.breakdown_errors` (which pairs them with ``estimates``) with
    ``share`` added. ``dataset`` is a ``sc6d_jax.bop.BopDataset``."""
    from sc6d_jax.metrics._breakdown import breakdown_errors
    from sc6d_jax.metrics._evaluate import load_eval_images, load_object_models

    if not isinstance(n, int) or n < 1:
        raise ValueError(f"n must be a positive int, got {n!r}")
    shares = {(int(r[0]), int(r[1]), int(r[2])): float(r[4]) for r in scores.get("per_target") or []}
    if not shares:
        raise ValueError("scores have no per_target shares (a sc6d eval scores dict is needed)")
    images = load_eval_images(dataset, with_depth=False)
    obj_ids = sorted({g.obj_id for img in images for g in img.gts})
    rows = [dict(r, share=shares[r["scene_id"], r["im_id"], r["gt_id"]])
            for r in breakdown_errors(images, estimates, load_object_models(dataset, obj_ids))
            if (r["scene_id"], r["im_id"], r["gt_id"]) in shares]
    if not rows:
        raise ValueError("no scored target matches the dataset's ground truths (scores of another dataset?)")
    rows.sort(key=lambda r: (r["share"], -r["rot_deg"]))
    return rows[:n]


def worst_targets_figure(
    dataset_dir: str | os.PathLike,
    results_csv: str | os.PathLike,
    scores: Mapping[str, Any],
    n: int = 12,
    split: str = "test",
    columns: int = 3,
    tile: int = 128,
) -> np.ndarray:
    """The ``n`` targets that scored lowest (share of the AR, then larger rotation error), as an
    RGB image: per target the crop around its visible box with the estimate's silhouette (red)
    and with the ground truth's (green), under a caption ``obj O  AR a  R deg  d %`` (the share
    of the AR, :func:`sc6d_jax.metrics.pose_errors`' rotation and relative depth error, or
    ``missed``). ``scores`` is ``sc6d eval``'s dict (its ``per_target``); targets are paired
    with estimates as in :func:`sc6d_jax.metrics.breakdown_errors`."""
    import cv2

    from sc6d_jax.bop import BopDataset, model_path, read_results_csv
    from sc6d_jax.metrics import group_estimates
    from sc6d_jax.render import load_mesh

    if not isinstance(columns, int) or columns < 1:
        raise ValueError(f"columns must be a positive int, got {columns!r}")
    ds = BopDataset(dataset_dir, split=split)
    ests = read_results_csv(results_csv)
    rows = lowest_scoring_targets(ds, ests, scores, n)
    groups = group_estimates(ests)  # what breakdown_errors' est_id indexes
    meshes: dict[int, Any] = {}
    tiles = []
    for r in rows:
        sc, im, o = r["scene_id"], r["im_id"], r["obj_id"]
        img = ds.load_rgb(sc, im)
        K = ds.scene_camera(sc)[im].K
        g = ds.scene_gt(sc)[im][r["gt_id"]]
        box = ds.scene_gt_info(sc)[im][r["gt_id"]].bbox_visib
        if o not in meshes:
            meshes[o] = load_mesh(model_path(ds.models_dir, o))
        est = None if r["missed"] else groups[sc, im, o][r["est_id"]][1]
        poses = (None if est is None else (est.R, est.t), (g.R, g.t))
        panels = []
        for pose, col in zip(poses, ((255, 64, 64), (64, 255, 64))):
            pic = img.copy()
            if pose is not None and float(np.asarray(pose[1])[2]) > 0:
                draw_silhouette(pic, meshes[o], K, pose[0], pose[1], col)
            panels.append(_target_crop(pic, box, tile))
        cap = np.zeros((18, 2 * tile, 3), np.uint8)
        what = "missed" if r["missed"] else f"{r['rot_deg']:.0f} deg  {100 * r['depth_rel']:.1f} %"
        cv2.putText(cap, f"obj {o}  AR {r['share']:.2f}  {what}", (4, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.4,
                    (255, 255, 255), 1, cv2.LINE_AA)
        t_img = np.concatenate([cap, np.concatenate(panels, axis=1)], axis=0)
        tiles.append(np.pad(t_img, ((2, 2), (2, 2), (0, 0))))
    tiles += [np.zeros_like(tiles[0])] * (-len(tiles) % columns)
    return np.concatenate([np.concatenate(tiles[i:i + columns], axis=1) for i in range(0, len(tiles), columns)], axis=0)


def _symmetry_rotations(info: Any) -> np.ndarray:
    from sc6d_jax.metrics import symmetry_transformations

    syms = symmetry_transformations(info, max_sym_disc_step=0.05)
    return np.stack([np.asarray(s["R"], np.float64) for s in syms])


def write_eval_figures(
    dataset_dir: str | os.PathLike,
    results_csv: str | os.PathLike,
    out_dir: str | os.PathLike,
    run: str | os.PathLike | None = None,
    n_images: int = 4,
    split: str = "test",
    scores: str | os.PathLike | Mapping[str, Any] | None = None,
    n_targets: int = 3,
    top_k: int = 500,
    library_size: int = 20_000,
) -> list[Path]:
    """Figures of an evaluation, written atomically under ``out_dir``; returns their paths.

    - ``poses_SCENE_IM.png``: overlays of the estimated poses on the first ``n_images`` images;
    - with ``run``: ``rotdist_SCENE_IM_objOBJ.png`` for the first ``n_targets`` ground-truth
      instances of those images: the model's top-``top_k`` rotations of a
      ``library_size`` library (from the ground-truth visible box) with the ground truth and
      its symmetric equivalents;
    - with ``scores`` (a ``sc6d eval`` JSON path or dict): ``ar_per_object.png``, and
      ``worst_targets.png`` (:func:`worst_targets_figure`) when it has ``per_target``.
    """
    from sc6d_jax.bop import BopDataset, bbox_extent

    dataset_dir, results_csv, out_dir = Path(dataset_dir), Path(results_csv), Path(out_dir)
    if not dataset_dir.is_dir():
        raise FileNotFoundError(f"dataset folder {dataset_dir} does not exist")
    if not results_csv.is_file():
        raise FileNotFoundError(f"results CSV {results_csv} does not exist")
    if not isinstance(n_targets, int) or n_targets < 0:
        raise ValueError(f"n_targets must be a non-negative int, got {n_targets!r}")
    written = overlay_figures(dataset_dir, results_csv, out_dir, n_images=n_images, split=split)

    if scores is not None:
        if not isinstance(scores, Mapping):
            sp = Path(scores)
            if not sp.is_file():
                raise FileNotFoundError(f"scores JSON {sp} does not exist")
            scores = json.loads(sp.read_text(encoding="utf-8"))
        fig = ar_bar_chart(scores)
        written.append(save_figure(fig, out_dir / "ar_per_object.png"))
        if scores.get("per_target"):
            from sc6d_jax._io import atomic_write_png

            pic = worst_targets_figure(dataset_dir, results_csv, scores, split=split)
            written.append(atomic_write_png(out_dir / "worst_targets.png", pic))

    if run is not None and n_targets > 0:
        from sc6d_jax.bop import read_results_csv
        from sc6d_jax.inference import Estimator

        from sc6d_jax.pretrained import check_run

        check_run(run)
        ds = BopDataset(dataset_dir, split=split)
        est = Estimator.load(run, library_size=library_size, progress=False)
        k = min(int(top_k), est.library.size)
        infos_all = ds.models_info
        keys = sorted({(e.scene_id, e.im_id) for e in read_results_csv(results_csv)})[: max(n_images, 1)]
        done = 0
        for scene_id, im_id in keys:
            gts = ds.scene_gt(scene_id).get(im_id, [])
            gtis = ds.scene_gt_info(scene_id).get(im_id, [])
            image = ds.load_rgb(scene_id, im_id)
            K = ds.scene_camera(scene_id)[im_id].K
            for g, gi in zip(gts, gtis):
                if done >= n_targets:
                    break
                if g.obj_id not in est.obj_ids or gi.bbox_visib[2] <= 0 or gi.bbox_visib[3] <= 0:
                    continue
                pred = est.predict(image, K, bbox_extent(gi.bbox_visib)[None], [g.obj_id], top_k=k)[0]
                info = infos_all.get(g.obj_id)
                syms = _symmetry_rotations(info) if info is not None else None
                eq = g.R[None] if syms is None else g.R @ syms
                cos = (np.trace(np.swapaxes(eq, 1, 2) @ pred.R, axis1=1, axis2=2) - 1) / 2
                err = float(np.degrees(np.arccos(np.clip(cos.max(), -1, 1))))
                fig = rotation_distribution_figure(
                    g.R, pred.R_topk, pred.prob_topk, symmetries=syms,
                    title=f"scene {scene_id} image {im_id} object {g.obj_id}: top-{k} of {est.library.size} "
                          f"rotations\n(best one {err:.0f} deg from the nearest symmetric ground truth)",
                )
                written.append(save_figure(fig, out_dir / f"rotdist_{scene_id:06d}_{im_id:06d}_obj{g.obj_id:02d}.png"))
                done += 1
            if done >= n_targets:
                break
    return written
