"""The crop stream's realism options (materials, resampling, sensor effects, background clutter,
object gain, rendered clutter scenes, shadows, tabletop scenes)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import trimesh

from sc6d_jax.data import CropStream, StreamConfig
from sc6d_jax.data._augment import camera_effects
from sc6d_jax.data._stream import object_colour, object_contrast
from sc6d_jax.render import Light, Renderer
from sc6d_jax.train import DataFns, preset, train
from sc6d_jax.train.cli import apply_overrides
from sc6d_jax.train.loop import _default_data_fns


def _checkerboard(S: int, cell: int = 1) -> np.ndarray:
    v, u = np.mgrid[0:S, 0:S]
    board = (((u // cell) + (v // cell)) % 2 * 255).astype(np.uint8)
    return np.repeat(board[..., None], 3, axis=-1)


def _detail(img: np.ndarray) -> float:
    return float(cv2.Laplacian(img[..., 0].astype(np.float32), cv2.CV_32F).var())


def test_resampling_removes_the_detail_a_small_box_cannot_have():
    img = _checkerboard(64)
    rng = np.random.default_rng(0)
    small = camera_effects(rng, img, side=16.0, sensor=False)
    assert small.shape == img.shape and small.dtype == np.uint8
    assert _detail(small) < 0.05 * _detail(img)  # a 1-px checkerboard cannot survive 16 px
    # a box as large as the crop or larger: nothing to do without the sensor effects
    np.testing.assert_array_equal(camera_effects(rng, img, side=64.0, sensor=False), img)
    np.testing.assert_array_equal(camera_effects(rng, img, side=300.0, sensor=False), img)
    np.testing.assert_array_equal(camera_effects(rng, img, side=16.0, resample=False, sensor=False), img)


def test_sensor_effects_are_seeded_and_change_the_crop():
    img = (_checkerboard(64, cell=8) // 2 + np.arange(64, dtype=np.uint8)[None, :, None]).astype(np.uint8)
    a = [camera_effects(np.random.default_rng(s), img, side=200.0, resample=False) for s in range(12)]
    b = [camera_effects(np.random.default_rng(s), img, side=200.0, resample=False) for s in range(12)]
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    changed = [not np.array_equal(x, img) for x in a]
    assert sum(changed) >= 9  # four effects at p 0.3-0.5: at least one in nearly every crop
    assert all(x.shape == img.shape and x.dtype == np.uint8 for x in a)


def test_set_material_changes_the_highlights_and_checks_its_input():
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=50.0)
    mesh.visual.face_colors = [150, 150, 150, 255]
    K = np.array([[200.0, 0, 47.5], [0, 200.0, 47.5], [0, 0, 1]])
    r = Renderer({1: mesh}, 96, 96, n_lights=1)
    try:
        r.set_lights([Light(direction=(0.0, 0.0, 1.0), diffuse=0.5, specular=1.0)], headlight=(0.2, 0.0))
        pose = [(1, np.eye(3), np.array([0.0, 0.0, 400.0]))]
        r.set_material(1, specular=0.0, shininess=0.5)
        dull = r.render(pose, K).rgb.astype(np.int32)
        r.set_material(1, specular=1.0, shininess=0.5)
        shiny = r.render(pose, K).rgb.astype(np.int32)
        assert shiny.max() > dull.max() + 20  # a highlight appears
        np.testing.assert_array_equal(shiny[0, 0], dull[0, 0])  # the background is untouched
        with pytest.raises(ValueError, match="unknown obj_id"):
            r.set_material(2)
        with pytest.raises(ValueError, match="specular"):
            r.set_material(1, specular=1.5)
    finally:
        r.close()


def test_distractors_stay_behind_the_target(models):
    """Clutter behind the target never covers it: with plain backgrounds and no occluders, the
    target's visible masks are those of the stream without distractors, while other pixels
    than the plain background appear around it."""
    kw = dict(crop_size=48, batch_size=12, workers=0, obj_ids=(1, 5, 8), seed=5, augment=False,
              background="plain", occlusion=0.0)
    with CropStream(StreamConfig(str(models), **kw)) as s:
        base = s.batch(0)
    with CropStream(StreamConfig(str(models), distractors=2, materials=True, **kw)) as s:
        clutter = s.batch(0)
    np.testing.assert_array_equal(clutter["mask_visib"], base["mask_visib"])
    for k in ("R", "t", "K", "delta_z", "obj_id"):
        np.testing.assert_array_equal(clutter[k], base[k])

    def colours_outside(batch):
        out = []
        for rgb, m in zip(batch["rgb"], batch["mask_visib"]):
            px = rgb[m == 0].reshape(-1, 3)
            out.append(len(np.unique(px, axis=0)))
        return np.array(out)

    assert np.all(colours_outside(base) <= 2)  # plain: one colour (anti-aliased edges aside)
    assert np.sum(colours_outside(clutter) > 10) >= 6  # clutter in most crops
    with pytest.raises(ValueError, match="distractors"):
        StreamConfig(str(models), distractors=-1)


def _object_pixels_with(models, **option) -> list[tuple[np.ndarray, np.ndarray]]:
    """Plain backgrounds, no occluders or augmentation, with and without a stream option that
    changes only the objects' pixels: checks that the labels and the background are the same,
    and returns each crop's object pixels (without, with) as float arrays (N, 3)."""
    kw = dict(crop_size=48, batch_size=12, workers=0, obj_ids=(1, 5, 8), seed=5, augment=False,
              background="plain", occlusion=0.0)
    with CropStream(StreamConfig(str(models), **kw)) as s:
        base = s.batch(0)
    with CropStream(StreamConfig(str(models), **option, **kw)) as s:
        changed = s.batch(0)
    for k in ("R", "t", "K", "delta_z", "obj_id", "mask_visib"):
        np.testing.assert_array_equal(changed[k], base[k])
    out = []
    for a, b, m in zip(base["rgb"], changed["rgb"], base["mask_visib"]):
        np.testing.assert_array_equal(b[m == 0], a[m == 0])  # the background is untouched
        out.append((a[m > 0].astype(np.float64), b[m > 0].astype(np.float64)))
    return out


