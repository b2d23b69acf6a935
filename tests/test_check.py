"""The render-and-check command: renderer and geometry agree on real MuJoCo renders."""

from __future__ import annotations

from sc6d_jax.check import THRESHOLDS, main, run_checks


def test_renderer_and_geometry_agree(tmp_path):
    rows = run_checks(n_poses=4, seed=3, out_png=tmp_path / "c.png")
    assert len(rows) == 4
    for r in rows:
        assert r["box_err_px"] <= THRESHOLDS["box_err_px"], r
        assert r["crop_iou"] >= THRESHOLDS["crop_iou"], r
        assert r["t_rel_err"] <= THRESHOLDS["t_rel_err"], r
        assert r["allo_iou"] >= THRESHOLDS["allo_iou"], r
    assert (tmp_path / "c.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_check_cli_rejects_bad_arguments(tmp_path, capsys):
    import pytest

    with pytest.raises(ValueError, match="--poses"):
        main(["--poses", "0", "--out", str(tmp_path / "x.png")])
    with pytest.raises(ValueError, match=".png"):
        main(["--out", str(tmp_path / "x.jpg")])
    assert not any(tmp_path.iterdir())
