"""A picture of the crop stream's realism options, beside real crops when a BOP test set is given.

    python experiments/realism_gallery.py --models ../shared/data/lmo/models --out gallery.png \\
        [--dataset ../shared/data/lmo] [--n 10] [--size 64] [--seed 0]

Rows: the stream as the presets use it, then with each realism option alone (``materials``,
``sensor``, ``resample``, ``distractors=3``, ``object_gain=(0.5, 2)``, ``object_contrast=(0.5, 2)``,
``object_colour=(0.7, 1.4)``, ``scene_backgrounds=1``, ``shadows=1``, ``tabletop=1``), the table
with shadows, the table with its neighbours against the target (``tabletop_spacing=(0, 0.2)``), then
the first four together. Every row draws from the same seed, so column j
shows the same object at the same pose in every row; the options draw random numbers of their
own, so backgrounds, lights and the in-plane turns differ. With ``--dataset``, a last row of
real test crops cut at their ground-truth visible boxes the way the estimator cuts them (pad
1.5, linear warp) and a row of the same crops with the object rendered over them at its
ground-truth pose. For looking at only: nothing here chooses a setting from real images.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

ROWS: tuple[tuple[str, dict], ...] = (
    ("stream (presets)", {}),
    ("materials", {"materials": True}),
    ("sensor", {"sensor": True}),
    ("resample", {"resample": True}),
    ("distractors=3", {"distractors": 3}),
    ("object_gain=0.5,2", {"object_gain": (0.5, 2.0)}),
    ("object_contrast=0.5,2", {"object_contrast": (0.5, 2.0)}),
    ("object_colour=0.7,1.4", {"object_colour": (0.7, 1.4)}),
    ("scene_backgrounds=1", {"scene_backgrounds": 1.0}),
    ("shadows=1", {"shadows": 1.0}),
    ("tabletop=1", {"tabletop": 1.0}),
    ("tabletop=1, shadows=1", {"tabletop": 1.0, "shadows": 1.0}),
    ("tabletop_spacing=0,0.2", {"tabletop": 1.0, "tabletop_spacing": (0.0, 0.2)}),
    ("all four", {"materials": True, "sensor": True, "resample": True, "distractors": 3}),
)


def stream_rows(models: Path, n: int, size: int, seed: int) -> list[tuple[str, np.ndarray]]:
    from sc6d_jax.data import CropStream, StreamConfig

    out = []
    for name, opts in ROWS:
        cfg = StreamConfig(str(models), crop_size=size, batch_size=n, seed=seed, workers=0, augment=True,
                           distance=(2.5, 12.0), **opts)
        with CropStream(cfg) as s:
            out.append((name, s.batch(0)["rgb"]))
    return out


def real_rows(dataset: Path, n: int, size: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` real test crops at ground-truth visible boxes (seeded choice) and the same crops
    with the object rendered over them at its ground-truth pose (the renderer's default lights):
    where the two agree, the render of the object itself is faithful and the gap is elsewhere."""
    from sc6d_jax import geometry as G
    from sc6d_jax.bop import BopDataset, bbox_extent, model_path
    from sc6d_jax.render import Renderer, load_mesh

    ds = BopDataset(dataset)
    items = []  # (scene, image, ground truth, its info, camera K), each scene's files read once
    for sid in ds.scene_ids():
        info, cams = ds.scene_gt_info(sid), ds.scene_camera(sid)
        for im_id, gts in ds.scene_gt(sid).items():
            for gt, gi in zip(gts, info[im_id]):
                if gi.visib_fract > 0.3:
                    items.append((sid, im_id, gt, gi, cams[im_id].K))
    rng = np.random.default_rng(seed)
    pick = [items[i] for i in rng.choice(len(items), size=min(n, len(items)), replace=False)]
    ids = sorted({gt.obj_id for _, _, gt, _, _ in pick})
    renderer = Renderer({i: load_mesh(model_path(dataset / "models", i)) for i in ids}, size, size, n_lights=1)
    crops, overlays = [], []
    try:
        for sid, im_id, gt, gi, K in pick:
            img = ds.load_rgb(sid, im_id)
            c, s = G.crop_box(bbox_extent(gi.bbox_visib), 1.5)
            T = np.asarray(G.crop_transform(np.asarray(c), np.asarray(s), size))
            crop = G.warp_crop(img, T, size)
            out = renderer.render([(gt.obj_id, gt.R, gt.t)], T @ K, depth=False)
            over = crop.copy()
            m = out.mask_visib[0] > 0
            over[m] = out.rgb[m]
            crops.append(crop)
            overlays.append(over)
    finally:
        renderer.close()
    return np.stack(crops), np.stack(overlays)


def figure(rows: list[tuple[str, np.ndarray]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = max(len(r) for _, r in rows)
    fig, axes = plt.subplots(len(rows), n, figsize=(1.3 * n, 1.4 * len(rows)), squeeze=False)
    for i, (name, imgs) in enumerate(rows):
        for j in range(n):
            ax = axes[i, j]
            ax.set_xticks([])
            ax.set_yticks([])
            if j < len(imgs):
                ax.imshow(imgs[j])
            else:
                ax.axis("off")
        axes[i, 0].set_ylabel(name, fontsize=8)
    fig.tight_layout(pad=0.3)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--models", required=True, type=Path, help="BOP models folder")
    p.add_argument("--out", required=True, type=Path, help="output PNG")
    p.add_argument("--dataset", type=Path, default=None, help="a BOP test set: a row of real crops")
    p.add_argument("--n", type=int, default=10, help="crops per row")
    p.add_argument("--size", type=int, default=64, help="crop side in pixels")
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args(argv)
    os.environ.setdefault("MUJOCO_GL", "egl")
    if not a.models.is_dir():
        print(f"realism_gallery: error: models folder not found: {a.models}", file=sys.stderr)
        return 2
    if a.dataset is not None and not a.dataset.is_dir():
        print(f"realism_gallery: error: dataset folder not found: {a.dataset}", file=sys.stderr)
        return 2
    if a.n < 1 or a.size < 16 or a.size % 4:
        print("realism_gallery: error: --n must be >= 1 and --size a multiple of 4, >= 16", file=sys.stderr)
        return 2
    rows = stream_rows(a.models, a.n, a.size, a.seed)
    if a.dataset is not None:
        real, overlay = real_rows(a.dataset, a.n, a.size, a.seed)
        rows += [("real test crops", real), ("render at GT pose", overlay)]
    a.out.parent.mkdir(parents=True, exist_ok=True)
    figure(rows, a.out)
    print(f"realism_gallery: wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