def test_object_gain_scales_the_objects_and_keeps_the_background(models):
    """Plain backgrounds, no occluders or augmentation: with object_gain the background pixels are
    those of the stream without it, and each crop's object pixels are one factor brighter or darker
    (within the range), the labels unchanged."""
    ratios = []
    for x, y in _object_pixels_with(models, object_gain=(0.5, 2.0)):
        ok = (x > 20) & (y < 250)  # neither dark (rounding) nor saturated
        ratios.append(np.median(y[ok] / x[ok]))
    ratios = np.array(ratios)
    assert np.all((ratios > 0.47) & (ratios < 2.1))
    assert ratios.min() < 0.85 and ratios.max() > 1.2  # a factor per crop, both ways
    with pytest.raises(ValueError, match="object_gain"):
        StreamConfig(str(models), object_gain=(2.0, 1.0))
    with pytest.raises(ValueError, match="object_gain"):
        apply_overrides(preset("tiny"), ["stream.object_gain=0,2"])


def test_object_contrast_spreads_each_object_about_its_mean(models):
    """Plain backgrounds, no occluders or augmentation: with object_contrast the background and the
    labels are those of the stream without it, each crop's object keeps its mean colour, and its
    pixels' spread about that mean grows or shrinks by one factor (within the range, both ways)."""
    factors = []
    for x, y in _object_pixels_with(models, object_contrast=(0.5, 2.0)):
        if (y > 250).mean() + (y < 5).mean() > 0.02:
            continue  # clipped: the spread is no longer one factor
        np.testing.assert_allclose(y.mean(0), x.mean(0), atol=1.0)  # the mean colour stays
        factors.append(np.linalg.norm(y - y.mean(0)) / np.linalg.norm(x - x.mean(0)))
    factors = np.array(factors)
    assert len(factors) >= 6
    assert np.all((factors > 0.48) & (factors < 2.05))
    assert factors.min() < 0.85 and factors.max() > 1.2  # a factor per crop, both ways
    img = np.full((4, 4, 3), 100, np.uint8)
    img[0, :2] = 200  # instance 0: two bright pixels and two dark ones, mean 150
    inst = np.full((4, 4), -1, np.int32)
    inst[0] = 0
    out = object_contrast(np.random.default_rng(0), img, inst, (2.0, 2.0))
    np.testing.assert_array_equal(out[0], [[250] * 3, [250] * 3, [50] * 3, [50] * 3])
    np.testing.assert_array_equal(out[1:], img[1:])  # the background (-1) is untouched
    with pytest.raises(ValueError, match="object_contrast"):
        StreamConfig(str(models), object_contrast=(2.0, 1.0))
    with pytest.raises(ValueError, match="object_contrast"):
        apply_overrides(preset("tiny"), ["stream.object_contrast=0,2"])


