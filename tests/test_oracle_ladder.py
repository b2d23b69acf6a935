"""``experiments/oracle_ladder.py``: a results CSV scored with parts of its poses from the ground
truth, or its depth error shrunk, on a dataset rendered for real, with known perturbations."""

from __future__ import annotations

import csv
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "experiments"))

import oracle_ladder as ol  # noqa: E402


@pytest.fixture(scope="module")
def perturbed(models, gt_estimates, tmp_path_factory):
    """A tiny rendered dataset and the ground truth as estimates: the first target of each image
    6 % too far along its own ray (its projected centre exact), the second turned 30 deg about x,
    the rest exact."""
    from sc6d_jax.bop import BopDataset, write_results_csv
    from sc6d_jax.render._dataset import DatasetSpec, render_dataset

    tmp = tmp_path_factory.mktemp("ladder")
    root = render_dataset(models, tmp / "ds", DatasetSpec(scenes=1, images_per_scene=2, objects_per_image=4,
                                                          width=160, height=120, seed=7), progress=False)
    ds = BopDataset(root)
    turn = Rotation.from_euler("x", 30.0, degrees=True).as_matrix()
    ests, kinds = gt_estimates(ds, lambda k, g: (g.R @ turn if k == 1 else g.R, g.t * (1.06 if k == 0 else 1.0)))
    assert kinds.count(0) >= 1 and kinds.count(1) >= 1 and len(kinds) >= 5
    return root, write_results_csv(tmp / "gt_ds-test.csv", ests), ests, kinds


def test_shrink_depth_error_moves_each_estimate_along_its_ray(perturbed):
    from sc6d_jax.bop import BopDataset
    from sc6d_jax.metrics import with_ground_truth

    root, _, ests, _ = perturbed
    ds = BopDataset(root)
    true = with_ground_truth(ds, ests, "depth")
    for a in (0.0, 0.5, 1.0):
        for e, g, s in zip(ests, true, ol.shrink_depth_error(ests, true, a)):
            assert s.t[2] / g.t[2] == pytest.approx((e.t[2] / g.t[2]) ** a, rel=1e-12)
            np.testing.assert_allclose(s.t[:2] / s.t[2], e.t[:2] / e.t[2], rtol=1e-12)
    with pytest.raises(ValueError, match="exponent"):
        ol.shrink_depth_error(ests, true, 1.5)


def test_ladder_command_scores_every_rung(perturbed, tmp_path, capsys):
    root, results, ests, kinds = perturbed
    turned = ",".join(str(i) for i in sorted({e.obj_id for e, k in zip(ests, kinds) if k == 1}))
    out = tmp_path / "ladder"
    assert ol.main(["--dataset", str(root), "--results", str(results), "--out", str(out), "--no-vsd",
                    "--rotation-objects", turned]) == 0
    rows = {r["rung"]: r for r in csv.DictReader((out / "oracle_ladder.csv").open())}
    names = [r for r, _ in ol.RUNGS]
    assert list(rows) == names[:2] + [f"rotation@{turned}"] + names[2:]
    # the turned targets' objects alone from the ground truth: every turn undone, as "rotation"
    only = {k: v for k, v in rows[f"rotation@{turned}"].items() if k not in ("rung", "what")}
    assert only == {k: v for k, v in rows["rotation"].items() if k not in ("rung", "what")}
    ar = {k: float(r["ar"]) for k, r in rows.items()}
    depth = {k: float(r["depth_rel_median"]) for k, r in rows.items()}
    # the perturbations cost AR; each is undone by its own oracle, both together by the ladder's top
    assert ar["as_estimated"] < 1.0
    assert ar["rotation,depth"] == 1.0 and ar["translation"] < 1.0 and ar["depth"] < 1.0 and ar["rotation"] < 1.0
    assert ar["centre"] == ar["as_estimated"]  # every centre was exact already
    assert ar["rotation"] <= ar["rotation,depth/2"] <= ar["rotation,depth/4"] <= ar["rotation,depth"]
    assert float(rows["rotation"]["rot_median_deg"]) == pytest.approx(0.0, abs=1e-6)
    assert float(rows["centre"]["centre_median_px"]) == pytest.approx(0.0, abs=1e-6)
    assert depth["depth"] == pytest.approx(0.0, abs=1e-9) and depth["rotation,depth"] == pytest.approx(0.0, abs=1e-9)
    md = (out / "oracle_ladder.md").read_text()
    assert "depth error quartered" in md and md in capsys.readouterr().out
    # bad input: one error line, status 2, nothing written
    bad = tmp_path / "bad"
    assert ol.main(["--dataset", str(root), "--results", str(tmp_path / "none.csv"), "--out", str(bad)]) == 2
    assert "does not exist" in capsys.readouterr().err and not bad.exists()
    assert ol.main(["--dataset", str(root), "--results", str(results), "--out", str(bad), "--no-vsd",
                    "--rotation-objects", "99"]) == 2
    assert "no estimates of objects [99]" in capsys.readouterr().err and not bad.exists()
