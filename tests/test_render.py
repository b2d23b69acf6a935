"""Renderer checks against analytic geometry: projection, depth, masks, colours, bad input."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import trimesh

from sc6d_jax.render import Light, Primitive, Renderer, load_mesh, prepare_mesh, render_depth

W, H = 160, 120
K_ODD = np.array([[151.3, 0.0, 71.2], [0.0, 172.9, 53.6], [0.0, 0.0, 1.0]])


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


@pytest.mark.parametrize("t", [(12.0, -7.0, 300.0), (-40.0, 25.0, 420.0), (0.0, 0.0, 250.0), (55.0, 30.0, 500.0)])
def test_sphere_mask_centre_is_K_t(scene_renderer, t):
    r, _ = scene_renderer
    t = np.asarray(t)
    out = r.render([(1, np.eye(3), t)], K_ODD)
    ys, xs = np.nonzero(out.mask_visib[0])
    assert len(xs) > 10
    expected = (K_ODD @ t / t[2])[:2]
    assert abs(xs.mean() - expected[0]) < 0.5 and abs(ys.mean() - expected[1]) < 0.5


def test_depth_of_slanted_plane_is_analytic(scene_renderer):
    r, meshes = scene_renderer
    R = _rot([1.0, 0.5, 0.0], np.radians(35.0))
    t = np.array([10.0, -5.0, 600.0])
    out = r.render([(3, R, t)], K_ODD)
    mask = out.mask_visib[0]
    assert mask.sum() > 0.3 * W * H
    # front face of the 2 mm plate: z = -1 in model coordinates, normal -z
    n = R @ np.array([0.0, 0.0, -1.0])
    d = n @ (R @ np.array([0.0, 0.0, -1.0]) + t)
    v, u = np.mgrid[0:H, 0:W]
    rays = np.stack([(u - K_ODD[0, 2]) / K_ODD[0, 0], (v - K_ODD[1, 2]) / K_ODD[1, 1], np.ones_like(u, float)], -1)
    z = d / (rays @ n)
    import cv2

    inner = cv2.erode(mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    err = np.abs(out.depth[inner] - z[inner])
    assert err.max() < 0.01, err.max()
    assert np.all(out.depth[~mask] == 0)


def test_bbox_matches_projected_vertices_and_origin_is_kept(scene_renderer):
    r, meshes = scene_renderer
    R = _rot([0.3, 1.0, 0.2], 0.9)
    t = np.array([-15.0, 10.0, 450.0])
    out = r.render([(2, R, t)], K_ODD)
    ys, xs = np.nonzero(out.mask_visib[0])
    lo, hi = _project_box(np.asarray(meshes[2].vertices), K_ODD, R, t)
    # pixel centres inside the silhouette: extent within one pixel of the projected box
    assert np.all(np.abs(np.array([xs.min(), ys.min()]) - lo) <= 1.0)
    assert np.all(np.abs(np.array([xs.max(), ys.max()]) - hi) <= 1.0)


def test_face_colours_are_exact_under_pure_ambient_light(scene_renderer):
    r, meshes = scene_renderer
    r.set_lights([], headlight=(1.0, 0.0))
    try:
        out = r.render([(2, np.eye(3), np.array([-25.0, 10.0, 400.0]))], K_ODD)
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
    out = r.render(objs, K_ODD, primitives=[prim], full_masks=True)
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
    out = r.render([(2, np.eye(3), np.array([0.0, 0.0, 400.0]))], K_ODD, background=bg)
    r.set_lights(None)
    empty = out.instance < 0
    assert np.array_equal(out.rgb[empty], bg[empty])


def test_render_depth_matches_renderer(scene_renderer):
    r, meshes = scene_renderer
    R = _rot([1, 2, 3], 1.0)
    t = np.array([5.0, 3.0, 420.0])
    d1 = render_depth(meshes[2], K_ODD, R, t, W, H)
    d2 = r.render([(2, R, t)], K_ODD).depth
    assert d1.dtype == np.float32 and d1.shape == (H, W)
    assert np.allclose(d1, d2, atol=1e-3)


def test_bad_input(scene_renderer, tmp_path):
    r, _ = scene_renderer
    with pytest.raises(ValueError, match="unknown obj_id"):
        r.render([(99, np.eye(3), np.array([0, 0, 300.0]))], K_ODD)
    with pytest.raises(ValueError, match="rotation"):
        r.render([(1, 2 * np.eye(3), np.array([0, 0, 300.0]))], K_ODD)
    with pytest.raises(ValueError, match="focal"):
        r.render([], np.diag([0.0, 1.0, 1.0]))
    with pytest.raises(ValueError, match="max_instances"):
        r.render([(1, np.eye(3), np.zeros(3) + 300)] * 3, K_ODD)
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
