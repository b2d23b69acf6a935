"""Where the gap between renders and real photographs lies: one model scored on versions of a real
BOP test set that swap the object's pixels and its surroundings between real and rendered.

    python experiments/lmo_gap.py --run runs/lmo-ab/real --dataset ../shared/data/lmo \\
        --out runs/lmo-gap [--obj-ids 8] [--tta] [--seed 0] [--library-size N] [--masks]

Every annotated object of each test image is rendered at its ground-truth pose (the renderer's
default light) with the others, which gives each one's visible mask (occlusion by annotated
objects only: an unannotated occluder counts as the object) and its rendered pixels. The
versions, each a BOP test folder under ``OUT`` with the original annotations:

- ``real``: the photographs as they are;
- ``real_objects``: the photographed pixels inside the annotated objects' visible masks, a
  procedural background (the training stream's kind) everywhere else;
- ``rendered_objects``: the rendered objects pasted over the photographs at their visible masks;
- ``rendered``: the rendered objects over a procedural background (the training distribution,
  without its occluders and colour augmentation);
- ``real_objects_recoloured``: ``real_objects`` with each object's photographed pixels shifted
  and scaled per channel to the mean and spread of its rendered pixels (the same procedural
  background);
- ``rendered_recoloured``: ``rendered`` with each object's rendered pixels given the mean and
  spread per channel of its photographed pixels.

If ``real_objects`` scores like ``rendered``, the surroundings are the gap; if
``rendered_objects`` does, the objects' appearance is. The two recoloured versions split the
appearance: how much of it is the objects' colour statistics (their brightness, colour cast and
contrast), which the recolouring exchanges, and how much is the rest (shading, texture,
sharpness), which it keeps. A diagnosis of a trained model only: it
trains nothing and chooses no setting. Prints AR and the pose-error breakdown per version
(restricted to ``--obj-ids`` when given) and writes ``OUT/gap.csv``; rerunning skips finished work.

``--masks`` also asks whether the pose decoder's gate (the predicted visible mask its features
are multiplied by) is what fails (``mask_rows``, ``OUT/masks.csv``): per version, the predicted
mask's IoU with the ground truth, and the rotation error with the network's own gate, with the
ground-truth mask as the gate, and with its own gate cleared off the object. If the ground-truth
gate rescues a version's rotations, the mask is the cause; if not, the features on the object.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "experiments"))

from learning_curve import BREAKDOWN_COLUMNS, _write_csv, dataset_rows, run_scores  # noqa: E402

VERSIONS = ("real", "real_objects", "rendered_objects", "rendered", "real_objects_recoloured", "rendered_recoloured")
COLUMNS = ("version", "obj_id", "targets", "ar", "ar_mssd", "ar_mspd", *BREAKDOWN_COLUMNS)
SHARED_FILES = ("camera.json", "test_targets_bop19.json", "models", "models_eval")
SCENE_FILES = ("scene_camera.json", "scene_gt.json", "scene_gt_info.json")


def _link(src: Path, dst: Path) -> None:
    if not dst.exists() and src.exists():
        dst.symlink_to(src.resolve(), target_is_directory=src.is_dir())


def match_colours(x: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Pixels ``x`` (N, 3) shifted and scaled per channel to the mean and spread of ``ref`` (M, 3)."""
    x, ref = x.astype(np.float64), ref.astype(np.float64)
    y = (x - x.mean(0)) / np.maximum(x.std(0), 1e-6) * ref.std(0) + ref.mean(0)
    return np.clip(np.round(y), 0, 255).astype(np.uint8)


