"""``sc6d render``: render a BOP-format test dataset of the given models with MuJoCo."""

from __future__ import annotations

import argparse
import time
from pathlib import Path


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(prog="sc6d render", description=__doc__)
    p.add_argument("--models", type=Path, required=True, help="BOP models folder (PLY in mm + models_info.json)")
    p.add_argument("--out", type=Path, required=True, help="dataset folder to write (must not exist unless --overwrite)")
    p.add_argument("--scenes", type=int, default=2)
    p.add_argument("--images-per-scene", type=int, default=10)
    p.add_argument("--objects-per-image", type=int, default=5)
    p.add_argument("--distractors", type=int, default=3, help="primitive distractor shapes per image")
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--obj-ids", type=str, default=None, help="comma-separated object ids (default: all)")
    p.add_argument("--overwrite", action="store_true")
    p.add_argument("--no-progress", action="store_true")
    a = p.parse_args(argv)
    from sc6d_jax.render._dataset import DatasetSpec, render_dataset

    ids = None
    if a.obj_ids:
        try:
            ids = tuple(int(x) for x in a.obj_ids.split(","))
        except ValueError as exc:
            raise ValueError(f"--obj-ids must be comma-separated integers, got {a.obj_ids!r}") from exc
    spec = DatasetSpec(a.scenes, a.images_per_scene, a.objects_per_image, a.distractors, a.width, a.height, a.seed, ids)
    t0 = time.perf_counter()
    render_dataset(a.models, a.out, spec, overwrite=a.overwrite, progress=not a.no_progress)
    n = spec.scenes * spec.images_per_scene
    print(f"wrote {a.out}: {spec.scenes} scenes x {spec.images_per_scene} images ({time.perf_counter() - t0:.1f} s)")
    return 0
