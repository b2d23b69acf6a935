"""BOP19 metrics against the BOP toolkit's own numbers (../shared/data/bop_reference) and LM-O.

The reference pairs were computed by thodan/bop_toolkit with its vispy renderer; ours renders
with MuJoCo, so VSD is compared with a tolerance while MSSD/MSPD must agree to rounding.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from sc6d_jax.bop import BopDataset, PoseEstimate, read_results_csv, write_results_csv
from sc6d_jax.metrics import (
    compute_errors,
    evaluate_bop19,
    load_eval_images,
    load_object_models,
    score_errors,
)


@pytest.fixture(scope="module")
def ref(shared_data):
    root = shared_data / "bop_reference"
    if not (root / "reference_synthperturb.json").is_file():
        pytest.skip("bop_reference data not found")
    ds = BopDataset(root / "tudl")
    data = json.loads((root / "reference_synthperturb.json").read_text())
    ests = read_results_csv(root / "synthperturb_tudl-test.csv")
    return ds, data, ests


@pytest.fixture(scope="module")
def ref_errors(ref):
    """Errors of the reference results; VSD with the MuJoCo renderer when it can start."""
    ds, data, ests = ref
    images = load_eval_images(ds, with_depth=True)
    models = load_object_models(ds, ds.obj_ids)
    reason = None
    renderer = None
    try:
        from sc6d_jax.metrics import VsdRenderer

        renderer = VsdRenderer.from_models_dir(ds.models_eval_dir(), ds.obj_ids, 640, 480)
    except Exception as exc:  # no GL / MuJoCo on this machine
        reason = f"MuJoCo depth renderer unavailable ({type(exc).__name__}: {exc})"
    try:
        errs = compute_errors(images, ests, models, renderer=renderer)
    finally:
        if renderer is not None:
            renderer.close()
    return images, models, errs, reason


def _pairs(ref, ref_errors):
    _, data, _ = ref
    _, _, errs, _ = ref_errors
    by_key = {(e.scene_id, e.im_id, e.obj_id, e.est_id): e for e in errs}
    assert len(data["pairs"]) == sum(len(e.mssd) for e in errs)  # the same pairs were evaluated
    for p in data["pairs"]:
        yield p, by_key[(p["scene_id"], p["im_id"], p["obj_id"], p["est_id"])]


def test_reference_pairs_mssd_mspd(ref, ref_errors):
    """Per pair MSSD [mm] and MSPD [px] equal the toolkit's (measured: max rel. diff ~1e-8, from
    the float32 vertex parsing of the PLY loader; 0 with float64-parsed vertices)."""
    worst = 0.0
    n_inf = 0
    for p, e in _pairs(ref, ref_errors):
        g = p["gt_id"]
        if math.isinf(p["mssd"]):
            assert math.isinf(e.mssd[g])
            n_inf += 1
        else:
            assert e.mssd[g] == pytest.approx(p["mssd"], rel=1e-6, abs=1e-6)
            worst = max(worst, abs(e.mssd[g] - p["mssd"]) / max(1.0, p["mssd"]))
        assert e.mspd[g] == pytest.approx(p["mspd"], rel=1e-6, abs=1e-6)
    assert n_inf > 0  # the "centres a diameter apart" shortcut was exercised
    print(f"mssd max rel diff {worst:.2e}")


def test_reference_pairs_vsd(ref, ref_errors):
    """VSD per tau close to the toolkit's (vispy vs MuJoCo rasterisation; measured max 3.5e-4)."""
    _, _, errs, reason = ref_errors
    if reason:
        pytest.skip(reason)
    diffs = []
    for p, e in _pairs(ref, ref_errors):
        d = np.abs(np.asarray(e.vsd[p["gt_id"]]) - np.asarray(p["vsd"]))
        diffs.append(d.max())
    print(f"vsd max abs diff {max(diffs):.2e}, mean {np.mean(diffs):.2e}")
    assert max(diffs) < 0.005


def test_reference_scores(ref, ref_errors):
    """AR, AR_VSD, AR_MSSD, AR_MSPD within 0.005 of the toolkit's (measured: identical)."""
    _, data, ests = ref
    images, models, errs, reason = ref_errors
    s = score_errors(images, errs, models, vsd_available=reason is None)
    want = data["scores"]
    for k in ("bop19_average_recall_mssd", "bop19_average_recall_mspd"):
        assert s[k] == pytest.approx(want[k], abs=1e-12)
    if reason:
        pytest.skip(reason)
    for k in ("bop19_average_recall", "bop19_average_recall_vsd"):
        assert abs(s[k] - want[k]) < 0.005, (k, s[k], want[k])


@pytest.mark.slow
def test_reference_evaluate_bop19_end_to_end(ref):
    ds, data, ests = ref
    s = evaluate_bop19(ds, ests)
    for k, v in data["scores"].items():
        assert abs(s[k] - v) < 0.005, (k, s[k], v)


def test_eval_cli_lmo_ground_truth_gives_ar_one(shared_data, tmp_path, capsys):
    """`sc6d eval` on LM-O (no depth) with the ground truth as estimates: AR 1, VSD skipped."""
    root = shared_data / "lmo"
    if not (root / "test_targets_bop19.json").is_file():
        pytest.skip("LM-O data not found")
    from sc6d_jax.metrics.cli import main

    ds = BopDataset(root)
    ests = []
    for tg in ds.targets():
        gts = ds.scene_gt(tg.scene_id)[tg.im_id]
        infos = ds.scene_gt_info(tg.scene_id)[tg.im_id]
        for g, inf in zip(gts, infos):
            if g.obj_id == tg.obj_id:
                ests.append(PoseEstimate(tg.scene_id, tg.im_id, g.obj_id, inf.visib_fract, g.R, g.t, 0.1))
    csv = write_results_csv(tmp_path / "gt_lmo-test.csv", ests)
    out = tmp_path / "scores.json"
    assert main(["--dataset", str(root), "--results", str(csv), "--out", str(out), "--no-progress"]) == 0
    s = json.loads(out.read_text())
    assert s["bop19_average_recall"] == 1.0
    assert s["bop19_average_recall_mssd"] == 1.0 and s["bop19_average_recall_mspd"] == 1.0
    assert s["bop19_average_recall_vsd"] is None and s["vsd_available"] is False
    assert "no depth" in s["vsd_skipped_reason"]
    assert all(v["ar"] == 1.0 for v in s["per_object"].values())
    bd = s["breakdown"]["overall"]  # the ground truth itself: no error, no miss
    assert bd["n"] == s["counts"]["targets"] and bd["missed"] == 0
    assert bd["rot_median_deg"] < 1e-3 and bd["rot_under_5"] == 1.0 and bd["depth_under_2pct"] == 1.0
    printed = capsys.readouterr().out
    assert "VSD skipped" in printed and "all" in printed


def test_eval_cli_rejects_missing_inputs(tmp_path):
    from sc6d_jax.metrics.cli import main

    with pytest.raises(FileNotFoundError):
        main(["--dataset", str(tmp_path / "nope"), "--results", "x.csv", "--out", str(tmp_path / "o.json")])