def build_versions(dataset: Path, out: Path, seed: int) -> dict[str, Path]:
    """The versions of ``dataset`` (``real`` is the dataset itself); images are written once."""
    import cv2

    from sc6d_jax.bop import BopDataset, model_path
    from sc6d_jax.render import Renderer, load_mesh
    from sc6d_jax.render._dataset import _background

    ds = BopDataset(dataset)
    paths = {"real": dataset}
    todo = [v for v in VERSIONS[1:] if not (out / v / "DONE").is_file()]
    for v in VERSIONS[1:]:
        paths[v] = out / v
    if not todo:
        return paths
    scenes = ds.scene_ids()
    gts = {s: ds.scene_gt(s) for s in scenes}
    ids = sorted({g.obj_id for s in scenes for im in gts[s].values() for g in im})
    per_image = max(len(im) for s in scenes for im in gts[s].values())
    cams = {s: ds.scene_camera(s) for s in scenes}
    h, w = ds.load_rgb(scenes[0], next(iter(gts[scenes[0]]))).shape[:2]
    for v in todo:
        (out / v).mkdir(parents=True, exist_ok=True)
        for name in SHARED_FILES:
            _link(dataset / name, out / v / name)
    rng = np.random.default_rng(seed)
    renderer = Renderer({i: load_mesh(model_path(dataset / "models", i)) for i in ids}, w, h,
                        max_instances=per_image, n_lights=1)
    try:
        from tqdm import tqdm

        items = [(s, im) for s in scenes for im in sorted(gts[s])]
        for s, im in tqdm(items, desc="lmo_gap: render", unit="image", file=sys.stderr):
            real = ds.load_rgb(s, im)
            objs = [(g.obj_id, g.R, g.t) for g in gts[s][im]]
            r = renderer.render(objs, cams[s][im].K, depth=False)
            m = r.mask_visib.any(axis=0)[..., None]
            bg = _background(rng, w, h)
            real_rec, rend_rec = real.copy(), r.rgb.copy()
            for mk in r.mask_visib:  # each object's visible pixels, photographed and rendered
                if mk.any():
                    real_rec[mk], rend_rec[mk] = match_colours(real[mk], r.rgb[mk]), match_colours(r.rgb[mk], real[mk])
            imgs = {"real_objects": np.where(m, real, bg), "rendered_objects": np.where(m, r.rgb, real),
                    "rendered": np.where(m, r.rgb, bg), "real_objects_recoloured": np.where(m, real_rec, bg),
                    "rendered_recoloured": np.where(m, rend_rec, bg)}
            for v in todo:
                d = out / v / "test" / f"{s:06d}"
                (d / "rgb").mkdir(parents=True, exist_ok=True)
                for name in SCENE_FILES:
                    _link(ds.scene_dir(s) / name, d / name)
                cv2.imwrite(str(d / "rgb" / f"{im:06d}.png"), np.ascontiguousarray(imgs[v][..., ::-1]))
    finally:
        renderer.close()
    for v in todo:
        (out / v / "DONE").write_text("ok\n")
    return paths


MASK_COLUMNS = ("version", "obj_id", "targets", "mask_iou_median", "mask_iou_under_half", "mask_area_ratio_median",
                "mask_recall_median", "rot_own_gate_deg", "rot_gt_gate_deg", "rot_own_gate_on_gt_deg")


