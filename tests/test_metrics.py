"""BOP19 metrics: pose errors, symmetries and the AR computation on small hand-checked cases."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from sc6d_jax.metrics import (
    MSPD_THRESHOLDS,
    MSSD_THRESHOLDS,
    VSD_TAUS,
    VSD_THRESHOLDS,
    EvalImage,
    GroundTruth,
    add,
    adi,
    average_time_per_image,
    depth_to_distance,
    evaluate_images,
    make_object_model,
    mspd,
    paired_difference,
    mssd,
    re,
    te,
    symmetry_coverage,
    symmetry_transformations,
    vsd,
)

K = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])

BOX_INFO = {  # 80 x 60 x 40 box: 180-degree symmetries about x, y, z
    "diameter": float(np.sqrt(80**2 + 60**2 + 40**2)),
    "symmetries_discrete": [
        [1, 0, 0, 0, 0, -1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1],
        [-1, 0, 0, 0, 0, 1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1],
        [-1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1],
    ],
}
CYL_INFO = {
    "diameter": 116.6,
    "symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}],
    "symmetries_discrete": [[1, 0, 0, 0, 0, -1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1]],
}


def box_points(sx=80.0, sy=60.0, sz=40.0, n=5) -> np.ndarray:
    g = np.stack(np.meshgrid(*[np.linspace(-0.5, 0.5, n)] * 3, indexing="ij"), -1).reshape(-1, 3)
    return g * np.array([sx, sy, sz])


def asym_points() -> np.ndarray:
    rng = np.random.default_rng(0)
    p = rng.uniform(-30, 30, size=(200, 3))
    return np.vstack([p, [[45.0, 0, 0], [0, 25.0, 0], [0, 0, 12.0]]])


def pose(rotvec=(0.3, -0.2, 0.5), t=(10.0, -20.0, 600.0)):
    return Rotation.from_rotvec(rotvec).as_matrix(), np.array(t, dtype=np.float64)


# ----------------------------------------------------------------------------- symmetries
def test_symmetry_transformations_discrete_box():
    syms = symmetry_transformations(BOX_INFO)
    assert len(syms) == 4
    np.testing.assert_array_equal(syms[0]["R"], np.eye(3))
    pts = box_points()
    for s in syms:
        assert abs(np.linalg.det(s["R"]) - 1) < 1e-12
        moved = pts @ s["R"].T + s["t"]
        # the box's vertex grid maps onto itself
        d = np.linalg.norm(moved[:, None] - pts[None], axis=2).min(axis=1)
        assert d.max() < 1e-9


def test_symmetry_transformations_continuous_count_and_order():
    syms = symmetry_transformations(CYL_INFO, 0.01)
    n = int(np.ceil(np.pi / 0.01))
    assert n == 315 and len(syms) == 2 * n
    # toolkit order: for each discrete (identity first) all continuous steps
    step = 2 * np.pi / n
    np.testing.assert_allclose(syms[1]["R"], Rotation.from_rotvec([0, 0, step]).as_matrix(), atol=1e-15)
    flip = np.diag([1.0, -1.0, -1.0])
    np.testing.assert_allclose(syms[n + 1]["R"], Rotation.from_rotvec([0, 0, step]).as_matrix() @ flip, atol=1e-15)
    # an axis offset gives t = offset - R offset
    info = {"diameter": 10.0, "symmetries_continuous": [{"axis": [0, 0, 2], "offset": [1.0, 0, 0]}]}
    s = symmetry_transformations(info, 0.5)[3]
    np.testing.assert_allclose(s["t"], np.array([1.0, 0, 0]) - s["R"] @ np.array([1.0, 0, 0]), atol=1e-15)


def test_symmetry_transformations_rejects_bad_input():
    with pytest.raises(ValueError, match="16 numbers"):
        symmetry_transformations({"symmetries_discrete": [[1, 0, 0]]})
    with pytest.raises(ValueError, match="max_sym_disc_step"):
        symmetry_transformations(BOX_INFO, 0)
    with pytest.raises(ValueError, match="zero axis"):
        symmetry_transformations({"symmetries_continuous": [{"axis": [0, 0, 0], "offset": [0, 0, 0]}]})


def test_symmetry_coverage_counts_equivalents():
    syms = symmetry_transformations(BOX_INFO)
    R_gt, _ = pose()
    flip_z = np.diag([-1.0, -1.0, 1.0])
    near = Rotation.from_rotvec([0, 0, np.radians(3)]).as_matrix()
    topk = np.stack([R_gt @ near, R_gt @ flip_z, Rotation.random(random_state=1).as_matrix()])
    assert symmetry_coverage(topk, R_gt, syms, 5.0) == (2, 0.5)
    assert symmetry_coverage(topk, R_gt, syms, 2.0)[0] == 1  # the 3-degree one no longer counts
    with pytest.raises(ValueError, match="R_topk"):
        symmetry_coverage(np.zeros((2, 3)), R_gt, syms, 5.0)


# ----------------------------------------------------------------------------- pose errors
def test_re_te_add_adi_basic():
    R, t = pose()
    R2 = R @ Rotation.from_rotvec([0, 0, np.radians(30)]).as_matrix()
    assert re(R2, R) == pytest.approx(30.0, abs=1e-9)
    assert re(R, R) == 0.0
    assert te(t + [3.0, 4.0, 0.0], t) == pytest.approx(5.0)
    pts = asym_points()
    assert add(R, t + [0, 0, 7.0], R, t, pts) == pytest.approx(7.0)
    assert adi(R2, t, R, t, pts) <= add(R2, t, R, t, pts) + 1e-12
    with pytest.raises(ValueError, match="R_est"):
        re(np.eye(2), R)
    with pytest.raises(ValueError, match="pts"):
        add(R, t, R, t, np.zeros((4, 2)))


def test_mssd_mspd_translation_and_symmetry():
    R, t = pose()
    pts = box_points()
    syms = symmetry_transformations(BOX_INFO)
    ident = symmetry_transformations({"diameter": 1.0})
    assert mssd(R, t + [0, 0, 12.5], R, t, pts, syms) == pytest.approx(12.5)
    # a 180-degree flip about the box's z axis is indistinguishable
    R_flip = R @ np.diag([-1.0, -1.0, 1.0])
    assert mssd(R_flip, t, R, t, pts, syms) < 1e-9
    assert mspd(R_flip, t, R, t, K, pts, syms) < 1e-9
    assert mssd(R_flip, t, R, t, pts, ident) > 50.0
    # MSPD of a fronto-parallel shift by dx mm at depth z is fx * dx / z pixels for every point
    R0 = np.eye(3)
    t0 = np.array([0.0, 0.0, 500.0])
    flat = np.c_[np.random.default_rng(0).uniform(-20, 20, (50, 2)), np.zeros(50)]
    assert mspd(R0, t0 + [5.0, 0, 0], R0, t0, K, flat, ident) == pytest.approx(600.0 * 5.0 / 500.0)


@settings(max_examples=25, deadline=None)
@given(
    rv=st.tuples(*[st.floats(-3, 3)] * 3),
    rv2=st.tuples(*[st.floats(-3, 3)] * 3),
    dt=st.tuples(*[st.floats(-30, 30)] * 3),
    k=st.integers(0, 3),
)
def test_mssd_invariant_to_symmetric_gt(rv, rv2, dt, k):
    """The box's symmetries form a group: replacing the GT by a symmetric equivalent changes nothing."""
    pts = box_points(n=3)
    syms = symmetry_transformations(BOX_INFO)
    R_g, t_g = Rotation.from_rotvec(rv).as_matrix(), np.array([0.0, 0.0, 700.0])
    R_e, t_e = Rotation.from_rotvec(rv2).as_matrix(), t_g + np.array(dt)
    S = syms[k]
    R_g2, t_g2 = R_g @ S["R"], R_g @ S["t"] + t_g
    a = mssd(R_e, t_e, R_g, t_g, pts, syms)
    b = mssd(R_e, t_e, R_g2, t_g2, pts, syms)
    assert a == pytest.approx(b, abs=1e-9)
    plain = np.linalg.norm(pts @ R_e.T + t_e - (pts @ R_g.T + t_g), axis=1).max()
    assert 0.0 <= a <= plain + 1e-9  # the identity is among the symmetries


