"""BOP19 evaluation of a BOP dataset folder (``sc6d_jax.bop.BopDataset``) and a list of estimates."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from sc6d_jax.metrics._bop19 import (
    MAX_SYM_DISC_STEP,
    VISIB_GT_MIN,
    VSD_DELTA,
    EvalImage,
    GroundTruth,
    ObjectModel,
    evaluate_images,
    make_object_model,
)


def _image_size(ds: Any, scene_id: int, im_id: int, cache: dict) -> tuple[int, int]:
    """(width, height): from the dataset's camera.json when it has them, else the image file."""
    if "camera" not in cache:
        p = Path(ds.root) / "camera.json"
        cam = None
        if p.is_file():
            try:
                d = json.loads(p.read_text())
                cam = (int(d["width"]), int(d["height"]))
            except (KeyError, TypeError, ValueError, json.JSONDecodeError):
                cam = None
        cache["camera"] = cam
    if cache["camera"] is not None:
        return cache["camera"]
    if scene_id not in cache:
        cache[scene_id] = ds.image_size(scene_id, im_id)
    return cache[scene_id]


def load_eval_images(ds: Any, *, with_depth: bool) -> list[EvalImage]:
    """EvalImages of every image named in the dataset's BOP19 targets (depth loaded lazily)."""
    by_im: dict[tuple[int, int], dict[int, int]] = {}
    for t in ds.targets():
        by_im.setdefault((t.scene_id, t.im_id), {})[t.obj_id] = t.inst_count
    images = []
    size_cache: dict = {}
    for (scene_id, im_id), targets in by_im.items():
        gts = ds.scene_gt(scene_id).get(im_id)
        infos = ds.scene_gt_info(scene_id).get(im_id)
        cam = ds.scene_camera(scene_id).get(im_id)
        if gts is None or infos is None or cam is None:
            raise ValueError(f"target image {scene_id}/{im_id} is missing from scene_gt, scene_gt_info or scene_camera")
        if len(gts) != len(infos):
            raise ValueError(f"image {scene_id}/{im_id}: {len(gts)} ground truths but {len(infos)} gt_info entries")
        w, h = _image_size(ds, scene_id, im_id, size_cache)
        depth = None
        if with_depth:
            depth = (lambda s=scene_id, i=im_id: ds.load_depth(s, i))
        images.append(
            EvalImage(
                scene_id=scene_id, im_id=im_id, K=np.asarray(cam.K, dtype=np.float64), width=w, height=h,
                gts=[GroundTruth(g.obj_id, g.R, g.t, float(inf.visib_fract)) for g, inf in zip(gts, infos)],
                targets=targets, depth=depth,
            )
        )
    return images


def load_object_models(ds: Any, obj_ids: Iterable[int], max_sym_disc_step: float = MAX_SYM_DISC_STEP) -> dict[int, ObjectModel]:
    """ObjectModels from ``models_eval/`` (or ``models/``) and ``models_info.json`` (as the toolkit)."""
    from sc6d_jax.bop import load_model_points, load_models_info

    models_dir = ds.models_eval_dir()
    info_path = Path(models_dir) / "models_info.json"
    infos = load_models_info(info_path) if info_path.is_file() else ds.models_info
    out = {}
    for o in sorted(set(int(x) for x in obj_ids)):
        if o not in infos:
            raise ValueError(f"object {o} is not in {info_path if info_path.is_file() else 'models_info.json'}")
        out[o] = make_object_model(o, infos[o], load_model_points(models_dir, o), max_sym_disc_step)
    return out


def evaluate_bop19(
    dataset: Any,
    estimates: Sequence[Any],
    *,
    split: str = "test",
    renderer: Any = "auto",
    visib_gt_min: float = VISIB_GT_MIN,
    vsd_delta: float = VSD_DELTA,
    max_sym_disc_step: float = MAX_SYM_DISC_STEP,
    progress: bool = False,
) -> dict[str, Any]:
    """BOP19 scores of ``estimates`` (e.g. from ``sc6d_jax.bop.read_results_csv``) on a dataset.

    Args:
        dataset: a ``sc6d_jax.bop.BopDataset`` or the path of a BOP dataset folder.
        renderer: ``"auto"`` (the project's MuJoCo renderer with the ``models_eval`` meshes when
            the dataset has depth images), None (skip VSD), or a depth renderer for :func:`vsd`.

    Returns:
        dict with ``bop19_average_recall``, ``bop19_average_recall_vsd`` (None when skipped),
        ``bop19_average_recall_mssd``, ``bop19_average_recall_mspd``,
        ``bop19_average_time_per_image``, ``vsd_available``, ``vsd_skipped_reason`` (when
        skipped), ``recalls``, ``per_object``, ``counts`` and ``breakdown`` (median rotation,
        relative depth and projected-centre errors and the fractions under thresholds, overall
        and per object: :func:`sc6d_jax.metrics.summarize_breakdown`).
    """
    from sc6d_jax.bop import BopDataset

    ds = dataset if isinstance(dataset, BopDataset) else BopDataset(dataset, split=split)
    has_depth = ds.has_depth()
    reason = None
    own_renderer = None
    if not has_depth:
        reason = "the dataset has no depth images"
    elif renderer is None:
        reason = "no renderer given"
    images = load_eval_images(ds, with_depth=has_depth)
    if not images:
        raise ValueError(f"{ds}: no BOP19 targets to evaluate")
    obj_ids = sorted({g.obj_id for img in images for g in img.gts} | {o for img in images for o in img.targets})
    models = load_object_models(ds, obj_ids, max_sym_disc_step)
    ren = None
    if reason is None:
        if isinstance(renderer, str):
            if renderer != "auto":
                raise ValueError(f"renderer must be 'auto', None or a depth renderer, got {renderer!r}")
            sizes = {(img.width, img.height) for img in images}
            if len(sizes) != 1:
                raise ValueError(f"images of several sizes {sorted(sizes)}: pass a renderer explicitly")
            from sc6d_jax.metrics._vsd_renderer import VsdRenderer

            (w, h), = sizes
            own_renderer = ren = VsdRenderer.from_models_dir(ds.models_eval_dir(), obj_ids, w, h)
        else:
            ren = renderer
    if ren is None:
        for img in images:
            img.depth = None
    try:
        out = evaluate_images(
            images, estimates, models, renderer=ren, visib_gt_min=visib_gt_min, vsd_delta=vsd_delta, progress=progress
        )
    finally:
        if own_renderer is not None:
            own_renderer.close()
    if reason is not None:
        out["vsd_skipped_reason"] = reason
    return out
