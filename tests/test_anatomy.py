"""experiments/error_anatomy.py: the error axis of known rotations, per-object rows of hand-made
estimates, and the command on a real checkpoint, rendered crops and bad input."""

from __future__ import annotations

import csv
import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "experiments"))

import error_anatomy  # noqa: E402


def _rot(axis, deg):
    from scipy.spatial.transform import Rotation

    a = np.asarray(axis, float)
    return Rotation.from_rotvec(np.radians(deg) * a / np.linalg.norm(a)).as_matrix()


@pytest.mark.parametrize("axis,deg", [((1, 0, 0), 180.0), ((0, 0, 1), 90.0), ((0, 1, 1), 120.0), ((1, 2, 0), 179.9)])
def test_error_axis_of_known_rotations(axis, deg):
    R_gt = _rot((0.3, -0.2, 0.9), 70.0)
    R_est = R_gt @ _rot(axis, deg).T  # R_est^T R_gt = the turn about `axis` in the object's frame
    ang, ax = error_anatomy.error_axis(R_est, R_gt)
    want = np.abs(np.asarray(axis, float)) / np.linalg.norm(axis)
    assert ang == pytest.approx(deg, abs=1e-3)
    assert np.allclose(ax, want, atol=1e-3)


def test_error_axis_takes_the_closest_symmetric_pose():
    R_gt = _rot((1, 1, 0), 40.0)
    flip_z = _rot((0, 0, 1), 180.0)
    R_est = R_gt @ flip_z @ _rot((1, 0, 0), 30.0).T  # 30 degrees about x away from the symmetric pose
    syms = np.stack([np.eye(3), flip_z])
    ang, ax = error_anatomy.error_axis(R_est, R_gt, syms)
    assert ang == pytest.approx(30.0, abs=1e-3) and np.allclose(ax, [1, 0, 0], atol=1e-3)
    assert error_anatomy.error_axis(R_est, R_gt)[0] > 150  # without the symmetry: a half turn off


def test_anatomy_rows_of_hand_made_estimates():
    """Object 7: every estimate a half turn about its x axis, 5 % too far; object 9: exact."""
    rng = np.random.default_rng(0)
    n = 6
    R = np.stack([_rot(rng.normal(size=3), rng.uniform(10, 170)) for _ in range(2 * n)])
    t = np.tile([10.0, -20.0, 800.0], (2 * n, 1))
    K = np.tile(np.array([[600.0, 0, 320], [0, 600, 240], [0, 0, 1]]), (2 * n, 1, 1))
    oid = np.array([7] * n + [9] * n)
    R_est, t_est = R.copy(), t.copy()
    R_est[:n] = R[:n] @ _rot((1, 0, 0), 180.0).T
    t_est[:n, 2] *= 1.05
    eye = np.eye(3)[None]
    rows = error_anatomy.anatomy_rows("full", {"R": R_est, "t": t_est},
                                      {"R": R, "t": t, "K": K, "obj_id": oid}, {7: eye, 9: eye})
    a, b = rows
    assert (a["obj_id"], a["n"], b["obj_id"], b["n"]) == (7, n, 9, n)
    assert a["rot_median_deg"] == pytest.approx(180.0, abs=1e-3) and a["rot_over_90"] == 1.0
    assert (a["axis_x"], a["axis_y"], a["axis_z"]) == pytest.approx((1.0, 0.0, 0.0), abs=1e-3)
    assert a["depth_rel_median"] == pytest.approx(0.05) and a["depth_signed_median"] == pytest.approx(0.05)
    assert b["rot_median_deg"] == pytest.approx(0.0, abs=1e-3) and b["rot_over_90"] == 0.0
    assert b["depth_rel_median"] == 0.0 and np.isnan(b["axis_x"])


def _untrained_run(tmp_path: Path) -> Path:
    """A run folder with one checkpoint (step 5) of fresh tiny-preset parameters for objects 1 and 2."""
    from sc6d_jax.model import init
    from sc6d_jax.train import StreamSettings, preset, save_checkpoint

    cfg = preset("tiny")
    cfg = cfg.replace(model=dataclasses.replace(cfg.model, n_objects=2), stream=StreamSettings(batch_size=8, obj_ids=(1, 2)),
                      z_range=(300.0, 3000.0))
    run = tmp_path / "run"
    save_checkpoint(run, 5, init(jax.random.PRNGKey(0), cfg.model), {}, np.zeros(2, np.uint32), cfg.to_dict(),
                    extra_meta={"models_dir": None})
    (run / "config.json").write_text(json.dumps(cfg.to_dict()))
    return run


