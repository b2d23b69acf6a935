"""Pose-error breakdown (sc6d_jax.metrics._breakdown): hand-made poses with known errors, symmetric
objects, misses, the summary, the scores of evaluate_images and ``sc6d eval`` end to end."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from sc6d_jax.metrics import (
    MISS,
    EvalImage,
    GroundTruth,
    breakdown_errors,
    evaluate_images,
    format_breakdown_line,
    make_object_model,
    pose_errors,
    rotation_error_deg,
    summarize_breakdown,
    symmetry_rotations,
)

K = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
BOX_INFO = {  # 180-degree symmetries about x, y, z
    "diameter": 108.0,
    "symmetries_discrete": [
        [1, 0, 0, 0, 0, -1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1],
        [-1, 0, 0, 0, 0, 1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1],
        [-1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1],
    ],
}
CYL_INFO = {"diameter": 116.6, "symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}]}


def rot(axis: str, deg: float) -> np.ndarray:
    return Rotation.from_euler(axis, deg, degrees=True).as_matrix()


R_GT = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()
T_GT = np.array([10.0, -20.0, 600.0])


# ----------------------------------------------------------------------------- rotation
@pytest.mark.parametrize("axis,deg", [("x", 30.0), ("y", 5.0), ("z", 179.0), ("x", 1e-5), ("y", 180.0)])
def test_rotation_error_known_angle(axis, deg):
    assert rotation_error_deg(R_GT @ rot(axis, deg), R_GT) == pytest.approx(deg, abs=1e-7)
    assert rotation_error_deg(R_GT, R_GT) == 0.0
    # the error is about the object's own axes: right-multiplied like R_gt @ R_s, and symmetric
    assert rotation_error_deg(R_GT, R_GT @ rot(axis, deg), None) == pytest.approx(deg, abs=1e-7)


def test_rotation_error_continuous_symmetry_within_the_step():
    Rs = symmetry_rotations(CYL_INFO, 0.01)
    n = int(np.ceil(np.pi / 0.01))
    assert Rs.shape == (n, 3, 3)
    step = 360.0 / n
    for a in (37.3, 90.0, 200.0, 359.0):
        e = rotation_error_deg(R_GT @ rot("z", a), R_GT, Rs)
        assert e <= step / 2 + 1e-9
        assert rotation_error_deg(R_GT @ rot("z", a), R_GT) == pytest.approx(min(a, 360 - a), abs=1e-7)
    # a tilt of the axis is not hidden by the symmetry: 20 deg about x after any spin about z
    assert rotation_error_deg(R_GT @ rot("z", 123.0) @ rot("x", 20.0), R_GT, Rs) == pytest.approx(20.0, abs=step)


def test_rotation_error_discrete_180_symmetry():
    Rs = symmetry_rotations(BOX_INFO)
    assert Rs.shape == (4, 3, 3)
    for axis in "xyz":
        assert rotation_error_deg(R_GT @ rot(axis, 180.0), R_GT, Rs) == pytest.approx(0.0, abs=1e-6)
        assert rotation_error_deg(R_GT @ rot(axis, 180.0), R_GT) == pytest.approx(180.0, abs=1e-6)
    # 170 deg about z is 10 deg from the z flip
    assert rotation_error_deg(R_GT @ rot("z", 170.0), R_GT, Rs) == pytest.approx(10.0, abs=1e-7)
    # a 90-degree turn about z is not a symmetry of the box
    assert rotation_error_deg(R_GT @ rot("z", 90.0), R_GT, Rs) == pytest.approx(90.0, abs=1e-7)


def test_rotation_error_rejects_bad_input():
    with pytest.raises(ValueError, match="R_est"):
        rotation_error_deg(np.eye(2), R_GT)
    with pytest.raises(ValueError, match="R_gt must be finite"):
        rotation_error_deg(R_GT, np.full((3, 3), np.nan))
    with pytest.raises(ValueError, match="sym_rotations"):
        rotation_error_deg(R_GT, R_GT, np.zeros((0, 3, 3)))
    with pytest.raises(ValueError, match="sym_rotations"):
        rotation_error_deg(R_GT, R_GT, np.zeros((2, 3)))


# ----------------------------------------------------------------------------- pose errors
def test_pose_errors_depth_and_centre():
    e = pose_errors(R_GT, T_GT * np.array([1.0, 1.0, 1.05]), R_GT, T_GT, K)
    assert e["rot_deg"] == 0.0
    assert e["depth_rel"] == pytest.approx(0.05, abs=1e-12)
    # the centre moves towards the principal point: (u - cx) scales by 1/1.05
    u, v = 600.0 * 10.0 / 600.0, 600.0 * -20.0 / 600.0
    assert e["centre_px"] == pytest.approx(math.hypot(u, v) * (1 - 1 / 1.05), abs=1e-9)
    # a fronto-parallel shift of 6 mm at 600 mm with f = 600 is 6 px; 8 mm down -> 10 px in all
    e = pose_errors(R_GT, T_GT + [6.0, 8.0, 0.0], R_GT, T_GT, K)
    assert e["centre_px"] == pytest.approx(10.0, abs=1e-9) and e["depth_rel"] == 0.0
    assert pose_errors(R_GT @ rot("x", 30.0), T_GT, R_GT, T_GT, K)["rot_deg"] == pytest.approx(30.0, abs=1e-9)
    # an estimate behind the camera has no projected centre
    assert pose_errors(R_GT, [0.0, 0.0, -5.0], R_GT, T_GT, K)["centre_px"] == math.inf
    # the signed depth error (too near is negative) and the angle of the ground truth's ray
    e = pose_errors(R_GT, T_GT * np.array([1.0, 1.0, 0.97]), R_GT, T_GT, K)
    assert e["depth_signed"] == pytest.approx(-0.03, abs=1e-12) and e["depth_rel"] == pytest.approx(0.03, abs=1e-12)
    assert e["ray_deg"] == pytest.approx(math.degrees(math.atan(math.hypot(*T_GT[:2]) / T_GT[2])), abs=1e-9)
    assert pose_errors(R_GT, [0, 0, 500.0], R_GT, [0, 0, 400.0], K)["ray_deg"] == 0.0
    assert pose_errors(R_GT, T_GT, R_GT, [400.0, 0.0, 400.0], K)["ray_deg"] == pytest.approx(45.0)
    with pytest.raises(ValueError, match="t_gt_z > 0"):
        pose_errors(R_GT, T_GT, R_GT, [0.0, 0.0, 0.0], K)
    with pytest.raises(ValueError, match="t_est"):
        pose_errors(R_GT, [1.0, 2.0], R_GT, T_GT, K)
    with pytest.raises(ValueError, match="K"):
        pose_errors(R_GT, T_GT, R_GT, T_GT, np.eye(2))


# ----------------------------------------------------------------------------- pairing
class Est:
    def __init__(self, obj_id, score, R, t, scene_id=1, im_id=0):
        self.scene_id, self.im_id, self.obj_id, self.score, self.R, self.t = (
            scene_id, im_id, obj_id, score, np.asarray(R), np.asarray(t, dtype=np.float64))


def _models():
    pts = np.random.default_rng(0).uniform(-40, 40, (100, 3))
    return {1: make_object_model(1, {"diameter": 100.0}, pts), 2: make_object_model(2, CYL_INFO, pts)}


def test_breakdown_errors_pairing_and_misses():
    t2 = T_GT + [200.0, 0.0, 0.0]
    gts = [GroundTruth(1, R_GT, T_GT, 1.0), GroundTruth(1, R_GT, t2, 1.0),
           GroundTruth(2, R_GT, T_GT + [0, 150.0, 0], 0.5),
           GroundTruth(1, R_GT, T_GT + [0, -150.0, 0], 0.05)]  # too occluded: not a target
    img = EvalImage(1, 0, K, 640, 480, gts, {1: 2, 2: 1})
    ests = [
        Est(1, 0.9, R_GT @ rot("x", 30.0), t2 + [0, 0, 6.0]),  # best score: takes GT 1 (nearest)
        Est(1, 0.8, R_GT, T_GT * [1, 1, 1.05]),  # then GT 0
        Est(1, 0.1, R_GT, T_GT),  # beyond inst_count 2: ignored
    ]
    recs = breakdown_errors([img], ests, _models())
    assert [(r["obj_id"], r["gt_id"]) for r in recs] == [(1, 0), (1, 1), (2, 2)]
    r0, r1, r2 = recs
    assert [r["visib_fract"] for r in recs] == [1.0, 1.0, 0.5]
    assert r1["est_id"] == 0 and r1["rot_deg"] == pytest.approx(30.0) and r1["depth_rel"] == pytest.approx(0.01)
    assert r0["est_id"] == 1 and r0["rot_deg"] == 0.0 and r0["depth_rel"] == pytest.approx(0.05)
    # object 2 has no estimate: a miss
    assert r2["missed"] and r2["est_id"] is None and r2["score"] is None
    assert (r2["rot_deg"], r2["depth_rel"], r2["centre_px"]) == (180.0, math.inf, math.inf) == tuple(MISS.values())
    # one estimate for two GTs: the nearer is paired, the other is a miss
    recs = breakdown_errors([img], [Est(1, 0.5, R_GT, t2)], _models())
    assert [r["missed"] for r in recs] == [True, False, True]


def test_evaluate_images_adds_breakdown_and_keeps_bop19_keys():
    img = EvalImage(1, 0, K, 640, 480, [GroundTruth(2, R_GT, T_GT, 1.0)], {2: 1})
    models = _models()
    est = [Est(2, 1.0, R_GT @ rot("z", 77.0), T_GT)]  # spun about the cylinder axis: correct
    s = evaluate_images([img], est, models)
    assert s["bop19_average_recall"] == 1.0
    b = s["breakdown"]
    assert b["overall"]["n"] == 1 and b["overall"]["rot_median_deg"] <= 0.5 * 360.0 / 315 + 1e-9  # half a step
    assert b["overall"]["rot_under_5"] == 1.0 and list(b["per_object"]) == [2]
    s_no = evaluate_images([img], [], models)
    assert s_no["breakdown"]["overall"]["missed"] == 1 and s_no["breakdown"]["overall"]["rot_median_deg"] == 180.0


# ----------------------------------------------------------------------------- summary
def test_summarize_breakdown_medians_and_fractions():
    per = [
        {"obj_id": 1, "rot_deg": 3.0, "depth_rel": 0.01, "centre_px": 1.0},
        {"obj_id": 1, "rot_deg": 8.0, "depth_rel": 0.03, "centre_px": 2.0},
        {"obj_id": 1, "rot_deg": 15.0, "depth_rel": 0.10, "centre_px": 5.0},
        {"obj_id": 2, "rot_deg": 4.0, "depth_rel": 0.02, "centre_px": 3.0},
        {"obj_id": 2, "missed": True, **MISS},
    ]
    s = summarize_breakdown(per)
    o = s["overall"]
    assert o["n"] == 5 and o["missed"] == 1
    assert o["rot_median_deg"] == 8.0 and o["depth_rel_median"] == 0.03 and o["centre_median_px"] == 3.0
    assert o["rot_under_5"] == pytest.approx(2 / 5) and o["rot_under_10"] == pytest.approx(3 / 5)
    assert o["rot_under_20"] == pytest.approx(4 / 5)
    assert o["rot_over_90"] == pytest.approx(1 / 5)  # the miss counts as 180 degrees
    assert o["depth_under_2pct"] == pytest.approx(1 / 5)  # 0.02 is not strictly below 2 %
    assert o["depth_under_5pct"] == pytest.approx(3 / 5)
    assert list(s["per_object"]) == [1, 2]
    p1, p2 = s["per_object"][1], s["per_object"][2]
    assert p1["n"] == 3 and p1["rot_median_deg"] == 8.0 and p1["missed"] == 0
    assert p2["rot_median_deg"] == 92.0 and p2["depth_rel_median"] == math.inf  # half missed
    assert p1["rot_over_90"] == 0.0 and p2["rot_over_90"] == 0.5
    assert set(o) == set(p1) >= {"n", "rot_median_deg", "depth_rel_median", "centre_median_px", "rot_under_5",
                                  "rot_under_10", "rot_under_20", "rot_over_90", "depth_under_2pct",
                                  "depth_under_5pct"}
    empty = summarize_breakdown([])
    assert empty["overall"]["n"] == 0 and empty["overall"]["rot_median_deg"] is None and empty["per_object"] == {}
    line = format_breakdown_line(o)
    assert "rotation median 8.0 deg" in line and "depth median 3.0 %" in line and "40/60/80 %" in line
    assert "per_visibility" not in s  # no visible fractions given
    # grouped by visible fraction when every target has one: only the groups that hold targets
    vis = [0.3, 0.97, 1.0, 0.6, 0.96]
    sv = summarize_breakdown([{**d, "visib_fract": v} for d, v in zip(per, vis)])
    assert list(sv["per_visibility"]) == ["<50%", "50-80%", ">=95%"]
    assert [sv["per_visibility"][k]["n"] for k in sv["per_visibility"]] == [1, 1, 3]
    hi = sv["per_visibility"][">=95%"]
    assert hi["rot_median_deg"] == 15.0 and hi["missed"] == 1 and sv["per_visibility"]["<50%"]["rot_median_deg"] == 3.0
    assert sv["overall"] == o and sv["per_object"] == s["per_object"]
    with pytest.raises(ValueError, match="visib_fract"):
        summarize_breakdown([{**per[0], "visib_fract": 1.5}])
    assert o["depth_bias_median"] is None  # no signed errors given
    # the signed depth error's median over the estimated targets (misses have none), and the
    # groups by ray angle when every target has one
    signed = [0.01, -0.03, 0.10, -0.02, None]
    rays = [3.0, 12.0, 25.0, 19.9, 31.0]
    sr = summarize_breakdown([{**d, "depth_signed": g, "ray_deg": r} for d, g, r in zip(per, signed, rays)])
    assert sr["overall"]["depth_bias_median"] == pytest.approx(-0.005)
    assert sr["per_object"][2]["depth_bias_median"] == pytest.approx(-0.02)
    assert list(sr["per_ray_angle"]) == ["<10deg", "10-20deg", ">=20deg"]
    assert [sr["per_ray_angle"][k]["n"] for k in sr["per_ray_angle"]] == [1, 2, 2]
    far = sr["per_ray_angle"][">=20deg"]
    assert far["missed"] == 1 and far["depth_bias_median"] == pytest.approx(0.10)
    assert sr["per_ray_angle"]["10-20deg"]["depth_bias_median"] == pytest.approx(-0.025)
    assert "per_ray_angle" not in summarize_breakdown([{**per[0], "ray_deg": 3.0}, per[1]])  # not every target
    with pytest.raises(ValueError, match="ray_deg"):
        summarize_breakdown([{**per[0], "ray_deg": -1.0}])
    # and by the extent across the view when every target has one
    se = summarize_breakdown([{**d, "depth_signed": g, "extent": e}
                              for d, g, e in zip(per, signed, [0.5, 0.8, 0.95, 1.0, 0.74])])
    assert list(se["per_extent"]) == ["<0.75", "0.75-0.9", ">=0.9"]
    assert [se["per_extent"][k]["n"] for k in se["per_extent"]] == [2, 1, 2]
    assert se["per_extent"][">=0.9"]["depth_bias_median"] == pytest.approx(0.04)
    with pytest.raises(ValueError, match="extent"):
        summarize_breakdown([{**per[0], "extent": 0.0}])
    with pytest.raises(ValueError, match=r"per_target\[0\] has no 'centre_px'"):
        summarize_breakdown([{"obj_id": 1, "rot_deg": 1.0, "depth_rel": 0.1}])
    with pytest.raises(ValueError, match="non-negative"):
        summarize_breakdown([{"obj_id": 1, "rot_deg": float("nan"), "depth_rel": 0.1, "centre_px": 1.0}])


def test_extent_ratio_of_a_rod_across_and_along_the_view():
    """A 100 x 10 x 10 mm rod 1 m away (f = 500): across the view its box spans its length
    (ratio ~ 100 / diameter, a little more for the perspective of its near corners); end-on
    only its near end's 10 mm, enlarged by being 5 cm nearer."""
    from sc6d_jax.metrics._breakdown import extent_ratio

    pts = np.array([[x, y, z] for x in (-50, 50) for y in (-5, 5) for z in (-5, 5)], float)
    d = float(np.sqrt(100**2 + 10**2 + 10**2))
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    t = np.array([0.0, 0.0, 1000.0])
    across = extent_ratio(pts, np.eye(3), t, K, d)
    assert across == pytest.approx(2 * 50 * 1000 / 995 / d, rel=1e-9)
    end_on = extent_ratio(pts, rot("y", 90.0), t, K, d)
    assert end_on == pytest.approx(2 * 5 * 1000 / 950 / d, rel=1e-9)
    with pytest.raises(ValueError, match="in front"):
        extent_ratio(pts, np.eye(3), np.array([0.0, 0.0, 3.0]), K, d)