def test_depth_to_distance_uses_integer_pixel_coordinates():
    depth = np.zeros((5, 7))
    depth[2, 3] = 100.0
    depth[0, 0] = 100.0
    Kc = np.array([[10.0, 0, 3.0], [0, 10.0, 2.0], [0, 0, 1]])
    d = depth_to_distance(depth, Kc)
    assert d[2, 3] == pytest.approx(100.0)  # (x, y) = (cx, cy): on the optical axis
    assert d[0, 0] == pytest.approx(100.0 * math.sqrt(1 + 0.3**2 + 0.2**2))
    assert d[1, 1] == 0.0


# ----------------------------------------------------------------------------- VSD
class PlateRenderer:
    """Analytic depth of a fronto-parallel square plate (side ``a`` mm) centred at t; rotation ignored
    except that it must be the identity. Pixel (i, j) is the ray through (i + 0.5, j + 0.5)."""

    def __init__(self, a=60.0, width=160, height=120):
        self.a, self.w, self.h = a, width, height

    def __call__(self, obj_id, R, t, K):
        assert np.allclose(R, np.eye(3))
        t = np.asarray(t, dtype=np.float64).reshape(3)
        u = (np.arange(self.w) + 0.5 - K[0, 2]) / K[0, 0] * t[2]
        v = (np.arange(self.h) + 0.5 - K[1, 2]) / K[1, 1] * t[2]
        inside = (np.abs(v[:, None] - t[1]) <= self.a / 2) & (np.abs(u[None, :] - t[0]) <= self.a / 2)
        return np.where(inside, t[2], 0.0).astype(np.float32)


