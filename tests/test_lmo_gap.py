"""experiments/lmo_gap.py: the four versions of a test set and their scores, on a small rendered
BOP test set of the built-in objects (real MuJoCo renders standing in for the photographs)."""

from __future__ import annotations

import csv
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "experiments"))

import lmo_gap  # noqa: E402


@pytest.fixture(scope="module")
def photos(models, tmp_path_factory) -> Path:
    from sc6d_jax.cli import main as sc6d

    out = tmp_path_factory.mktemp("gap") / "photos"
    rc = sc6d(["render", "--models", str(models), "--out", str(out), "--scenes", "1", "--images-per-scene", "2",
               "--objects-per-image", "2", "--obj-ids", "1,2", "--width", "160", "--height", "128", "--seed", "3",
               "--no-progress"])
    assert rc == 0
    return out


def test_versions_swap_objects_and_surroundings_and_are_scored(photos, tmp_path, capsys):
    from sc6d_jax.bop import BopDataset

    out = tmp_path / "gap"
    rc = lmo_gap.main(["--run", "builtin", "--dataset", str(photos), "--out", str(out), "--library-size", "20000"])
    assert rc == 0
    real = BopDataset(photos)
    ver = {v: BopDataset(out / v) for v in lmo_gap.VERSIONS[1:]}
    (sid,) = real.scene_ids()
    for im in real.im_ids(sid):
        a = real.load_rgb(sid, im)
        ro, rd, r = (ver[v].load_rgb(sid, im) for v in ("real_objects", "rendered_objects", "rendered"))
        inside = np.all(ro == a, axis=-1) & ~np.all(rd == a, axis=-1)  # object pixels that the render changed
        outside = ~np.all(ro == a, axis=-1)  # surroundings replaced by a procedural background
        assert outside.mean() > 0.3 and inside.any()
        assert np.all(np.all(ro == a, axis=-1) | np.all(rd == a, axis=-1))  # each pixel keeps one of the two
        np.testing.assert_array_equal(r[inside], rd[inside])  # the rendered objects are the same render
        np.testing.assert_array_equal(r[outside], ro[outside])  # the same procedural background
        rro, rr = (ver[v].load_rgb(sid, im) for v in ("real_objects_recoloured", "rendered_recoloured"))
        np.testing.assert_array_equal(rro[outside], ro[outside])
        np.testing.assert_array_equal(rr[outside], ro[outside])
        # recoloured, the photographed pixels take the rendered ones' mean colour, and the other way round
        np.testing.assert_allclose(rro[inside].mean(0), r[inside].mean(0), atol=6)
        np.testing.assert_allclose(rr[inside].mean(0), a[inside].mean(0), atol=6)
    x = np.array([[0, 10, 20], [20, 30, 20]], np.uint8)
    ref = np.array([[100, 100, 100], [140, 100, 120]], np.uint8)
    np.testing.assert_array_equal(lmo_gap.match_colours(x, ref), [[100, 100, 110], [140, 100, 110]])
    rows = list(csv.DictReader(open(out / "gap.csv")))
    assert [r["version"] for r in rows if r["obj_id"] == "all"] == list(lmo_gap.VERSIONS)
    assert all(0.0 <= float(r["ar"]) <= 1.0 for r in rows)
    printed = capsys.readouterr().out
    assert "rendered_objects" in printed and "gap.csv" in printed
    # a rerun reuses the versions and the scores
    mtime = (out / "real_objects" / "DONE").stat().st_mtime
    assert lmo_gap.main(["--run", "builtin", "--dataset", str(photos), "--out", str(out)]) == 0
    assert (out / "real_objects" / "DONE").stat().st_mtime == mtime


def test_bad_inputs_error_cleanly(tmp_path, capsys):
    assert lmo_gap.main(["--run", "builtin", "--dataset", str(tmp_path / "none"), "--out", str(tmp_path / "o")]) == 2
    assert "no BOP test split" in capsys.readouterr().err
    (tmp_path / "ds" / "test").mkdir(parents=True)
    assert lmo_gap.main(["--run", "builtin", "--dataset", str(tmp_path / "ds"), "--out", str(tmp_path / "o"),
                         "--obj-ids", "a,b"]) == 2
    assert "--obj-ids" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_masks_measure_the_gate_on_every_version(photos, tmp_path, capsys):
    """--masks: per version, the predicted visible mask against the rendered ground truth and the
    rotation with three gates; on these renders the builtin model's masks overlap the truth."""
    out = tmp_path / "gap"
    rc = lmo_gap.main(["--run", "builtin", "--dataset", str(photos), "--out", str(out), "--library-size", "20000",
                       "--obj-ids", "1", "--masks"])
    assert rc == 0
    rows = list(csv.DictReader(open(out / "masks.csv")))
    pooled = {r["version"]: r for r in rows if r["obj_id"] == "all"}
    assert list(pooled) == list(lmo_gap.VERSIONS)
    assert {r["obj_id"] for r in rows} == {"1", "all"}
    for r in rows:
        assert int(r["targets"]) >= 1
        assert 0.0 <= float(r["mask_iou_under_half"]) <= 1.0
        assert 0.0 <= float(r["mask_recall_median"]) <= 1.0 and float(r["mask_area_ratio_median"]) > 0.0
        for k in ("rot_own_gate_deg", "rot_gt_gate_deg", "rot_own_gate_on_gt_deg"):
            assert 0.0 <= float(r[k]) <= 180.0
    assert float(pooled["rendered"]["mask_iou_median"]) > 0.5
    assert float(pooled["rendered"]["mask_recall_median"]) >= float(pooled["rendered"]["mask_iou_median"])
    assert float(pooled["real"]["mask_iou_median"]) > 0.5  # here the "photographs" are renders too
    assert "masks.csv" in capsys.readouterr().out
