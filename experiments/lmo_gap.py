"""Where the gap between renders and real photographs lies: one model scored on versions of a real
BOP test set that swap the object's pixels and its surroundings between real and rendered.

    python experiments/lmo_gap.py --run runs/lmo-ab/real --dataset ../shared/data/lmo \\
        --out runs/lmo-gap [--obj-ids 8] [--tta] [--seed 0] [--library-size N]

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
"""

from __future__ import annotations

import argparse
import csv
import os
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "experiments"))

from learning_curve import BREAKDOWN_COLUMNS, dataset_rows, run_scores  # noqa: E402

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


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--run", required=True, help="a training run directory or a shipped model name")
    p.add_argument("--dataset", required=True, type=Path, help="a real BOP test set (e.g. ../shared/data/lmo)")
    p.add_argument("--out", required=True, type=Path, help="folder for the versions and scores (created)")
    p.add_argument("--obj-ids", default=None, help="report these objects only (comma-separated)")
    p.add_argument("--tta", action="store_true", help="score with fused test-time augmentation")
    p.add_argument("--seed", type=int, default=0, help="seed of the procedural backgrounds")
    p.add_argument("--library-size", type=int, default=None, help="rotation library size (sc6d predict's default)")
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
    tmp = a.out / "gap.tmp"
    with open(tmp, "w", newline="") as f:
        wr = csv.DictWriter(f, fieldnames=COLUMNS, extrasaction="ignore")
        wr.writeheader()
        wr.writerows(rows)
    tmp.replace(a.out / "gap.csv")
    print(f"lmo_gap: wrote {a.out / 'gap.csv'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