KS = np.array([[300.0, 0, 80.0], [0, 300.0, 60.0], [0, 0, 1]])


def test_vsd_perfect_far_and_depth_shift():
    ren = PlateRenderer()
    I = np.eye(3)
    t = np.array([0.0, 0.0, 400.0])
    scene = ren(1, I, t, KS)
    diam = 100.0
    e = vsd(I, t, I, t, scene, KS, 15.0, VSD_TAUS, True, diam, ren, 1)
    assert e == [0.0] * 10
    far = vsd(I, t + [80.0, 0, 0], I, t, scene, KS, 15.0, VSD_TAUS, True, diam, ren, 1)
    assert far == [1.0] * 10
    # 10 mm further away: the distance differences are 0.1-0.102 x diameter, and the smaller
    # plate lies inside the GT one -> error 1 for tau <= 0.1, 1 - area_est / area_gt above
    sh = vsd(I, t + [0, 0, 10.0], I, t, scene, KS, 15.0, VSD_TAUS, True, diam, ren, 1)
    assert sh[0] == 1.0 and sh[1] == 1.0
    n_gt, n_est = (scene > 0).sum(), (ren(1, I, t + [0, 0, 10.0], KS) > 0).sum()
    assert 0 < n_est < n_gt
    for x in sh[2:]:
        assert x == pytest.approx(1 - n_est / n_gt, abs=1e-12)
    # 40 mm behind the scene surface (beyond delta) the estimate still counts as visible where the
    # GT is visible (the toolkit's visib_est rule): error 1 up to tau 0.4, then 1 - area ratio
    far_z = vsd(I, t + [0, 0, 40.0], I, t, scene, KS, 15.0, VSD_TAUS, True, diam, ren, 1)
    n_far = (ren(1, I, t + [0, 0, 40.0], KS) > 0).sum()
    assert far_z[:8] == [1.0] * 8
    assert far_z[8] == far_z[9] == pytest.approx(1 - n_far / n_gt, abs=1e-12)
    # shifted sideways by 20 mm (about 15 px): pixels outside the GT footprint are invisible
    # where the scene has depth in front of them; here the scene is empty there -> visible
    side = vsd(I, t + [20.0, 0, 0], I, t, scene, KS, 15.0, [0.5], True, diam, ren, 1)
    m_gt, m_est = scene > 0, ren(1, I, t + [20.0, 0, 0], KS) > 0
    assert side[0] == pytest.approx(1 - (m_gt & m_est).sum() / (m_gt | m_est).sum(), abs=1e-12)


