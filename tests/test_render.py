"""MuJoCo renderer and `sc6d render`: exact camera, exact depth, masks, BOP dataset round trip."""

from __future__ import annotations

import hashlib
import warnings

import numpy as np
import pytest
import trimesh

from sc6d_jax import bop
from sc6d_jax.objects import write_models
from sc6d_jax.render import Renderer, load_mesh, render_depth
from sc6d_jax.render._dataset import DatasetSpec, render_dataset

K_ODD = np.array([[530.0, 0.0, 300.7], [0.0, 495.0, 261.3], [0.0, 0.0, 1.0]])  # fx != fy, off-centre


def _coloured(mesh, rgb=(200, 100, 50)):
    mesh.visual.face_colors = np.array([*rgb, 255], np.uint8)
    return mesh


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    out = tmp_path_factory.mktemp("r") / "models"
    write_models(out)
    return out


def test_sphere_centre_projects_to_K_t():
    sphere = _coloured(trimesh.creation.icosphere(subdivisions=4, radius=6.0))
    rng = np.random.default_rng(0)
    with Renderer({1: sphere}, 640, 480) as r:
        for _ in range(5):
            t = np.array([rng.uniform(-150, 150), rng.uniform(-120, 120), rng.uniform(500, 900)])
            out = r.render([(1, np.eye(3), t)], K_ODD)
            ys, xs = np.nonzero(out.mask_visib[0])
            uv = K_ODD @ t
            # the centroid of a sphere's silhouette sits at K t up to a small perspective term
            assert abs(xs.mean() - uv[0] / uv[2]) < 0.5 and abs(ys.mean() - uv[1] / uv[2]) < 0.5


def test_depth_of_a_plane_is_exact():
    plane = _coloured(trimesh.creation.box(extents=(400.0, 400.0, 1.0)))
    R = trimesh.transformations.rotation_matrix(np.radians(35), [1, 0.3, 0])[:3, :3]
    t = np.array([10.0, -5.0, 700.0])
    d = render_depth(plane, K_ODD, R, t, 640, 480)
    n = R @ np.array([0.0, 0.0, 1.0])
    p0 = t + R @ np.array([0.0, 0.0, -0.5])  # the face seen from the camera
    if n @ (-t) > 0:
        p0 = t + R @ np.array([0.0, 0.0, 0.5])
    v, u = np.mgrid[0:480, 0:640]
    rays = np.stack([(u - K_ODD[0, 2]) / K_ODD[0, 0], (v - K_ODD[1, 2]) / K_ODD[1, 1], np.ones_like(u, float)], -1)
    z = (n @ p0) / (rays @ n)  # ray (x, y, 1) * z hits the plane
    inner = (d > 0)
    inner[:2] = inner[-2:] = False
    inner[:, :2] = inner[:, -2:] = False
    from scipy.ndimage import binary_erosion

    inner = binary_erosion(inner, iterations=2)
    assert inner.sum() > 10000
    assert np.abs(d[inner] - z[inner]).max() < 0.05  # mm; no multisample bias


def test_occlusion_masks_and_instances(models):
    meshes = {1: load_mesh(bop.model_path(models, 1)), 5: load_mesh(bop.model_path(models, 5))}
    with Renderer(meshes, 320, 240) as r:
        K = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])
        objs = [(1, np.eye(3), np.array([0.0, 0, 800])), (5, np.eye(3), np.array([75.0, 0, 500]))]
        out = r.render(objs, K, full_masks=True)
        assert out.mask_full[0].sum() > out.mask_visib[0].sum() > 0  # object 1 is partly hidden
        assert np.array_equal(out.mask_full[1], out.mask_visib[1])  # object 5 is in front
        assert not np.any(out.mask_visib[0] & out.mask_visib[1])
        assert np.all(out.depth[out.mask_visib[1]] < 600)


def test_load_mesh_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.ply"):
        load_mesh(tmp_path / "nope.ply")
    bad = tmp_path / "bad.ply"
    bad.write_text("this is not a ply file")
    with pytest.raises(ValueError, match="bad.ply"):
        load_mesh(bad)
    tiny = tmp_path / "metres.stl"
    trimesh.creation.box(extents=(0.1, 0.05, 0.05)).export(tiny)  # 10 cm box written in metres
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        load_mesh(tiny)
    assert any("diameter" in str(x.message) for x in w)
    m = load_mesh(tiny, units="m")
    assert m.extents.max() == pytest.approx(100.0)


def test_dataset_round_trip_and_boxes(tmp_path, models):
    spec = DatasetSpec(scenes=1, images_per_scene=3, objects_per_image=4, width=320, height=240, seed=3)
    root = render_dataset(models, tmp_path / "ds", spec, progress=False)
    ds = bop.BopDataset(root)
    assert ds.scene_ids() == [1] and ds.has_depth()
    gts, infos, cams = ds.scene_gt(1), ds.scene_gt_info(1), ds.scene_camera(1)
    verts = {i: bop.load_model_points(root / "models", i) for i in ds.obj_ids}
    for im in range(3):
        K = cams[im].K
        for g, (gt, info) in enumerate(zip(gts[im], infos[im])):
            np.testing.assert_allclose(gt.R @ gt.R.T, np.eye(3), atol=1e-9)
            uv = (verts[gt.obj_id] @ gt.R.T + gt.t) @ K.T
            uv = uv[:, :2] / uv[:, 2:]
            box = np.array([uv[:, 0].min(), uv[:, 1].min(), uv[:, 0].max(), uv[:, 1].max()])
            x, y, w, h = info.bbox_obj
            assert np.abs(np.array([x, y, x + w, y + h]) - box).max() <= 1.0
            full = ds.mask_path(1, im, g)
            assert full.is_file() and ds.mask_visib_path(1, im, g).is_file()
            vis = ds.load_mask_visib(1, im, g)
            assert vis.sum() == info.px_count_visib
        depth = ds.load_depth(1, im)
        assert depth.max() > 100 and depth.dtype == np.float32
    assert len(ds.targets()) > 0
    # same seed -> same bytes
    again = render_dataset(models, tmp_path / "ds2", spec, progress=False)

    def digest(p):
        return {f.relative_to(p).as_posix(): hashlib.sha256(f.read_bytes()).hexdigest() for f in sorted(p.rglob("*")) if f.is_file()}

    assert digest(root) == digest(again)


def test_dataset_errors_leave_nothing(tmp_path, models):
    with pytest.raises(ValueError, match="not in"):
        render_dataset(models, tmp_path / "x", DatasetSpec(scenes=1, images_per_scene=1, obj_ids=(99,)), progress=False)
    with pytest.raises(FileNotFoundError, match="models folder"):
        render_dataset(tmp_path / "none", tmp_path / "x", DatasetSpec(scenes=1, images_per_scene=1), progress=False)
    assert not any(tmp_path.iterdir())
    root = render_dataset(models, tmp_path / "ok", DatasetSpec(scenes=1, images_per_scene=1, width=64, height=48), progress=False)
    (root / "test" / "000001" / "scene_camera.json").unlink()
    with pytest.raises(FileNotFoundError, match="scene_camera.json"):
        bop.BopDataset(root).scene_camera(1)