def test_object_colour_scales_each_channel_of_each_object(models):
    """Plain backgrounds, no occluders or augmentation: with object_colour the background and the
    labels are those of the stream without it, and each crop's object pixels are scaled per channel
    by factors within the range that differ between channels."""
    spreads = []
    for x, y in _object_pixels_with(models, object_colour=(0.7, 1.4)):
        ok = np.all((x > 20) & (y < 250), axis=1)  # neither dark (rounding) nor saturated
        g = np.median(y[ok] / x[ok], axis=0)
        assert np.all((g > 0.68) & (g < 1.43))
        spreads.append(g.max() - g.min())
    assert max(spreads) > 0.2  # the channels move apart: a white balance, not a gain
    img = np.full((2, 2, 3), 100, np.uint8)
    inst = np.array([[0, 0], [-1, 1]], np.int32)
    out = object_colour(np.random.default_rng(0), img, inst, (0.5, 2.0))
    np.testing.assert_array_equal(out[1, 0], img[1, 0])  # the background (-1) is untouched
    np.testing.assert_array_equal(out[0, 0], out[0, 1])  # one instance: one set of factors
    assert not np.array_equal(out[0, 0], out[1, 1])  # another instance: its own
    with pytest.raises(ValueError, match="object_colour"):
        apply_overrides(preset("tiny"), ["stream.object_colour=1.4,0.7"])


def test_scene_backgrounds_are_windows_of_rendered_clutter(models):
    """scene_backgrounds=1: every crop's background is an S x S window (maybe mirrored) of one of
    the worker's rendered clutter scenes, which are a pure function of the seed and show the
    models (many colours and shades, not a procedural pattern); labels and masks are unchanged."""
    from sc6d_jax.data import _stream
    from sc6d_jax.data._clutter import clutter_scenes

    S = 48
    kw = dict(crop_size=S, batch_size=8, workers=0, obj_ids=(1, 5, 8), seed=5, augment=False, occlusion=0.0)
    with CropStream(StreamConfig(str(models), **kw)) as s:
        base = s.batch(0)
    with CropStream(StreamConfig(str(models), scene_backgrounds=1.0, **kw)) as s:
        got = s.batch(0)
        bank = s._local.scenes  # the in-process worker (workers=0)
    assert bank.shape == (_stream.SCENE_BANK, 2 * S, 2 * S, 3)
    for k in ("R", "t", "K", "delta_z", "obj_id", "mask_visib"):
        np.testing.assert_array_equal(got[k], base[k])
    def window_of_bank(rgb: np.ndarray, bg: np.ndarray) -> bool:
        r0, c0 = (int(v[0]) for v in np.nonzero(bg))  # one background pixel anchors the search
        for scene in bank:
            for img in (scene, scene[:, ::-1]):
                for y, x in zip(*np.nonzero(np.all(img == rgb[r0, c0], axis=-1))):
                    y, x = y - r0, x - c0
                    if 0 <= y <= S and 0 <= x <= S and np.array_equal(img[y:y + S, x:x + S][bg], rgb[bg]):
                        return True
        return False

    assert all(window_of_bank(rgb, m == 0) for rgb, m in zip(got["rgb"], got["mask_visib"]))
    assert not window_of_bank(base["rgb"][0], base["mask_visib"][0] == 0)  # a procedural one is not
    from sc6d_jax.bop import load_models_info, model_path
    from sc6d_jax.render import load_mesh

    info = load_models_info(models)
    meshes = {i: load_mesh(model_path(models, i)) for i in (1, 5, 8)}
    a = clutter_scenes(meshes, {i: info[i].diameter for i in meshes}, 3, 64, np.random.default_rng(1))
    b = clutter_scenes(meshes, {i: info[i].diameter for i in meshes}, 3, 64, np.random.default_rng(1))
    np.testing.assert_array_equal(a, b)
    assert all(len(np.unique(x.reshape(-1, 3), axis=0)) > 200 for x in a)  # shaded models, not flat fills
    with pytest.raises(ValueError, match="scene_backgrounds"):
        StreamConfig(str(models), scene_backgrounds=1.5)
    with pytest.raises(ValueError, match="scene_backgrounds"):
        apply_overrides(preset("tiny"), ["stream.scene_backgrounds=-0.1"])