def test_vsd_occlusion_and_missing_depth():
    ren = PlateRenderer()
    I = np.eye(3)
    t = np.array([0.0, 0.0, 400.0])
    scene = ren(1, I, t, KS).copy()
    scene[:, :80] = np.where(scene[:, :80] > 0, 300.0, scene[:, :80])  # occluder on the left half
    est = t + [0, 0, 10.0]
    e_occ = vsd(I, est, I, t, scene, KS, 15.0, [0.5], True, 100.0, ren, 1)
    # only the visible (right) half is compared
    cols = np.arange(160)[None, :] >= 80
    n_gt = ((ren(1, I, t, KS) > 0) & cols).sum()
    n_est = ((ren(1, I, est, KS) > 0) & cols).sum()
    assert e_occ[0] == pytest.approx(1 - n_est / n_gt, abs=1e-12)
    # pixels with no depth count as visible (BOP19): a hole in the scene changes nothing
    holed = ren(1, I, t, KS).copy()
    holed[50:70, 70:90] = 0.0
    assert vsd(I, t, I, t, holed, KS, 15.0, VSD_TAUS, True, 100.0, ren, 1) == [0.0] * 10
    with pytest.raises(ValueError, match="cost_type"):
        vsd(I, t, I, t, holed, KS, 15.0, VSD_TAUS, True, 100.0, ren, 1, cost_type="x")


# ----------------------------------------------------------------------------- AR
class Est:
    def __init__(self, obj_id, score, R, t, scene_id=1, im_id=0, time=0.5):
        self.scene_id, self.im_id, self.obj_id, self.score, self.R, self.t, self.time = (
            scene_id, im_id, obj_id, score, R, np.asarray(t, dtype=np.float64), time)


def _image(gts, targets, width=160, height=120, depth=None):
    return EvalImage(1, 0, KS, width, height, gts, targets, depth)


def test_ar_perfect_estimate_is_one_with_vsd():
    ren = PlateRenderer()
    I = np.eye(3)
    t = np.array([0.0, 0.0, 400.0])
    plate = np.array([[x, y, 0.0] for x in (-30, 30) for y in (-30, 30)])
    models = {1: make_object_model(1, {"diameter": 100.0}, plate)}
    img = _image([GroundTruth(1, I, t, 1.0)], {1: 1}, depth=ren(1, I, t, KS))
    s = evaluate_images([img], [Est(1, 0.9, I, t)], models, renderer=ren)
    assert s["vsd_available"] is True
    for k in ("bop19_average_recall", "bop19_average_recall_vsd", "bop19_average_recall_mssd",
              "bop19_average_recall_mspd"):
        assert s[k] == 1.0
    assert s["bop19_average_time_per_image"] == 0.5
    assert len(s["recalls"]["vsd"]) == 10 and len(s["recalls"]["vsd"][0]) == 10


def test_ar_symmetric_flip_is_correct_and_vsd_skipped_without_depth():
    R, t = pose()
    R_flip = R @ np.diag([1.0, -1.0, -1.0])
    sym = {1: make_object_model(1, BOX_INFO, box_points())}
    asym = {1: make_object_model(1, {"diameter": BOX_INFO["diameter"]}, box_points())}
    img = EvalImage(1, 0, K, 640, 480, [GroundTruth(1, R, t, 0.8)], {1: 1})
    s = evaluate_images([img], [Est(1, 1.0, R_flip, t)], sym)
    assert s["bop19_average_recall"] == 1.0
    assert s["vsd_available"] is False and s["bop19_average_recall_vsd"] is None and "note" in s
    s2 = evaluate_images([img], [Est(1, 1.0, R_flip, t)], asym)
    assert s2["bop19_average_recall_mssd"] == 0.0


def _shift(t, d):
    return t + np.array([d, 0.0, 0.0])