# ----------------------------------------------------------------------------- sc6d eval
def test_eval_cli_breakdown_on_a_rendered_dataset(models, gt_estimates, tmp_path, capsys):
    """A tiny rendered dataset, the ground truth as estimates with known perturbations: per image
    x 1.06 in depth for the first target, 30 deg about x for the second (at least 30 deg for every
    built-in object: no symmetry of theirs is closer), the rest exact, and one target left without
    an estimate."""
    from sc6d_jax.bop import BopDataset, write_results_csv
    from sc6d_jax.metrics.cli import main
    from sc6d_jax.render._dataset import DatasetSpec, render_dataset

    root = render_dataset(models, tmp_path / "ds", DatasetSpec(scenes=1, images_per_scene=2, objects_per_image=4,
                                                               width=160, height=120, seed=5), progress=False)
    ds = BopDataset(root)
    dropped = []

    def change(k, g):
        if k == 0:
            return g.R, g.t * np.array([1.0, 1.0, 1.06])
        if k == 1:
            return g.R @ rot("x", 30.0), g.t
        if not dropped:
            dropped.append(g.obj_id)
            return None
        return g.R, g.t

    ests, ks = gt_estimates(ds, change)
    n, n_depth, n_rot, dropped = len(ests) + 1, ks.count(0), ks.count(1), dropped[0] if dropped else None
    assert n >= 6 and dropped is not None and n_rot >= 1
    csv = write_results_csv(tmp_path / "gt_ds-test.csv", ests)
    out = tmp_path / "scores.json"
    assert main(["--dataset", str(root), "--results", str(csv), "--out", str(out), "--no-vsd", "--no-progress"]) == 0
    s = json.loads(out.read_text())
    b = s["breakdown"]["overall"]
    assert b["n"] == n == s["counts"]["targets"] and b["missed"] == 1
    assert b["rot_median_deg"] < 1e-3 and b["centre_median_px"] < 1e-3
    assert b["rot_under_5"] == b["rot_under_20"] == pytest.approx((n - n_rot - 1) / n)
    assert b["depth_under_5pct"] == pytest.approx((n - n_depth - 1) / n)
    assert set(s["breakdown"]["per_object"]) == set(s["per_object"])
    missed = s["breakdown"]["per_object"][str(dropped)]
    assert missed["missed"] == 1
    if missed["n"] == 1:
        assert missed["depth_rel_median"] is None  # inf is written as null
    # grouped by the targets' visible fractions (scene_gt_info), which account for every target
    pv = s["breakdown"]["per_visibility"]
    assert set(pv) <= {"<50%", "50-80%", "80-95%", ">=95%"} and sum(d["n"] for d in pv.values()) == n
    # and by the angle of their rays; the depth bias is the +6 % of the first targets or 0
    pr = s["breakdown"]["per_ray_angle"]
    assert set(pr) <= {"<10deg", "10-20deg", ">=20deg"} and sum(d["n"] for d in pr.values()) == n
    assert b["depth_bias_median"] == pytest.approx(0.0, abs=1e-6)
    first = [d["depth_bias_median"] for d in s["breakdown"]["per_object"].values()]
    assert all(v is None or v == pytest.approx(0.0, abs=1e-6) or v == pytest.approx(0.06, abs=1e-6) or
               0.0 < v < 0.06 for v in first)
    pe = s["breakdown"]["per_extent"]
    assert set(pe) <= {"<0.75", "0.75-0.9", ">=0.9"} and sum(d["n"] for d in pe.values()) == n
    printed = capsys.readouterr().out
    assert "pose-error breakdown" in printed and "rot_med" in printed and "bias" in printed
    assert "by visible fraction of the target:" in printed
    assert "by angle of the target's ray from the optical axis:" in printed
    assert "by the target's extent across the view" in printed
    # --oracle: parts of every pose from the ground truth; the other parts' errors stay (the
    # first target's 6 % in depth goes with "depth", stays with "centre")
    for part, rot_ok, depth_ok in (("rotation", n - 1, n - n_depth - 1), ("translation", n - n_rot - 1, n - 1),
                                   ("depth", n - n_rot - 1, n - 1), ("centre", n - n_rot - 1, n - n_depth - 1),
                                   ("depth,rotation", n - 1, n - 1)):
        o = tmp_path / f"oracle_{part}.json"
        assert main(["--dataset", str(root), "--results", str(csv), "--out", str(o), "--no-vsd", "--no-progress",
                     "--oracle", part]) == 0
        so = json.loads(o.read_text())
        assert so["oracle"] == ("rotation,depth" if part == "depth,rotation" else part)
        bo = so["breakdown"]["overall"]
        assert bo["missed"] == 1  # a missing estimate is not made up
        assert bo["rot_under_5"] == pytest.approx(rot_ok / n)
        assert bo["depth_under_2pct"] == pytest.approx(depth_ok / n)
    printed = capsys.readouterr().out
    assert "oracle: every estimate's translation taken from the ground truth (the AR measures the rotation" in printed
    assert "every estimate's centre taken from the ground truth (the AR measures the rotation and the depth" in printed
    assert "every estimate's rotation and depth taken from the ground truth (the AR measures the centre" in printed
    with pytest.raises(ValueError, match="oracle part must be one of"):
        main(["--dataset", str(root), "--results", str(csv), "--out", str(tmp_path / "x.json"), "--oracle", "scale"])
    with pytest.raises(ValueError, match="--oracle and --figures do not go together"):
        main(["--dataset", str(root), "--results", str(csv), "--out", str(tmp_path / "x.json"), "--oracle", "rotation",
              "--figures", str(tmp_path / "f")])
    from sc6d_jax.metrics import with_ground_truth

    with pytest.raises(ValueError, match="oracle part must be one of"):
        with_ground_truth(ds, ests, "scale")
    # depth and centre split the translation as the network predicts it: the distance along the
    # estimate's ray, and the ray (projected centre) at the estimate's distance
    off = [dataclasses.replace(e, t=e.t * np.array([1.03, 0.97, 1.1]) + np.array([5.0, -4.0, 0.0])) for e in ests]
    gt = with_ground_truth(ds, off, "translation")
    for part in ("depth", "centre"):
        for e, o, g in zip(off, with_ground_truth(ds, off, part), gt):
            assert np.array_equal(o.R, e.R)
            ray, z = (e, g) if part == "depth" else (g, e)
            np.testing.assert_allclose(o.t[:2] / o.t[2], ray.t[:2] / ray.t[2], rtol=1e-12)
            assert o.t[2] == pytest.approx(z.t[2], rel=1e-12)
    for o, g in zip(with_ground_truth(ds, off, ["centre", "depth"]), gt):
        np.testing.assert_allclose(o.t, g.t, rtol=1e-12)
