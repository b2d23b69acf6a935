"""Regenerate the README's pictures (deterministic): ``python experiments/make_figures.py``.

Writes under experiments/figures/: objects.png (the built-in set), crops.png (training crops from
the stream), scene.png (a rendered BOP test image), check.png (render-and-check), and from a
``sc6d demo`` run with the shipped ``builtin`` model: poses.png (estimated poses drawn on a test
image) and rotdist.png (one target's top rotations on the sphere).
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import cv2
import numpy as np

OUT = Path(__file__).resolve().parent / "figures"


def _save(name: str, rgb: np.ndarray) -> None:
    OUT.mkdir(exist_ok=True)
    cv2.imwrite(str(OUT / name), rgb[..., ::-1], [cv2.IMWRITE_PNG_COMPRESSION, 9])
    print(f"wrote {OUT / name}")


def main() -> int:
    from scipy.spatial.transform import Rotation

    from sc6d_jax.check import run_checks
    from sc6d_jax.data import CropStream, StreamConfig
    from sc6d_jax.objects import builtin_objects, write_models
    from sc6d_jax.render import Renderer, load_mesh
    from sc6d_jax.render._dataset import DatasetSpec, render_dataset

    with tempfile.TemporaryDirectory() as tmp:
        models = write_models(Path(tmp) / "models")
        objs = builtin_objects()
        meshes = {o.obj_id: load_mesh(models / f"obj_{o.obj_id:06d}.ply") for o in objs}
        K = np.array([[420.0, 0, 79.5], [0, 420.0, 79.5], [0, 0, 1]])
        tiles = []
        with Renderer(meshes, 160, 160) as r:
            for o in objs:
                R = Rotation.from_euler("xyz", [35, -25, 20], degrees=True).as_matrix()
                img = r.render([(o.obj_id, R, np.array([0, 0, 700.0]))], K, background=np.full((160, 160, 3), 245, np.uint8)).rgb
                img = img.copy()
                label = f"{o.obj_id} {o.name}" + (" (sym)" if o.symmetric else "")
                cv2.putText(img, label, (4, 152), cv2.FONT_HERSHEY_SIMPLEX, 0.38, (20, 20, 20), 1, cv2.LINE_AA)
                tiles.append(img)
        rows = [np.concatenate(tiles[i:i + 7], 1) for i in range(0, 14, 7)]
        _save("objects.png", np.concatenate(rows, 0))
        with CropStream(StreamConfig(str(models), crop_size=64, batch_size=32, workers=0)) as s:
            b = s.batch(0)
        crops = np.concatenate([np.concatenate(list(b["rgb"][i * 16:(i + 1) * 16]), 1) for i in range(2)], 0)
        _save("crops.png", crops)
        ds = render_dataset(models, Path(tmp) / "ds", DatasetSpec(scenes=1, images_per_scene=1, seed=1), progress=False)
        scene = cv2.imread(str(ds / "test" / "000001" / "rgb" / "000000.png"))[..., ::-1]
        _save("scene.png", cv2.resize(scene, (480, 360), interpolation=cv2.INTER_AREA))
        run_checks(4, 0, OUT / "check.png")
        print(f"wrote {OUT / 'check.png'}")
        from sc6d_jax.demo import main as demo_main

        demo = Path(tmp) / "demo"
        demo_main(["--out", str(demo), "--scenes", "1", "--images-per-scene", "2"])
        for name, pattern in (("poses.png", "poses_*.png"), ("rotdist.png", "rotdist_*.png")):
            src = sorted((demo / "figures").glob(pattern))[0]
            (OUT / name).write_bytes(src.read_bytes())
            print(f"wrote {OUT / name} (from {src.name})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
