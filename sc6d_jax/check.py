"""``sc6d check``: render-and-check that the renderer and the geometry core agree.

Renders a few objects at random poses through an off-centre pinhole camera (f_x != f_y) with
MuJoCo, then checks, per pose:

- the silhouette's box equals the box of the model vertices projected with K (<= 1 px);
- a crop cut from the rendered image with the image->crop transform T equals the crop rendered
  directly through K_B = T K (mask IoU);
- the translation encoding (delta_xy, delta_z) decodes back to t;
- allocentric invariance: the object moved sideways at a fixed allocentric rotation gives the
  same crop (mask IoU between the two directly rendered crops).

Prints a table, writes a picture (image | cut crop | rendered crop | sideways crop) and exits
non-zero when a check fails.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import cv2
import numpy as np
import trimesh

CROP = 128
W, H = 640, 480
K = np.array([[600.0, 0.0, 331.3], [0.0, 585.0, 236.7], [0.0, 0.0, 1.0]])


def check_meshes() -> dict[int, trimesh.Trimesh]:
    """Three shapes in mm: a box, a cylinder and an asymmetric L-shaped composite."""
    box = trimesh.creation.box(extents=(80.0, 50.0, 30.0))
    cyl = trimesh.creation.cylinder(radius=25.0, height=90.0, sections=48)
    a = trimesh.creation.box(extents=(90.0, 20.0, 20.0))
    b = trimesh.creation.box(extents=(20.0, 60.0, 20.0))
    b.apply_translation((35.0, 40.0, 0.0))
    c = trimesh.creation.icosphere(radius=14.0, subdivisions=2)
    c.apply_translation((-35.0, 0.0, 20.0))
    comp = trimesh.util.concatenate([a, b, c])
    colours = {1: (200, 60, 40), 2: (40, 120, 210), 3: (90, 180, 70)}
    meshes = {1: box, 2: cyl, 3: comp}
    for k, m in meshes.items():
        m.visual.face_colors = np.array([*colours[k], 255], np.uint8)
    return meshes


def _box_of(mask: np.ndarray) -> np.ndarray | None:
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return None
    return np.array([xs.min(), ys.min(), xs.max(), ys.max()], np.float64)


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    u = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / u) if u else 1.0


def run_checks(n_poses: int = 6, seed: int = 0, out_png: Path | None = None) -> list[dict]:
    from sc6d_jax import geometry as G
    from sc6d_jax.data import project_box
    from sc6d_jax.render import Renderer

    meshes = check_meshes()
    rng = np.random.default_rng(seed)
    rows, tiles = [], []
    with Renderer(meshes, W, H) as big, Renderer(meshes, CROP, CROP) as small:
        for i in range(n_poses):
            obj_id = int(list(meshes)[i % len(meshes)])
            R = np.asarray(G.random_rotations(_key(seed, i), 1)[0], np.float64)
            z = rng.uniform(450.0, 900.0)
            t = np.array([rng.uniform(-0.25, 0.25) * z, rng.uniform(-0.2, 0.2) * z, z])
            out = big.render([(obj_id, R, t)], K, full_masks=True)
            mask = out.mask_full[0]
            # 1. silhouette box vs projected vertices
            xywh = project_box(np.asarray(meshes[obj_id].vertices), K, R, t)
            proj_box = np.array([xywh[0], xywh[1], xywh[0] + xywh[2], xywh[1] + xywh[3]])
            sil_box = _box_of(mask)
            box_err = float(np.abs(proj_box - sil_box).max()) if sil_box is not None else np.inf
            # 2. cut crop vs crop rendered through K_B
            center, side = G.crop_box(xywh)
            T = np.asarray(G.crop_transform(center, side, CROP), np.float64)
            K_B = np.asarray(G.crop_intrinsics(K, T), np.float64)
            cut_rgb = G.warp_crop(out.rgb, T, CROP, interpolation="linear")
            cut_mask = G.warp_crop(mask.astype(np.uint8), T, CROP, interpolation="nearest") > 0
            direct = small.render([(obj_id, R, t)], K_B, full_masks=True)
            iou_crop = _iou(cut_mask, direct.mask_full[0])
            # 3. translation encoding round trip
            dxy, dz = G.encode_translation(t, K, center, side, CROP)
            t_back = np.asarray(G.decode_translation(dxy, dz, K, center, side, CROP), np.float64)
            t_err = float(np.abs(t_back - t).max() / np.linalg.norm(t))
            # 4. allocentric invariance: move sideways, keep the allocentric rotation
            R_allo = np.asarray(G.egocentric_to_allocentric(R, t), np.float64)
            t2 = np.array([-t[0] * 0.8 + 0.1 * z, t[1] * -0.5, z])
            R2 = np.asarray(G.allocentric_to_egocentric(R_allo, t2), np.float64)
            # same crop scale as the first view, centred on the projected origin offset alike
            o1 = (K @ t)[:2] / t[2]
            o2 = (K @ t2)[:2] / t2[2]
            T2 = np.asarray(G.crop_transform(o2 + (np.asarray(center) - o1), side, CROP), np.float64)
            side_view = small.render([(obj_id, R2, t2)], G.crop_intrinsics(K, T2), full_masks=True)
            iou_allo = _iou(direct.mask_full[0], side_view.mask_full[0])
            rows.append(
                dict(pose=i, obj_id=obj_id, box_err_px=box_err, crop_iou=iou_crop, t_rel_err=t_err, allo_iou=iou_allo)
            )
            if out_png is not None and i < 4:
                vis = out.rgb.copy()
                x0, y0, x1, y1 = proj_box.astype(int)
                cv2.rectangle(vis, (x0, y0), (x1, y1), (255, 255, 0), 2)
                cv2.circle(vis, tuple(int(round(c)) for c in o1), 4, (255, 0, 255), -1)
                thumb = cv2.resize(vis, (CROP * W // H, CROP), interpolation=cv2.INTER_AREA)
                row = np.concatenate([thumb, cut_rgb, direct.rgb, side_view.rgb], axis=1)
                tiles.append(row)
    if out_png is not None and tiles:
        from sc6d_jax._io import atomic_write_png

        sheet = np.concatenate(tiles, axis=0)
        header = np.full((22, sheet.shape[1], 3), 255, np.uint8)
        x = 4
        for label, w in (("image (box, origin)", CROP * W // H), ("cut with T", CROP), ("rendered via K_B", CROP), ("moved, same allo R", CROP)):
            cv2.putText(header, label, (x, 15), cv2.FONT_HERSHEY_SIMPLEX, 0.38, (0, 0, 0), 1, cv2.LINE_AA)
            x += w
        sheet = np.concatenate([header, sheet], axis=0)
        atomic_write_png(out_png, sheet)
    return rows


def _key(seed: int, i: int):
    import jax

    return jax.random.fold_in(jax.random.PRNGKey(seed), i)


# A silhouette pixel is covered when its centre is inside the projected surface, so the box of
# covered pixels sits up to 1 px inside the vertex box, a little more at sharp corners.
THRESHOLDS = dict(box_err_px=1.5, crop_iou=0.95, t_rel_err=1e-5, allo_iou=0.90)


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(prog="sc6d check", description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, default=Path("sc6d-check.png"), help="picture to write (PNG)")
    p.add_argument("--poses", type=int, default=6, help="random poses to check")
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args(argv)
    if a.poses < 1:
        raise ValueError(f"--poses must be >= 1, got {a.poses}")
    if a.out.suffix.lower() != ".png":
        raise ValueError(f"--out must name a .png file, got {a.out}")
    t0 = time.perf_counter()
    rows = run_checks(a.poses, a.seed, a.out)
    failed = 0
    print(f"{'pose':>4} {'obj':>3} {'box err px':>10} {'crop IoU':>8} {'t rel err':>10} {'allo IoU':>8}  result")
    for r in rows:
        ok = (
            r["box_err_px"] <= THRESHOLDS["box_err_px"]
            and r["crop_iou"] >= THRESHOLDS["crop_iou"]
            and r["t_rel_err"] <= THRESHOLDS["t_rel_err"]
            and r["allo_iou"] >= THRESHOLDS["allo_iou"]
        )
        failed += not ok
        print(
            f"{r['pose']:>4} {r['obj_id']:>3} {r['box_err_px']:>10.3f} {r['crop_iou']:>8.4f} "
            f"{r['t_rel_err']:>10.2e} {r['allo_iou']:>8.4f}  {'ok' if ok else 'FAIL'}"
        )
    print(f"\n{len(rows) - failed}/{len(rows)} poses pass; picture: {a.out} ({time.perf_counter() - t0:.1f} s)")
    return 1 if failed else 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main(sys.argv[1:]))