def test_command_on_a_checkpoint_writes_tables_and_a_figure(models, tmp_path):
    run = _untrained_run(tmp_path)
    out = tmp_path / "anatomy"
    res = subprocess.run([sys.executable, str(REPO / "experiments" / "error_anatomy.py"), "--run", str(run),
                          "--models", str(models), "--out", str(out), "--crops", "12", "--lib", "600"],
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stdout + res.stderr
    with open(out / "anatomy.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert {(r["difficulty"], r["obj_id"]) for r in rows} <= {(d, o) for d in error_anatomy.DIFFICULTIES for o in ("1", "2")}
    assert {r["difficulty"] for r in rows} == set(error_anatomy.DIFFICULTIES)
    for d in error_anatomy.DIFFICULTIES:
        assert sum(int(r["n"]) for r in rows if r["difficulty"] == d) == 12
    assert all(0.0 <= float(r["rot_median_deg"]) <= 180.0 for r in rows)
    assert (out / "anatomy.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "plain: AR" in res.stdout
    assert json.loads((out / "anatomy.json").read_text())["step"] == 5  # the checkpoint's, not None

    bad = subprocess.run([sys.executable, str(REPO / "experiments" / "error_anatomy.py"), "--run", str(run),
                          "--models", str(tmp_path), "--out", str(tmp_path / "x")], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "models_info.json" in bad.stderr and not (tmp_path / "x").exists()


# ----------------------------------------------------------------------------- ring_profile.py
import ring_profile  # noqa: E402


def test_ring_rows_of_hand_made_profiles():
    """Object 3 about z: an encoder that gives the ring one embedding and crops whose scores peak a
    half turn away; about x: peaks at the ground truth, a drop of 5 logits."""
    theta = np.arange(0.0, 360.0, 5.0)
    n = 4
    peak = lambda c: np.tile(-np.abs((theta - c + 180.0) % 360.0 - 180.0) / 36.0, (n, 1))  # noqa: E731
    profiles = {(3, "z"): {"theta": theta, "enc_cos": np.ones_like(theta), "score": peak(180.0)},
                (3, "x"): {"theta": theta, "enc_cos": np.cos(np.radians(theta)), "score": peak(0.0)}}
    z, x = ring_profile.ring_rows(profiles)
    assert (z["obj_id"], z["axis"], z["n"], x["axis"]) == (3, "z", n, "x")
    assert z["enc_min_cos"] == 1.0 and (z["at_gt"], z["at_90"], z["at_180"], z["at_270"]) == (0.0, 0.0, 1.0, 0.0)
    assert z["score_range"] == pytest.approx(0.0)  # the ground truth is the worst of its ring
    assert x["enc_min_cos"] == pytest.approx(-1.0) and x["at_gt"] == 1.0 and x["at_180"] == 0.0
    assert x["score_range"] == pytest.approx(5.0)


def test_ring_profile_command_on_a_checkpoint(models, tmp_path):
    run = _untrained_run(tmp_path)
    out = tmp_path / "rings"
    assert ring_profile.main(["--run", str(run), "--models", str(models), "--out", str(out), "--crops", "10",
                              "--gallery", "13"]) == 0
    assert (out / "turns.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with open(out / "rings.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    objs = sorted({r["obj_id"] for r in rows})
    assert set(objs) <= {"1", "2"} and [r["axis"] for r in rows] == ["x", "y", "z"] * len(objs)
    assert sum(int(r["n"]) for r in rows if r["axis"] == "x") == 10
    for r in rows:
        assert -1.0 <= float(r["enc_min_cos"]) <= 1.0 and float(r["score_range"]) >= 0.0  # the best is at least g.t.
        assert float(r["at_gt"]) + float(r["at_180"]) <= 1.0
    assert (out / "rings.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert json.loads((out / "rings.json").read_text())["step"] == 5
    assert ring_profile.main(["--run", str(run), "--models", str(tmp_path), "--out", str(tmp_path / "x")]) == 2
    assert not (tmp_path / "x").exists()