def test_primitive_support_is_the_farthest_point_along_the_direction():
    """``support`` of each primitive shape equals the largest projection of points sampled on its
    surface (the box's corners exactly, the curved ones to within sampling)."""
    from sc6d_jax.data._clutter import support
    from sc6d_jax.data._scene import random_rotation

    rng = np.random.default_rng(0)
    u = rng.normal(size=(20000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    for _ in range(5):
        R, n = random_rotation(rng), rng.normal(size=3)
        n /= np.linalg.norm(n)
        s = rng.uniform(5.0, 30.0, 3)
        corners = np.array(np.meshgrid(*[[-1, 1]] * 3)).reshape(3, -1).T * s
        assert support("box", s, R, n) == pytest.approx((corners @ R.T @ n).max(), rel=1e-9)
        assert support("sphere", s, R, n) == pytest.approx(s[0])
        assert support("ellipsoid", s, R, n) == pytest.approx(((u * s) @ R.T @ n).max(), rel=1e-3)
        ang = rng.uniform(0, 2 * np.pi, 20000)
        rim = np.stack([s[0] * np.cos(ang), s[0] * np.sin(ang), rng.choice([-1, 1], 20000) * s[1]], 1)
        assert support("cylinder", s, R, n) == pytest.approx((rim @ R.T @ n).max(), rel=1e-3)
    with pytest.raises(ValueError, match="shape"):
        support("cone", (1, 1, 1), np.eye(3), np.array([0, 0, 1.0]))


def _table_models(models, ids):
    """What ``tabletop_around`` takes of the models ``ids``: (meshes, hull vertices, radii, diameters)."""
    from sc6d_jax.bop import load_models_info, model_path
    from sc6d_jax.data._scene import hull_vertices
    from sc6d_jax.render import load_mesh

    info = load_models_info(models)
    meshes = {i: load_mesh(model_path(models, i)) for i in ids}
    verts = {i: hull_vertices(m.vertices) for i, m in meshes.items()}
    radii = {i: float(np.linalg.norm(v, axis=1).max()) for i, v in verts.items()}
    return meshes, verts, radii, {i: info[i].diameter for i in ids}


def test_tabletop_stands_the_target_and_its_neighbours_on_one_table(models):
    """``tabletop_around``: the table's plane touches the target's lowest point and faces the
    camera; every neighbour and shape rests on it without meeting the target; a pure function of
    the seed. Rendered, the table never covers the target and fills much of the crop."""
    from sc6d_jax import geometry as G
    from sc6d_jax.data._clutter import TABLE_GREY, support, table_under, tabletop_around, textured_table
    from sc6d_jax.data._scene import sample_pose

    ids = [1, 5, 8]
    meshes, verts, radii, diam = _table_models(models, ids)
    S = 64
    ren = Renderer(meshes, S, S, max_instances=2, n_primitives=4)
    try:
        tables = 0.0
        for seed in range(6):
            p = sample_pose(np.random.default_rng(seed), ids, verts, diam)
            rng = np.random.default_rng(100 + seed)
            table, objs, prims = tabletop_around(rng, p.obj_id, p.R, p.t, verts, radii, diam, ids)
            again = tabletop_around(np.random.default_rng(100 + seed), p.obj_id, p.R, p.t, verts, radii, diam, ids)
            assert [o[0] for o in again[1]] == [o[0] for o in objs]
            np.testing.assert_array_equal(again[0].t, table.t)
            n, h = table_under(np.random.default_rng(100 + seed), p.R, p.t, verts[p.obj_id])
            assert h < 0 < float(np.dot(n, -p.t))  # the camera (the origin) above the table, facing it
            assert float(((verts[p.obj_id] @ p.R.T + p.t) @ n).min()) == pytest.approx(h)
            top = np.asarray(table.t) + table.size[2] * n  # the box's top face lies in the plane
            assert float(top @ n) == pytest.approx(h) and tuple(table.rgb) == (TABLE_GREY,) * 3
            assert len(objs) <= 4 and len(prims) <= 2
            for oid, R_o, c in objs:
                assert float(((verts[oid] @ R_o.T + c) @ n).min()) == pytest.approx(h, abs=1e-6 * diam[oid])
                assert np.linalg.norm(c - p.t) >= radii[oid] + radii[p.obj_id]
            for q in prims:
                assert float(np.asarray(q.t) @ n) - support(q.shape, q.size, q.R, n) == pytest.approx(h)
            T = np.asarray(G.crop_transform(p.box[:2] + p.box[2:] / 2, 1.5 * p.box[2:].max(), S), np.float64)
            K_B = T @ p.K
            alone = ren.render([(p.obj_id, p.R, p.t)], K_B, depth=False)
            on_table = ren.render([(p.obj_id, p.R, p.t)], K_B, primitives=[table], depth=False)
            np.testing.assert_array_equal(on_table.mask_visib[0], alone.mask_visib[0])  # never in front
            table_px = on_table.instance == 1
            tables += table_px.mean()
            tex = np.full((S, S, 3), 200, np.uint8)
            out = textured_table(on_table.rgb, table_px, tex)
            np.testing.assert_array_equal(out[~table_px], on_table.rgb[~table_px])
            shade = on_table.rgb[table_px].astype(np.float64) / (255 * TABLE_GREY)
            assert np.abs(out[table_px] - np.clip(200 * shade, 0, 255)).max() <= 1.0
        assert tables / 6 > 0.3  # the table fills a good part of the crops
    finally:
        ren.close()


def test_tabletop_spacing_stands_neighbours_against_the_target(models):
    """``spacing``: along each neighbour's direction from the target in the table's plane, its
    nearest point lies the drawn spacing (0-0.1 target diameters) beyond the target's farthest one,
    so a plane separates them; they stand nearer than outside the bounding spheres."""
    from sc6d_jax.data._clutter import support, table_under, tabletop_around
    from sc6d_jax.data._scene import sample_pose

    ids = [1, 5, 8]
    _, verts, radii, diam = _table_models(models, ids)
    spacings, dist_spaced, dist_sphere = [], [], []
    for seed in range(12):
        p = sample_pose(np.random.default_rng(seed), ids, verts, diam)
        _, objs, prims = tabletop_around(np.random.default_rng(7 + seed), p.obj_id, p.R, p.t, verts, radii, diam, ids,
                                         spacing=(0.0, 0.1))
        _, objs0, _ = tabletop_around(np.random.default_rng(7 + seed), p.obj_id, p.R, p.t, verts, radii, diam, ids)
        n, _ = table_under(np.random.default_rng(7 + seed), p.R, p.t, verts[p.obj_id])
        target = verts[p.obj_id] @ p.R.T  # about the target's centre

        def along(c):  # the unit direction from the target to c, in the table's plane
            d = np.asarray(c, np.float64) - p.t
            d = d - (d @ n) * n
            return d / np.linalg.norm(d)

        for oid, R_o, c in objs:
            u = along(c)
            spacings.append((float(((verts[oid] @ R_o.T + c - p.t) @ u).min()) - float((target @ u).max())) / diam[p.obj_id])
            dist_spaced.append(float(np.linalg.norm(c - p.t)))
        for q in prims:
            u = along(q.t)
            reach = float((np.asarray(q.t) - p.t) @ u) - support(q.shape, q.size, q.R, u)
            spacings.append((reach - float((target @ u).max())) / diam[p.obj_id])
        dist_sphere += [float(np.linalg.norm(c - p.t)) for _, _, c in objs0]
    assert len(spacings) >= 12
    assert min(spacings) >= -1e-6 and max(spacings) <= 0.1 + 1e-6
    assert np.median(dist_spaced) < 0.8 * np.median(dist_sphere)


def test_stream_tabletop_keeps_the_labels_and_is_deterministic(models):
    """tabletop=1: the same poses and labels as without (the scene is drawn after them), other
    pixels around the target, batches a pure function of the seed; bad values are refused."""
    def first_batch(**opts):
        cfg = StreamConfig(str(models), crop_size=48, batch_size=8, workers=0, obj_ids=(1, 5, 8), seed=4,
                           augment=False, occlusion=0.0, **opts)
        with CropStream(cfg) as s:
            return s.batch(0)

    base, got, again = first_batch(), first_batch(tabletop=1.0), first_batch(tabletop=1.0)
    for k in got:
        np.testing.assert_array_equal(got[k], again[k])
    for k in ("R", "t", "K", "delta_z", "obj_id"):
        np.testing.assert_array_equal(got[k], base[k])
    bg = (got["mask_visib"] == 0) & (base["mask_visib"] == 0)
    assert np.mean(np.any(got["rgb"] != base["rgb"], axis=-1)[bg]) > 0.5
    with pytest.raises(ValueError, match="tabletop"):
        StreamConfig(str(models), tabletop=1.5)
    with pytest.raises(ValueError, match="tabletop"):
        apply_overrides(preset("tiny"), ["stream.tabletop=-0.1"])
    with pytest.raises(ValueError, match="tabletop_spacing"):
        StreamConfig(str(models), tabletop=1.0, tabletop_spacing=(0.3, 0.1))
    with pytest.raises(ValueError, match="needs stream.tabletop > 0"):
        apply_overrides(preset("tiny"), ["stream.tabletop_spacing=0,0.2"])
    # neighbours in contact, crops cut from the visible box: still the same poses, deterministic
    near, near2 = (first_batch(tabletop=1.0, tabletop_spacing=(0.0, 0.1), box_source="visible") for _ in range(2))
    for k in near:
        np.testing.assert_array_equal(near[k], near2[k])
    np.testing.assert_array_equal(near["R"], base["R"])


def _plate_and_ball(shadow_size: int = 256) -> Renderer:
    plate = trimesh.creation.box(extents=(400.0, 400.0, 4.0))
    plate.visual.face_colors = [200, 200, 200, 255]
    ball = trimesh.creation.icosphere(subdivisions=3, radius=30.0)
    ball.visual.face_colors = [60, 120, 200, 255]
    return Renderer({1: plate, 2: ball}, 96, 96, n_lights=1, shadow_size=shadow_size)


def test_a_light_casts_the_shadow_of_one_object_onto_another():
    """A ball in front of a plate, lit along (1, 0, 1): with ``castshadow`` a dark spot appears
    on the plate where the ball's shadow falls, nowhere else; the ball itself and the plate's lit
    part keep their colours, and ``render(shadows=False)`` draws it unshadowed."""
    K = np.array([[120.0, 0, 47.5], [0, 120.0, 47.5], [0, 0, 1]])
    scene = [(1, np.eye(3), np.array([0.0, 0.0, 1000.0])), (2, np.eye(3), np.array([-80.0, 0.0, 800.0]))]
    r = _plate_and_ball()
    try:
        images = {}
        for cast in (False, True):
            r.set_lights([Light(direction=(1.0, 0.0, 1.0), diffuse=0.6, specular=0.0, castshadow=cast)],
                         headlight=(0.3, 0.0), shadow_region=((0.0, 0.0, 900.0), 400.0))
            images[cast] = r.render(scene, K).rgb.astype(np.int32)
            if cast:
                unshadowed = r.render(scene, K, shadows=False).rgb.astype(np.int32)
        lit, shaded = images[False], images[True]
        # the light's ray through the ball's centre meets the plate (z = 998) at x = 118 mm:
        # u = 47.5 + 120 * 118 / 998 = 61.7 px, v = 47.5 px; the ball is seen at u = 35.5
        assert (lit[47, 61] - shaded[47, 61]).min() > 60  # in the shadow: the light's share is gone
        assert np.abs(lit[47, 47] - shaded[47, 47]).max() <= 2  # plate outside the shadow
        assert np.abs(lit[47, 35] - shaded[47, 35]).max() <= 2  # the ball
        dark = (lit - shaded).min(axis=-1) > 30
        ys, xs = np.nonzero(dark)
        assert 20 < len(xs) < 150 and xs.min() > 53 and xs.max() < 71 and ys.min() > 38 and ys.max() < 57
        assert np.abs(unshadowed - lit).max() <= 2
        with pytest.raises(ValueError, match="shadow_region"):
            r.set_lights([Light(direction=(1.0, 0.0, 1.0), castshadow=True)])
        with pytest.raises(ValueError, match="shadow_region"):
            r.set_lights([Light(direction=(1.0, 0.0, 1.0), castshadow=True)], shadow_region=((0, 0, 800), -1.0))
    finally:
        r.close()
    r = _plate_and_ball(shadow_size=0)
    try:
        with pytest.raises(ValueError, match="shadow_size=0"):
            r.set_lights([Light(direction=(1.0, 0.0, 1.0), castshadow=True)], shadow_region=((0, 0, 800), 400.0))
    finally:
        r.close()
    with pytest.raises(ValueError, match="shadow_size"):
        _plate_and_ball(shadow_size=-1)


def test_stream_shadows_darken_the_objects_and_keep_the_labels(models):
    """shadows=1: every crop's key light casts shadows from a side; the labels are drawn as
    without the option, batches are a pure function of the seed, and with shadows=0 (the
    default) the stream draws no extra random numbers (earlier runs' streams unchanged)."""
    kw = dict(crop_size=48, batch_size=8, workers=0, obj_ids=(1, 5, 8), seed=5, augment=False, occlusion=1.0,
              background="plain")
    with CropStream(StreamConfig(str(models), **kw)) as s:
        base = s.batch(0)
    with CropStream(StreamConfig(str(models), shadows=0.0, **kw)) as s:
        off = s.batch(0)
    for k in base:
        np.testing.assert_array_equal(off[k], base[k])
    with CropStream(StreamConfig(str(models), shadows=1.0, **kw)) as s:
        got, again = s.batch(0), s.batch(0)
        assert s._local.renderer.shadow_size > 0
    for k in got:
        np.testing.assert_array_equal(got[k], again[k])
    for k in ("R", "t", "K", "obj_id"):
        np.testing.assert_array_equal(got[k], base[k])
    assert not np.array_equal(got["rgb"], base["rgb"])
    with pytest.raises(ValueError, match="shadows"):
        StreamConfig(str(models), shadows=1.5)
    with pytest.raises(ValueError, match="shadows"):
        apply_overrides(preset("tiny"), ["stream.shadows=-0.1"])


def test_realism_options_reach_the_stream_from_the_config(models, tmp_path):
    """``--set stream.sensor=true`` etc. (and the box jitter) are passed to the crop stream; when
    off (unset), nothing is."""
    seen: list[dict] = []
    default = _default_data_fns()

    class Stop(Exception):
        pass

    def spy(**kw):
        seen.append(kw)
        raise Stop

    fns = DataFns(spy, default.stream, default.z_range)
    cfg = apply_overrides(preset("tiny"), ["stream.sensor=true", "stream.distractors=2", "stream.materials=true",
                                           "stream.resample=true", "stream.box_shift=0", "stream.box_scale=0.9,1.1",
                                           "stream.box_source=visible", "stream.object_gain=0.5,2",
                                           "stream.object_contrast=0.7,1.5", "stream.object_colour=0.8,1.25",
                                           "stream.scene_backgrounds=0.5", "stream.shadows=0.25",
                                           "stream.tabletop=0.5", "steps=2",
                                           "val_crops=0"])
    with pytest.raises(Stop):
        train(cfg, models, tmp_path / "a", workers=0, progress=False, verbose=False, data_fns=fns)
    keys = ("sensor", "distractors", "materials", "resample", "box_shift", "box_scale", "box_source", "object_gain",
            "object_contrast", "object_colour", "scene_backgrounds", "shadows", "tabletop")
    assert {k: seen[-1].get(k) for k in keys} == {"sensor": True, "distractors": 2, "materials": True, "resample": True,
                                                  "box_shift": 0.0, "box_scale": (0.9, 1.1), "box_source": "visible",
                                                  "object_gain": (0.5, 2.0), "object_contrast": (0.7, 1.5),
                                                  "object_colour": (0.8, 1.25),
                                                  "scene_backgrounds": 0.5, "shadows": 0.25, "tabletop": 0.5}
    with pytest.raises(Stop):
        train(apply_overrides(preset("tiny", steps=2, val_crops=0), ["stream.box_shift=none", "stream.box_scale=none"]),
              models, tmp_path / "b", workers=0, progress=False, verbose=False, data_fns=fns)
    assert not set(keys) & set(seen[-1])
    # the training settings hold every option the stream takes from them, with the same default
    import dataclasses

    from sc6d_jax.data._stream import PASSED_WHEN_SET
    from sc6d_jax.train import StreamSettings

    stream_defaults = {f.name: f.default for f in dataclasses.fields(StreamConfig)}
    assert set(keys) - {"box_shift", "box_scale", "box_source"} <= set(PASSED_WHEN_SET)
    for name in PASSED_WHEN_SET:
        assert getattr(StreamSettings(), name) == stream_defaults[name], name
    with pytest.raises(ValueError, match="distractors"):
        apply_overrides(preset("tiny"), ["stream.distractors=-1"])
    with pytest.raises(ValueError, match="box_scale"):
        apply_overrides(preset("tiny"), ["stream.box_scale=1.1,0.9"])
    with pytest.raises(ValueError, match="box_source"):
        apply_overrides(preset("tiny"), ["stream.box_source=full"])


def test_gallery_script_draws_every_row_and_refuses_a_missing_folder(models, tmp_path, capsys):
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "experiments" / "realism_gallery.py"
    spec = importlib.util.spec_from_file_location("realism_gallery", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    out = tmp_path / "g.png"
    assert mod.main(["--models", str(models), "--out", str(out), "--n", "2", "--size", "32"]) == 0
    assert out.stat().st_size > 1000
    assert mod.main(["--models", str(tmp_path / "nope"), "--out", str(out)]) == 2
    assert "models folder not found" in capsys.readouterr().err


def test_simplify_mesh_keeps_shape_colours_and_orientation():
    from sc6d_jax.render import simplify_mesh

    mesh = trimesh.creation.icosphere(subdivisions=5, radius=40.0)  # 20,480 faces
    top = mesh.triangles_center[:, 2] > 0
    colours = np.where(top[:, None], [[200, 30, 30, 255]], [[30, 30, 200, 255]]).astype(np.uint8)
    mesh.visual.face_colors = colours
    small = simplify_mesh(mesh, 2000)
    assert 500 < len(small.faces) <= 2000
    # every vertex stays near the sphere (within a grid cell: extent 80 mm, k >= 10 cells)
    r = np.linalg.norm(small.vertices, axis=1)
    assert np.all(np.abs(r - 40.0) < 80.0 / 10 * np.sqrt(3))
    # faces still point outwards, and keep their colours
    outward = np.einsum("ij,ij->i", small.face_normals, small.triangles_center) > 0
    assert outward.mean() > 0.98
    fc = np.asarray(small.visual.face_colors)
    z = small.triangles_center[:, 2]
    assert np.all(fc[z > 8.0, 0] == 200) and np.all(fc[z < -8.0, 2] == 200)
    # silhouettes at crop size agree with the full mesh
    K = np.array([[140.0, 0, 31.5], [0, 140.0, 31.5], [0, 0, 1]])
    masks = []
    for m in (mesh, small):
        rr = Renderer({1: m}, 64, 64, n_lights=0)
        try:
            masks.append(rr.render([(1, np.eye(3), np.array([0.0, 0.0, 200.0]))], K, depth=False).mask_visib[0] > 0)
        finally:
            rr.close()
    iou = (masks[0] & masks[1]).sum() / (masks[0] | masks[1]).sum()
    assert iou > 0.97
    assert simplify_mesh(mesh, 30_000) is mesh  # within the limit: unchanged
    with pytest.raises(ValueError, match="max_faces"):
        simplify_mesh(mesh, 2)


def test_stream_renders_simplified_meshes_with_the_same_labels(models):
    from sc6d_jax.render import load_mesh

    kw = dict(crop_size=32, batch_size=4, workers=0, obj_ids=(1, 8), seed=2, augment=False)
    with CropStream(StreamConfig(str(models), **kw)) as s:
        full = s.batch(0)
    faces = len(load_mesh(models / "obj_000008.ply").faces)
    limit = max(4, faces // 4)
    with CropStream(StreamConfig(str(models), max_faces=limit, **kw)) as s:
        assert int(s._local.renderer.model.mesh_facenum.max()) <= limit
        simple = s.batch(0)
    for k in ("R", "t", "K_B", "delta_z", "obj_id"):
        np.testing.assert_array_equal(simple[k], full[k])
    assert not np.array_equal(simple["rgb"], full["rgb"])
    with pytest.raises(ValueError, match="max_faces"):
        StreamConfig(str(models), max_faces=2)