def mask_rows(run: str, dataset: Path, paths: dict[str, Path], obj_ids: list[int] | None,
              library_size: int | None) -> list[dict]:
    """The pose decoder's gate on each version: per target (ground-truth visible box, cut as
    ``sc6d predict`` cuts it), the network's predicted visible mask at S/4 against the rendered
    ground-truth visible mask cut the same way (IoU at 0.5; its area over the truth's, above 1
    when the gate lets the surroundings in; the share of the truth it covers), and the median symmetry-aware
    rotation error (the best library match, made egocentric with the ground-truth translation)
    with three gates: the network's own, the ground-truth mask instead, and its own with the
    pixels off the ground-truth mask zeroed. Rows per version and object, and pooled (``all``).
    Needs a model with ``mask_gate``."""
    import jax
    import jax.numpy as jnp

    from sc6d_jax.bop import BopDataset, bbox_extent, model_path
    from sc6d_jax.geometry import allocentric_to_egocentric, crop_transform, pe_map, warp_crop
    from sc6d_jax.inference import Estimator
    from sc6d_jax.inference._matching import match_library
    from sc6d_jax.metrics._breakdown import rotation_error_deg, symmetry_rotations
    from sc6d_jax.model import apply
    from sc6d_jax.render import Renderer, load_mesh

    kw = {} if library_size is None else {"library_size": library_size}
    est = Estimator.load(run, progress=False, **kw)
    if not est.mcfg.mask_gate:
        raise ValueError(f"--masks needs a model with a mask gate (model.mask_gate); {run} has none")
    S, mcfg = est.mcfg.crop_size, est.mcfg
    ds = BopDataset(dataset)
    wanted = set(est.obj_ids) if obj_ids is None else set(obj_ids) & set(est.obj_ids)
    targets = [t for t in ds.targets() if t.obj_id in wanted]
    if not targets:
        return []
    images = sorted({(t.scene_id, t.im_id) for t in targets})
    gts = {k: ds.scene_gt(k[0])[k[1]] for k in images}
    ids = sorted({g.obj_id for k in images for g in gts[k]})
    h, w = ds.load_rgb(*images[0]).shape[:2]
    syms = {i: symmetry_rotations(ds.models_info[i]) for i in wanted if i in ds.models_info}
    blocks, n_valid = est.packed_library()
    lib_R = np.asarray(est.library.R)

    def gates(p, rgb, pe, oi, gt_mask):
        """The mask logit and the best library index with the own gate, the GT mask, own x GT."""
        out = apply(p, mcfg, rgb, pe, oi)
        on = jnp.ones((rgb.shape[0],), bool)
        embs = [out["rot_emb"]] + [apply(p, mcfg, rgb, pe, oi, teacher_gate=(g, on))["rot_emb"]
                                   for g in (gt_mask, jax.nn.sigmoid(out["mask_logit"]) * gt_mask)]
        ix = [match_library(p["rot_head"], mcfg.rot_head, e, blocks, n_valid, 1, est.tau, False, oi).index[:, 0]
              for e in embs]
        return out["mask_logit"], ix

    fwd = jax.jit(gates)
    versions = {v: BopDataset(paths[v]) for v in VERSIONS}
    per: dict[str, list[tuple[int, float, float, float, float]]] = {v: [] for v in VERSIONS}
    renderer = Renderer({i: load_mesh(model_path(dataset / "models", i)) for i in ids}, w, h,
                        max_instances=max(len(g) for g in gts.values()), n_lights=1)
    try:
        from tqdm import tqdm

        for key in tqdm(images, desc="lmo_gap: masks", unit="image", file=sys.stderr):
            K = ds.scene_camera(key[0])[key[1]].K
            info = ds.scene_gt_info(key[0])[key[1]]
            r = renderer.render([(g.obj_id, g.R, g.t) for g in gts[key]], K, depth=False)
            imgs = {v: versions[v].load_rgb(*key) for v in VERSIONS}
            for i, g in enumerate(gts[key]):
                if g.obj_id not in wanted or info[i].bbox_visib[2] <= 0 or info[i].bbox_visib[3] <= 0:
                    continue
                box = np.asarray([bbox_extent(info[i].bbox_visib)], np.float32)
                oi = jnp.asarray(est.obj_index([g.obj_id]))
                gt = None
                for v in VERSIONS:
                    crops, center, side = est.make_crops(imgs[v], box, 1)
                    T = np.asarray(crop_transform(center, side, S))
                    if gt is None:  # the ground-truth visible mask at S/4, cut like the crop
                        m = warp_crop(r.mask_visib[i].astype(np.float32), T, S, interpolation="linear")
                        gt = m.reshape(1, S // 4, 4, S // 4, 4).mean(axis=(2, 4)) > 0.5
                    pe = pe_map(jnp.asarray(K[None], jnp.float32), jnp.asarray(T, jnp.float32), S)
                    pe = pe if mcfg.use_pe else None
                    logit, ixs = fwd(est.params, jnp.asarray(crops), pe, oi, jnp.asarray(gt, jnp.float32))
                    errs = []
                    for ix in ixs:  # own gate, GT mask, own x GT
                        R = np.asarray(allocentric_to_egocentric(jnp.asarray(lib_R[int(ix[0])]),
                                                                 jnp.asarray(g.t, jnp.float32)))
                        errs.append(rotation_error_deg(R, g.R, syms.get(g.obj_id)))
                    pred = np.asarray(logit) > 0.0
                    iou = float((pred & gt).sum() / max((pred | gt).sum(), 1))
                    area = float(pred.sum() / max(gt.sum(), 1))
                    recall = float((pred & gt).sum() / max(gt.sum(), 1))
                    per[v].append((g.obj_id, iou, area, recall, *errs))
    finally:
        renderer.close()
    rows = []
    for v in VERSIONS:
        a = per[v]
        for oid in [*sorted({x[0] for x in a}), "all"]:
            sel = np.array([x[1:] for x in a if oid == "all" or x[0] == oid], np.float64)
            rows.append({"version": v, "obj_id": oid, "targets": len(sel),
                         "mask_iou_median": float(np.median(sel[:, 0])),
                         "mask_iou_under_half": float(np.mean(sel[:, 0] < 0.5)),
                         "mask_area_ratio_median": float(np.median(sel[:, 1])),
                         "mask_recall_median": float(np.median(sel[:, 2])),
                         "rot_own_gate_deg": float(np.median(sel[:, 3])),
                         "rot_gt_gate_deg": float(np.median(sel[:, 4])),
                         "rot_own_gate_on_gt_deg": float(np.median(sel[:, 5]))})
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--run", required=True, help="a training run directory or a shipped model name")
    p.add_argument("--dataset", required=True, type=Path, help="a real BOP test set (e.g. ../shared/data/lmo)")
    p.add_argument("--out", required=True, type=Path, help="folder for the versions and scores (created)")
    p.add_argument("--obj-ids", default=None, help="report these objects only (comma-separated)")
    p.add_argument("--tta", action="store_true", help="score with fused test-time augmentation")
    p.add_argument("--seed", type=int, default=0, help="seed of the procedural backgrounds")
    p.add_argument("--library-size", type=int, default=None, help="rotation library size (sc6d predict's default)")
    p.add_argument("--masks", action="store_true",
                   help="also measure the pose decoder's gate per version: predicted vs ground-truth visible "
                        "mask and the rotation with each gate (OUT/masks.csv)")
    a = p.parse_args(argv)
    os.environ.setdefault("MUJOCO_GL", "egl")
    if not (a.dataset / "test").is_dir():
        print(f"lmo_gap: error: no BOP test split in {a.dataset}", file=sys.stderr)
        return 2
    try:
        obj_ids = None if a.obj_ids is None else [int(x) for x in a.obj_ids.split(",")]
    except ValueError:
        print(f"lmo_gap: error: --obj-ids must be comma-separated integers, got {a.obj_ids!r}", file=sys.stderr)
        return 2
    a.out.mkdir(parents=True, exist_ok=True)
    paths = build_versions(a.dataset, a.out, a.seed)
    rows = []
    for v in VERSIONS:
        predict_args = (*(["--tta"] if a.tta else []),
                        *([] if a.library_size is None else ["--library-size", str(a.library_size)]))
        sc = run_scores(a.run, paths[v], a.out, v + ("_tta" if a.tta else ""), predict_args)
        rows += dataset_rows(v, sc, obj_ids, key="version")
    print(f"{'version':>23} {'obj':>4} {'n':>4} {'AR':>6} {'MSSD':>6} {'MSPD':>6} {'rot':>7} {'depth':>7} {'centre':>7}")
    for r in rows:
        rot, dep, cen = r.get("rot_median_deg"), r.get("depth_rel_median"), r.get("centre_median_px")
        print(f"{r['version']:>23} {r['obj_id']:>4} {r['targets']:>4} {r['ar']:6.3f} {r['ar_mssd']:6.3f} "
              f"{r['ar_mspd']:6.3f} " + (f"{rot:7.1f} {100 * dep:6.1f}% {cen:7.1f}" if rot is not None else ""))
    _write_csv(a.out / "gap.csv", rows, COLUMNS)
    print(f"lmo_gap: wrote {a.out / 'gap.csv'}")
    if a.masks:
        try:
            mrows = mask_rows(a.run, a.dataset, paths, obj_ids, a.library_size)
        except ValueError as e:
            print(f"lmo_gap: error: {e}", file=sys.stderr)
            return 2
        print(f"{'version':>23} {'obj':>4} {'n':>4} {'IoU':>6} {'<0.5':>6} {'area':>6} {'recall':>6} "
              f"{'rot own':>8} {'GT gate':>8} {'own*GT':>8}")
        for r in mrows:
            print(f"{r['version']:>23} {r['obj_id']:>4} {r['targets']:>4} {r['mask_iou_median']:6.3f} "
                  f"{r['mask_iou_under_half']:6.2f} {r['mask_area_ratio_median']:6.2f} {r['mask_recall_median']:6.2f} "
                  f"{r['rot_own_gate_deg']:8.1f} {r['rot_gt_gate_deg']:8.1f} {r['rot_own_gate_on_gt_deg']:8.1f}")
        _write_csv(a.out / "masks.csv", mrows, MASK_COLUMNS)
        print(f"lmo_gap: wrote {a.out / 'masks.csv'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
