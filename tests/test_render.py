"""MuJoCo renderer and `sc6d render`: exact camera, exact depth, masks, BOP dataset round trip."""

from __future__ import annotations

import hashlib
import warnings

import numpy as np
import pytest
import trimesh

from sc6d_jax import bop
from sc6d_jax.render import Light, Primitive, Renderer, load_mesh, prepare_mesh, render_depth
from sc6d_jax.render._dataset import DatasetSpec, render_dataset

K_ODD = np.array([[530.0, 0.0, 300.7], [0.0, 495.0, 261.3], [0.0, 0.0, 1.0]])  # fx != fy, off-centre


def _coloured(mesh, rgb=(200, 100, 50)):
    mesh.visual.face_colors = np.array([*rgb, 255], np.uint8)
    return mesh



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
    assert np.abs(d[inner] - z[inner]).max() < 0.01  # mm; no multisample bias


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


# ---- small-image checks with one shared renderer (fx != fy, off-centre principal point)

W, H = 160, 120
K_SMALL = np.array([[151.3, 0.0, 71.2], [0.0, 172.9, 53.6], [0.0, 0.0, 1.0]])  # fx != fy, off-centre


def _rot(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return trimesh.transformations.rotation_matrix(angle, axis)[:3, :3]


def _project_box(vertices, K, R, t):
    x = (R @ vertices.T).T + t
    uv = (K @ x.T).T
    uv = uv[:, :2] / uv[:, 2:]
    return uv.min(0), uv.max(0)


@pytest.fixture(scope="module")
def scene_renderer():
    sphere = prepare_mesh(trimesh.creation.icosphere(subdivisions=3, radius=6.0))
    # off-centre mesh: its own origin must be kept (MuJoCo re-centres meshes internally)
    box = trimesh.creation.box(extents=[80.0, 50.0, 30.0])
    box.apply_translation([25.0, -10.0, 5.0])
    rng = np.random.default_rng(1)
    fc = np.concatenate([rng.integers(0, 256, (len(box.faces), 3)), np.full((len(box.faces), 1), 255)], 1)
    box.visual.face_colors = fc.astype(np.uint8)
    plate = prepare_mesh(trimesh.creation.box(extents=[400.0, 400.0, 2.0]))
    r = Renderer({1: sphere, 2: prepare_mesh(box), 3: plate}, W, H, n_primitives=2, max_instances=2)
    yield r, {1: sphere, 2: box, 3: plate}
    r.close()


def test_bbox_matches_projected_vertices_and_origin_is_kept(scene_renderer):
    r, meshes = scene_renderer
    R = _rot([0.3, 1.0, 0.2], 0.9)
    t = np.array([-15.0, 10.0, 450.0])
    out = r.render([(2, R, t)], K_SMALL)
    ys, xs = np.nonzero(out.mask_visib[0])
    lo, hi = _project_box(np.asarray(meshes[2].vertices), K_SMALL, R, t)
    # pixel centres inside the silhouette: extent within one pixel of the projected box
    assert np.all(np.abs(np.array([xs.min(), ys.min()]) - lo) <= 1.0)
    assert np.all(np.abs(np.array([xs.max(), ys.max()]) - hi) <= 1.0)


def test_face_colours_are_exact_under_pure_ambient_light(scene_renderer):
    r, meshes = scene_renderer
    r.set_lights([], headlight=(1.0, 0.0))
    try:
        out = r.render([(2, np.eye(3), np.array([-25.0, 10.0, 400.0]))], K_SMALL)
    finally:
        r.set_lights(None, headlight=(0.3, 0.4))
    colours = np.unique(out.rgb[out.mask_visib[0]].reshape(-1, 3), axis=0)
    fc = np.asarray(meshes[2].visual.face_colors)[:, :3]
    front = np.nonzero(meshes[2].face_normals[:, 2] < -0.9)[0]  # faces towards the camera
    assert {tuple(c) for c in colours} == {tuple(fc[k]) for k in front}


def test_occlusion_visible_and_full_masks(scene_renderer):
    r, _ = scene_renderer
    objs = [(2, np.eye(3), np.array([-25.0, 10.0, 500.0])), (1, np.eye(3), np.array([0.0, 0.0, 300.0])),
            (1, np.eye(3), np.array([30.0, 0.0, 300.0]))]
    prim = Primitive("sphere", (8.0, 8.0, 8.0), (1.0, 0.0, 0.0), np.eye(3), np.array([-30.0, 0.0, 350.0]))
    out = r.render(objs, K_SMALL, primitives=[prim], full_masks=True)
    assert out.mask_visib.shape == (3, H, W) and out.mask_full.shape == (3, H, W)
    assert np.all(out.mask_full >= out.mask_visib)
    # the small sphere in front hides part of the box; nothing hides the spheres
    assert out.mask_visib[0].sum() < out.mask_full[0].sum()
    assert np.array_equal(out.mask_visib[1], out.mask_full[1])
    assert np.any(out.instance == 3)  # the distractor is drawn, with its own instance id
    assert np.array_equal(out.instance >= 0, out.depth > 0)
    # the occluder is nearer where it covers the box
    covered = out.mask_full[0] & out.mask_visib[1]
    assert covered.any() and np.all(out.depth[covered] < 480)


def test_background_composited_and_lights(scene_renderer):
    r, _ = scene_renderer
    bg = np.random.default_rng(0).integers(0, 256, (H, W, 3), dtype=np.uint8)
    r.set_lights([Light((0, 0, 1), 0.9), Light((1, 0, 0), 0.2)])
    out = r.render([(2, np.eye(3), np.array([0.0, 0.0, 400.0]))], K_SMALL, background=bg)
    r.set_lights(None)
    empty = out.instance < 0
    assert np.array_equal(out.rgb[empty], bg[empty])


def test_render_depth_matches_renderer(scene_renderer):
    r, meshes = scene_renderer
    R = _rot([1, 2, 3], 1.0)
    t = np.array([5.0, 3.0, 420.0])
    d1 = render_depth(meshes[2], K_SMALL, R, t, W, H)
    d2 = r.render([(2, R, t)], K_SMALL).depth
    assert d1.dtype == np.float32 and d1.shape == (H, W)
    assert np.allclose(d1, d2, atol=1e-3)


def test_bad_input(scene_renderer, tmp_path):
    r, _ = scene_renderer
    with pytest.raises(ValueError, match="unknown obj_id"):
        r.render([(99, np.eye(3), np.array([0, 0, 300.0]))], K_SMALL)
    with pytest.raises(ValueError, match="rotation"):
        r.render([(1, 2 * np.eye(3), np.array([0, 0, 300.0]))], K_SMALL)
    # BOP files store R with few digits (LM-O: |R R^T - I| up to 0.01): rendered as the nearest rotation
    R_loose = np.round(_rot([1, 2, 3], 1.0), 2)
    assert np.abs(R_loose @ R_loose.T - np.eye(3)).max() > 1e-3
    out = r.render([(1, R_loose, np.array([0, 0, 300.0]))], K_SMALL)
    assert out.mask_visib[0].sum() > 0
    with pytest.raises(ValueError, match="focal"):
        r.render([], np.diag([0.0, 1.0, 1.0]))
    with pytest.raises(ValueError, match="max_instances"):
        r.render([(1, np.eye(3), np.zeros(3) + 300)] * 3, K_SMALL)
    with pytest.raises(FileNotFoundError, match="nope.ply"):
        load_mesh(tmp_path / "nope.ply")
    bad = tmp_path / "bad.ply"
    bad.write_text("ply\nthis is not a mesh\n")
    with pytest.raises(ValueError, match="bad.ply"):
        load_mesh(bad)
    empty = tmp_path / "empty.obj"
    empty.write_text("# nothing\n")
    with pytest.raises(ValueError, match="empty.obj"):
        load_mesh(empty)
    with pytest.raises(ValueError, match="units"):
        load_mesh(bad, units="inch")


def test_load_mesh_ply_vertex_colours_and_units(tmp_path):
    mesh = trimesh.creation.box(extents=[0.1, 0.06, 0.04])  # metres
    vc = np.zeros((len(mesh.vertices), 4), np.uint8)
    vc[:, 0] = 200
    vc[:, 3] = 255
    mesh.visual.vertex_colors = vc
    path = tmp_path / "m.ply"
    mesh.export(path)
    with pytest.warns(UserWarning, match="metres"):
        as_mm = load_mesh(path)  # metres passed as mm
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ok = load_mesh(path, units="m")
    assert np.allclose(ok.vertices, as_mm.vertices * 1000.0)
    assert np.all(np.asarray(ok.visual.face_colors)[:, :3] == [200, 0, 0])
    stl = tmp_path / "m.stl"
    trimesh.creation.box(extents=[10, 20, 30]).export(stl)
    assert np.allclose(load_mesh(stl).extents, [10, 20, 30])


def test_single_object_mask_from_depth_equals_segmentation(scene_renderer):
    """One object in the scene: the mask comes from the depth buffer, identical to the seg pass."""
    r, _ = scene_renderer
    bg = np.full((H, W, 3), 7, np.uint8)
    for k, (oid, R) in enumerate([(2, _rot([1, 1, 0], 0.7)), (1, np.eye(3)), (3, _rot([0, 1, 0], 1.2))]):
        t = np.array([5.0 * k, -3.0, 450.0])
        fast = r.render([(oid, R, t)], K_SMALL, background=bg, depth=False, full_masks=True)
        r._force_segmentation = True
        try:
            slow = r.render([(oid, R, t)], K_SMALL, background=bg, depth=False, full_masks=True)
        finally:
            r._force_segmentation = False
        assert fast.mask_visib[0].any()
        assert np.array_equal(fast.instance, slow.instance)
        assert np.array_equal(fast.mask_full, slow.mask_full)
        assert np.array_equal(fast.rgb, slow.rgb)


def test_scene_holds_only_the_placed_geoms(scene_renderer):
    """Unplaced slots are left out of the MuJoCo scene (each one would cost a draw call), and a
    slot used in one call and not in the next disappears from the image."""
    r, _ = scene_renderer
    box = (2, np.eye(3), np.array([0.0, 0.0, 400.0]))
    sphere = (1, np.eye(3), np.array([10.0, 0.0, 300.0]))  # in front of the box
    both = r.render([box, sphere], K_SMALL)
    assert r._scene.ngeom == 2 and set(np.unique(both.instance)) == {-1, 0, 1}
    alone = r.render([box], K_SMALL)
    assert r._scene.ngeom == 1 and set(np.unique(alone.instance)) == {-1, 0}
    assert alone.mask_visib[0].sum() > both.mask_visib[0].sum()  # the sphere no longer hides it
