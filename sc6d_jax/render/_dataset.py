"""Rendering a BOP-format dataset (test split) with MuJoCo: several objects per image, clutter,
occlusion, random lights and textured backgrounds; same seed, same bytes.

Layout written (BOP toolkit conventions)::

    OUT/camera.json  OUT/test_targets_bop19.json  OUT/models/ (copy, with models_info.json)
    OUT/test/<scene:06d>/{rgb,depth,mask,mask_visib}/  scene_camera.json scene_gt.json scene_gt_info.json
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from sc6d_jax._io import atomic_directory, atomic_write_json, png_bytes
from sc6d_jax.bop import Camera, GtInfo, GtPose, Target, load_models_info, model_path
from sc6d_jax.bop import write_scene_camera, write_scene_gt, write_scene_gt_info, write_targets

DEPTH_SCALE = 0.1  # depth png units -> mm
MIN_TARGET_VISIB = 0.1  # BOP19: targets are instances with at least 10 % visible


@dataclass(frozen=True)
class DatasetSpec:
    scenes: int = 2
    images_per_scene: int = 10
    objects_per_image: int = 5
    distractors: int = 3
    width: int = 640
    height: int = 480
    seed: int = 0
    obj_ids: tuple[int, ...] | None = None

    def __post_init__(self) -> None:
        for name in ("scenes", "images_per_scene", "objects_per_image"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.distractors < 0 or self.distractors > 8:
            raise ValueError(f"distractors must be in 0..8, got {self.distractors}")
        if not (32 <= self.width <= 4096 and 32 <= self.height <= 4096):
            raise ValueError(f"image size must be in 32..4096, got {self.width}x{self.height}")


def _background(rng: np.random.Generator, w: int, h: int) -> np.ndarray:
    from sc6d_jax.backgrounds import random_background

    side = max(w, h)
    big = random_background(rng, min(side, 512))
    return cv2.resize(big, (side, side), interpolation=cv2.INTER_LINEAR)[:h, :w].copy()


def _scene_camera(rng: np.random.Generator, w: int, h: int) -> np.ndarray:
    f = rng.uniform(0.85, 1.05) * w
    return np.array([[f * rng.uniform(0.98, 1.02), 0, (w - 1) / 2 + rng.uniform(-0.03, 0.03) * w],
                     [0, f, (h - 1) / 2 + rng.uniform(-0.03, 0.03) * h], [0, 0, 1.0]])


def _place_objects(rng, ids, diam, K, w, h, n):
    """Random poses whose centres project inside the image, depth ~ 3-7 median diameters."""
    chosen = [int(i) for i in rng.choice(ids, size=min(n, len(ids)), replace=False)]
    base = float(np.median([diam[i] for i in ids]))
    out = []
    for obj_id in chosen:
        z = base * rng.uniform(3.0, 7.0)
        u, v = rng.uniform(0.12, 0.88) * w, rng.uniform(0.12, 0.88) * h
        t = z * np.linalg.solve(K, [u, v, 1.0])
        out.append((obj_id, Rotation.random(random_state=rng).as_matrix(), t))
    return out


def render_dataset(models_dir: str | Path, out_dir: str | Path, spec: DatasetSpec = DatasetSpec(),
                   overwrite: bool = False, progress: bool = True) -> Path:
    """Render a BOP test split into ``out_dir`` (written to a temporary folder, then renamed)."""
    from tqdm import tqdm

    from sc6d_jax.render import Light, Primitive, Renderer, load_mesh

    models_dir = Path(models_dir)
    if not models_dir.is_dir():
        raise FileNotFoundError(f"{models_dir}: models folder not found")
    infos = load_models_info(models_dir)
    ids = sorted(infos) if spec.obj_ids is None else list(spec.obj_ids)
    missing = [i for i in ids if i not in infos]
    if missing:
        raise ValueError(f"objects {missing} are not in {models_dir}/models_info.json")
    meshes = {i: load_mesh(model_path(models_dir, i)) for i in ids}
    verts = {i: np.asarray(m.vertices) for i, m in meshes.items()}
    diam = {i: infos[i].diameter for i in ids}
    W, H = spec.width, spec.height
    out_dir = Path(out_dir)
    with atomic_directory(out_dir, overwrite=overwrite) as tmp:
        shutil.copytree(models_dir, tmp / "models")
        (tmp / "models_eval").symlink_to("models")
        targets: list[Target] = []
        first_K = None
        total = spec.scenes * spec.images_per_scene
        bar = tqdm(total=total, desc="render", unit="img", disable=not progress, leave=False)
        with Renderer(meshes, W, H, n_primitives=spec.distractors, n_lights=3) as r:
            for s in range(1, spec.scenes + 1):
                rng = np.random.default_rng([spec.seed, s])
                K = _scene_camera(rng, W, H)
                first_K = K if first_K is None else first_K
                sdir = tmp / "test" / f"{s:06d}"
                for sub in ("rgb", "depth", "mask", "mask_visib"):
                    (sdir / sub).mkdir(parents=True)
                cams, gts, gt_infos = {}, {}, {}
                for im in range(spec.images_per_scene):
                    objs = _place_objects(rng, ids, diam, K, W, H, spec.objects_per_image)
                    prims = []
                    for _ in range(spec.distractors):
                        z = float(np.median(list(diam.values()))) * rng.uniform(2.5, 7.0)
                        c = z * np.linalg.solve(K, [rng.uniform(0, W), rng.uniform(0, H), 1.0])
                        size = rng.uniform(0.1, 0.35, 3) * float(np.median(list(diam.values())))
                        prims.append(Primitive(str(rng.choice(["box", "sphere", "cylinder", "ellipsoid", "capsule"])),
                                               size, rng.uniform(0, 1, 3), Rotation.random(random_state=rng).as_matrix(), c))
                    lights = [Light(direction=rng.normal(size=3) + [0, 0, 1.5], diffuse=rng.uniform(0.2, 0.6),
                                    specular=rng.uniform(0, 0.3)) for _ in range(rng.integers(1, 4))]
                    r.set_lights(lights, headlight=(rng.uniform(0.15, 0.35), rng.uniform(0.1, 0.4)))
                    out = r.render(objs, K, primitives=prims, background=_background(rng, W, H), full_masks=True)
                    (sdir / "rgb" / f"{im:06d}.png").write_bytes(png_bytes(out.rgb))
                    depth = np.round(out.depth / DEPTH_SCALE)
                    (sdir / "depth" / f"{im:06d}.png").write_bytes(png_bytes(np.clip(depth, 0, 65535).astype(np.uint16)))
                    cams[im] = Camera(K, DEPTH_SCALE)
                    gts[im] = [GtPose(o, R, t) for o, R, t in objs]
                    infos_im = []
                    counts: dict[int, int] = {}
                    for g, (o, R, t) in enumerate(objs):
                        full, vis = out.mask_full[g], out.mask_visib[g]
                        (sdir / "mask" / f"{im:06d}_{g:06d}.png").write_bytes(png_bytes(full.astype(np.uint8) * 255))
                        (sdir / "mask_visib" / f"{im:06d}_{g:06d}.png").write_bytes(png_bytes(vis.astype(np.uint8) * 255))
                        infos_im.append(_gt_info(verts[o], K, R, t, full, vis))
                        if infos_im[-1].visib_fract >= MIN_TARGET_VISIB:
                            counts[o] = counts.get(o, 0) + 1
                    gt_infos[im] = infos_im
                    targets += [Target(s, im, o, n) for o, n in sorted(counts.items())]
                    bar.update()
                write_scene_camera(sdir / "scene_camera.json", cams)
                write_scene_gt(sdir / "scene_gt.json", gts)
                write_scene_gt_info(sdir / "scene_gt_info.json", gt_infos)
        bar.close()
        write_targets(tmp / "test_targets_bop19.json", targets)
        atomic_write_json(tmp / "camera.json", {
            "cx": float(first_K[0, 2]), "cy": float(first_K[1, 2]), "depth_scale": DEPTH_SCALE,
            "fx": float(first_K[0, 0]), "fy": float(first_K[1, 1]), "height": H, "width": W,
        })
        atomic_write_json(tmp / "dataset_info.json", {
            "generator": "sc6d render", "spec": {k: (list(v) if isinstance(v, tuple) else v) for k, v in spec.__dict__.items()},
        })
    return out_dir


def _gt_info(verts, K, R, t, full, vis) -> GtInfo:
    """bbox_obj from the projected model vertices, bbox_visib from the visible mask (BOP toolkit's
    calc_2d_bbox convention: w = max - min)."""
    uv = (verts @ R.T + t) @ K.T
    uv = uv[:, :2] / uv[:, 2:3]
    x0, y0 = int(np.floor(uv[:, 0].min())), int(np.floor(uv[:, 1].min()))
    x1, y1 = int(np.ceil(uv[:, 0].max())), int(np.ceil(uv[:, 1].max()))
    ys, xs = np.nonzero(vis)
    bbox_visib = (int(xs.min()), int(ys.min()), int(xs.max() - xs.min()), int(ys.max() - ys.min())) if len(xs) else (-1, -1, -1, -1)
    n_all, n_vis = int(full.sum()), int(vis.sum())
    return GtInfo((x0, y0, x1 - x0, y1 - y0), bbox_visib, n_all, n_vis, n_all, n_vis / n_all if n_all else 0.0)
