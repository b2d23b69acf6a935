"""BOP dataset IO: round trips of every writer, the reader on real datasets, clear errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from sc6d_jax import bop


def _rot(seed: int) -> np.ndarray:
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def _write_scene(root, scene_id=1):
    d = root / "test" / f"{scene_id:06d}"
    K = np.array([[600.0, 0, 320.5], [0, 610.0, 240.25], [0, 0, 1]])
    cams = {0: bop.Camera(K, 0.1), 1: bop.Camera(K, 0.1)}
    gts = {i: [bop.GtPose(1, _rot(i), np.array([10.0, -5.0, 600.0 + i])), bop.GtPose(2, _rot(10 + i), np.array([1.0, 2.0, 3.0]))] for i in (0, 1)}
    info = bop.GtInfo((1, 2, 30, 40), (3, 4, 20, 30), 1200, 600, 1200, 0.5)
    infos = {i: [info, info] for i in (0, 1)}
    bop.write_scene_camera(d / "scene_camera.json", cams)
    bop.write_scene_gt(d / "scene_gt.json", gts)
    bop.write_scene_gt_info(d / "scene_gt_info.json", infos)
    mi = {
        1: bop.ModelInfo(1, 100.0, (-1.0, -2.0, -3.0), (2.0, 4.0, 6.0)),
        2: bop.ModelInfo(2, 50.0, (0, 0, 0), (1, 1, 1), [np.diag([1.0, -1, -1, 1])], [{"axis": np.array([0, 0, 1.0]), "offset": np.zeros(3)}]),
    }
    bop.write_models_info(root / "models" / "models_info.json", mi)
    return cams, gts, infos, mi


def test_scene_files_round_trip(tmp_path):
    cams, gts, infos, mi = _write_scene(tmp_path)
    ds = bop.BopDataset(tmp_path)
    assert ds.scene_ids() == [1]
    assert ds.im_ids(1) == [0, 1]
    np.testing.assert_array_equal(ds.scene_camera(1)[1].K, cams[1].K)
    assert ds.scene_camera(1)[0].depth_scale == 0.1
    for im_id in (0, 1):
        for a, b in zip(ds.scene_gt(1)[im_id], gts[im_id]):
            assert a.obj_id == b.obj_id
            np.testing.assert_array_equal(a.R, b.R)
            np.testing.assert_array_equal(a.t, b.t)
        assert ds.scene_gt_info(1)[im_id] == infos[im_id]
    got = ds.models_info
    assert got[1].diameter == 100.0 and not got[1].is_symmetric
    assert got[2].is_symmetric
    np.testing.assert_array_equal(got[2].symmetries_discrete[0], np.diag([1.0, -1, -1, 1]))
    # Without a targets file every GT instance is a target.
    assert [(t.im_id, t.obj_id, t.inst_count) for t in ds.targets()] == [(0, 1, 1), (0, 2, 1), (1, 1, 1), (1, 2, 1)]
    bop.write_targets(tmp_path / "test_targets_bop19.json", [bop.Target(1, 1, 2, 1)])
    assert ds.targets() == [bop.Target(1, 1, 2, 1)]


def test_results_csv_round_trip_and_equal_times(tmp_path):
    path = tmp_path / "sc6d_demo-test.csv"
    ests = [
        bop.PoseEstimate(1, 0, 1, 0.9, _rot(1), np.array([1.5, -2.25, 700.125]), 0.2),
        bop.PoseEstimate(1, 0, 2, 0.8, _rot(2), np.array([0.0, 0.0, 500.0]), 0.3),
        bop.PoseEstimate(1, 1, 1, 0.7, _rot(3), np.array([3.0, 4.0, 5.0]), 0.1),
    ]
    bop.write_results_csv(path, ests)
    assert path.read_text().splitlines()[0] == "scene_id,im_id,obj_id,score,R,t,time"
    back = bop.read_results_csv(path)
    assert len(back) == 3
    for a, b in zip(back, ests):
        np.testing.assert_array_equal(a.R, b.R)  # repr() keeps every bit
        np.testing.assert_array_equal(a.t, b.t)
    assert back[0].time == back[1].time == 0.3  # one time per image, as BOP requires
    assert bop.results_name_ok(path) and not bop.results_name_ok(tmp_path / "my_method_x-test.csv")


def test_results_csv_rejects_nan(tmp_path):
    bad = bop.PoseEstimate(1, 0, 1, 0.9, np.full((3, 3), np.nan), np.zeros(3))
    with pytest.raises(ValueError, match="NaN"):
        bop.write_results_csv(tmp_path / "a_b-test.csv", [bad])
    assert not (tmp_path / "a_b-test.csv").exists()
    assert list(tmp_path.iterdir()) == []  # nothing half-written


def test_errors_name_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="dataset folder"):
        bop.BopDataset(tmp_path / "nope")
    _write_scene(tmp_path)
    ds = bop.BopDataset(tmp_path)
    (tmp_path / "test" / "000001" / "scene_camera.json").unlink()
    with pytest.raises(FileNotFoundError, match="scene_camera.json"):
        ds.scene_camera(1)
    with pytest.raises(FileNotFoundError, match="scene_camera.json"):
        bop.check_scene_files(tmp_path / "test" / "000001")
    (tmp_path / "test" / "000001" / "scene_gt.json").write_text("{not json")
    with pytest.raises(bop.BopFormatError, match="scene_gt.json: not valid JSON"):
        ds.scene_gt(1)
    (tmp_path / "test" / "000001" / "scene_gt_info.json").write_text(json.dumps({"0": [{"bbox_obj": [1, 2, 3, 4]}]}))
    with pytest.raises(bop.BopFormatError, match="scene_gt_info.json: image 0 gt 0"):
        ds.scene_gt_info(1)
    (tmp_path / "models" / "models_info.json").write_text(json.dumps({"1": {"diameter": -1}}))
    with pytest.raises(bop.BopFormatError, match="models_info.json"):
        _ = ds.models_info
    with pytest.raises(FileNotFoundError, match="obj_000007.ply"):
        bop.model_path(tmp_path / "models", 7)
    (tmp_path / "r.csv").write_text("a,b\n")
    with pytest.raises(bop.BopFormatError, match="header"):
        bop.read_results_csv(tmp_path / "r.csv")


def test_reads_real_lmo(shared_data):
    root = shared_data / "lmo"
    if not root.is_dir():
        pytest.skip("../shared/data/lmo not present")
    ds = bop.BopDataset(root)
    assert ds.scene_ids() == [2]
    assert not ds.has_depth()
    assert ds.obj_ids == [1, 5, 6, 8, 9, 10, 11, 12]
    targets = ds.targets()
    assert len(targets) > 0 and all(t.scene_id == 2 for t in targets)
    t0 = targets[0]
    gts = [g for g in ds.scene_gt(2)[t0.im_id] if g.obj_id == t0.obj_id]
    assert len(gts) == t0.inst_count
    for g in gts:
        np.testing.assert_allclose(g.R @ g.R.T, np.eye(3), atol=1e-3)  # LM-O GT is orthonormal to ~3e-4
    im = ds.load_rgb(2, t0.im_id)
    assert im.shape == (480, 640, 3) and im.dtype == np.uint8
    pts = ds.model_points(1)
    assert pts.shape[1] == 3 and np.ptp(pts, axis=0).max() < 2 * ds.models_info[1].diameter


def test_reads_reference_results(shared_data):
    ref = shared_data / "bop_reference"
    if not ref.is_dir():
        pytest.skip("../shared/data/bop_reference not present")
    ests = bop.read_results_csv(ref / "synthperturb_tudl-test.csv")
    assert len(ests) > 50
    ds = bop.BopDataset(ref / "tudl")
    assert ds.has_depth()
    depth = ds.load_depth(1, 0)
    assert depth.dtype == np.float32 and depth.max() > 100  # mm


def test_bbox_extent_turns_bop_pixel_boxes_into_the_silhouettes_extent():
    """BOP's bbox_visib runs from the first visible pixel's centre to the last one's: about one
    pixel short of the silhouette. bbox_extent recovers the silhouette's extent without bias
    (discs at random sub-pixel positions, pixel centres at integers)."""
    from sc6d_jax.bop import bbox_extent

    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:96, 0:96]
    raw_err, ext_err = [], []
    for _ in range(200):
        cx, cy, r = rng.uniform(40, 56), rng.uniform(40, 56), rng.uniform(8, 30)
        ys, xs = np.nonzero((xx - cx) ** 2 + (yy - cy) ** 2 <= r * r)
        bbox = (xs.min(), ys.min(), xs.max() - xs.min(), ys.max() - ys.min())  # the toolkit's calc_2d_bbox
        ext = bbox_extent(bbox)
        raw_err += [bbox[2] - 2 * r, bbox[3] - 2 * r]
        ext_err += [ext[2] - 2 * r, ext[3] - 2 * r]
        np.testing.assert_allclose(ext[:2] + ext[2:] / 2, (cx, cy), atol=0.5)  # the centre stays
    assert -1.2 < np.mean(raw_err) < -0.8  # the pixel box is a pixel short
    assert abs(np.mean(ext_err)) < 0.2 and np.max(np.abs(ext_err)) <= 1.0
    np.testing.assert_array_equal(bbox_extent(np.array([[10, 20, 5, 7]] * 2)), [[9.5, 19.5, 6, 8]] * 2)
    with pytest.raises(ValueError, match="bbox"):
        bbox_extent([1, 2, 3])


def test_most_visible_instances_ranks_by_visible_pixels_and_skips_empty_boxes():
    from sc6d_jax.bop import GtInfo, GtPose, most_visible_instances

    def gt(o):
        return GtPose(o, np.eye(3), np.zeros(3))

    def info(px, w=10):
        return GtInfo((0, 0, 10, 10), (0, 0, w, 10), px, px, px, 1.0)

    gts = [gt(1), gt(2), gt(1), gt(1), gt(1)]
    infos = [info(50), info(900), info(80), info(50), info(999, w=0)]
    # obj 1: 80 px first, then the two 50 px ones in file order; the empty visible box is left out
    assert most_visible_instances(gts, infos, 1) == [2, 0, 3]
    assert most_visible_instances(gts, infos, 2) == [1]
    assert most_visible_instances(gts, infos, 7) == []