def test_ar_high_score_wrong_estimate_steals_top1():
    R, t = pose()
    models = {1: make_object_model(1, {"diameter": 100.0}, asym_points())}
    img = EvalImage(1, 0, K, 640, 480, [GroundTruth(1, R, t, 1.0)], {1: 1})
    good = Est(1, 1.0, R, t)
    wrong = Est(1, 2.0, R, _shift(t, 300.0))
    assert evaluate_images([img], [good], models)["bop19_average_recall"] == 1.0
    s = evaluate_images([img], [good, wrong], models)  # only the top-1 (wrong) estimate counts
    assert s["bop19_average_recall"] == 0.0 and s["counts"]["estimates_evaluated"] == 1


def test_ar_greedy_matching_order():
    """Two GTs 0.33 d apart (inst_count 2). est_a: 0.12 d from A (0.21 d from B); est_b: exactly A.

    est_a first: A taken by est_a for th >= 0.15; est_b reaches B only for th > 0.33 ->
    matches per th (0.05..0.5) = 1,1,1,1,1,1,2,2,2,2 -> recall 14/20.
    est_b first: est_b takes A; est_a reaches B for th > 0.21 -> 1,1,1,1,2,2,2,2,2,2 -> 16/20.
    """
    d = 100.0
    R, t = pose(t=(0.0, 0.0, 800.0))
    models = {1: make_object_model(1, {"diameter": d}, asym_points())}
    gts = [GroundTruth(1, R, t, 1.0), GroundTruth(1, R, _shift(t, 0.33 * d), 1.0)]
    img = EvalImage(1, 0, K, 640, 480, gts, {1: 2})
    est_a, est_b = Est(1, 0.9, R, _shift(t, 0.12 * d)), Est(1, 0.5, R, t)
    s = evaluate_images([img], [est_a, est_b], models)
    assert s["recalls"]["mssd"] == [0.5] * 6 + [1.0] * 4
    assert s["bop19_average_recall_mssd"] == pytest.approx(14 / 20)
    est_a.score, est_b.score = 0.5, 0.9
    s = evaluate_images([img], [est_a, est_b], models)
    assert s["recalls"]["mssd"] == [0.5] * 4 + [1.0] * 6
    assert s["bop19_average_recall_mssd"] == pytest.approx(16 / 20)
    # duplicates of one estimate match one GT only (B far away now)
    far = EvalImage(1, 0, K, 640, 480, [gts[0], GroundTruth(1, R, _shift(t, 3 * d), 1.0)], {1: 2})
    s = evaluate_images([far], [Est(1, 0.9, R, t), Est(1, 0.8, R, t)], models)
    assert s["recalls"]["mssd"] == [0.5] * 10


def test_ar_visibility_threshold_and_mspd_width_normalisation():
    R, t = pose(t=(0.0, 0.0, 1000.0))
    models = {1: make_object_model(1, {"diameter": 100.0}, asym_points())}
    gts = [GroundTruth(1, R, t, 0.09), GroundTruth(1, R, _shift(t, 300.0), 0.5)]
    img = EvalImage(1, 0, K, 640, 480, gts, {1: 1})
    s = evaluate_images([img], [Est(1, 1.0, R, t)], models)  # matches only the invisible GT
    assert s["counts"]["targets"] == 1 and s["bop19_average_recall"] == 0.0
    s = evaluate_images([img], [Est(1, 1.0, R, t)], models, visib_gt_min=0.05)
    assert s["counts"]["targets"] == 2 and s["bop19_average_recall_mssd"] == 0.5
    # the toolkit's newer rule (visib_gt_min < 0): the inst_count most visible GTs are valid
    s = evaluate_images([img], [Est(1, 1.0, R, _shift(t, 300.0))], models, visib_gt_min=-1)
    assert s["counts"]["targets"] == 1 and s["bop19_average_recall"] == 1.0
    # a 12-px shift everywhere: correct for MSPD thresholds > 12 at width 640, > 6 at width 1280
    dx = 12.0 * 1000.0 / 600.0
    one = [GroundTruth(1, R, t, 1.0)]
    e = [Est(1, 1.0, R, _shift(t, dx))]
    r640 = evaluate_images([EvalImage(1, 0, K, 640, 480, one, {1: 1})], e, models)["recalls"]["mspd"]
    r1280 = evaluate_images([EvalImage(1, 0, K, 1280, 960, one, {1: 1})], e, models)["recalls"]["mspd"]
    assert r640 == [0.0, 0.0] + [1.0] * 8
    assert r1280 == [0.0] + [1.0] * 9


def test_per_target_shares_average_to_ar_and_give_its_standard_error():
    """Greedy case above (14/20 and 16/20 MSSD) plus a second image with one far-off estimate:
    each target's share is the fraction of thresholds it is matched at (mean over MSSD, MSPD)."""
    d = 100.0
    R, t = pose(t=(0.0, 0.0, 800.0))
    models = {1: make_object_model(1, {"diameter": d}, asym_points())}
    gts = [GroundTruth(1, R, t, 1.0), GroundTruth(1, R, _shift(t, 0.33 * d), 1.0)]
    imgs = [EvalImage(1, 0, K, 640, 480, gts, {1: 2}), EvalImage(1, 1, K, 640, 480, [gts[0]], {1: 1})]
    ests = [Est(1, 0.9, R, _shift(t, 0.12 * d)), Est(1, 0.5, R, t)]
    far = Est(1, 1.0, R, _shift(t, 2 * d), im_id=1)
    s = evaluate_images(imgs, [*ests, far], models)
    shares = [r[4] for r in s["per_target"]]
    assert [r[:4] for r in s["per_target"]] == [[1, 0, 0, 1], [1, 0, 1, 1], [1, 1, 0, 1]]
    assert np.mean(shares) == pytest.approx(s["bop19_average_recall"])
    assert shares[0] == pytest.approx(1.0)  # A: matched at every MSSD and MSPD threshold
    # B: MSSD for th > 0.33 only (4 of 10); MSPD once est_b reaches it: 0.33 d at 800 mm is up to
    # 25.7 px for the model's nearest points, so from 30 px on (5 of 10)
    assert shares[1] == pytest.approx((4 / 10 + 5 / 10) / 2)
    assert shares[2] == 0.0
    assert s["average_recall_standard_error"] == pytest.approx(np.std(shares, ddof=1) / math.sqrt(3))
    # the same targets scored with the far estimate replaced by a perfect one: +1 on one target of 3
    good = Est(1, 1.0, R, t, im_id=1)
    s2 = evaluate_images(imgs, [*ests, good], models)
    diff, se, n = paired_difference(s, s2)
    assert n == 3 and diff == pytest.approx(1 / 3) and diff == pytest.approx(
        s2["bop19_average_recall"] - s["bop19_average_recall"])
    assert se == pytest.approx(np.std([0, 0, 1], ddof=1) / math.sqrt(3))
    assert paired_difference(s, s2, obj_ids=[1])[0] == pytest.approx(diff)
    with pytest.raises(ValueError, match="no targets"):
        paired_difference(s, s2, obj_ids=[2])
    one = evaluate_images(imgs[1:], [good], models)
    assert one["average_recall_standard_error"] is None  # one target


def test_threshold_grids_are_numpy_arange():
    assert VSD_THRESHOLDS[2] == 0.15000000000000002 and MSSD_THRESHOLDS[6] == 0.35000000000000003
    assert VSD_TAUS == VSD_THRESHOLDS and len(MSSD_THRESHOLDS) == 10
    assert MSPD_THRESHOLDS == (5.0, 10.0, 15.0, 20.0, 25.0, 30.0, 35.0, 40.0, 45.0, 50.0)


def test_average_time_per_image_rules():
    R, t = pose()
    assert average_time_per_image([Est(1, 1, R, t, im_id=0, time=1.0), Est(2, 1, R, t, im_id=1, time=3.0)]) == 2.0
    assert average_time_per_image([Est(1, 1, R, t, time=-1.0)]) == -1.0
    with pytest.raises(ValueError, match="running time"):
        average_time_per_image([Est(1, 1, R, t, time=1.0), Est(2, 1, R, t, time=2.0)])
