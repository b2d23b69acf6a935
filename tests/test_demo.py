"""`sc6d demo` runs end to end on the built-in objects (without a model: objects, render, check)."""

from __future__ import annotations

import json

import pytest

from sc6d_jax.demo import _ar_groups, main


def test_demo_without_model(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["--out", str(out), "--scenes", "1", "--images-per-scene", "2", "--no-model"]) == 0
    assert (out / "models" / "models_info.json").is_file()
    assert (out / "dataset" / "test_targets_bop19.json").is_file()
    assert (out / "check.png").read_bytes()[:4] == b"\x89PNG"
    assert "6/6 poses pass" in capsys.readouterr().out


def test_demo_bad_arguments(tmp_path):
    with pytest.raises(ValueError, match="either --run"):
        main(["--out", str(tmp_path / "d"), "--run", str(tmp_path), "--train"])
    with pytest.raises(FileNotFoundError, match="config.json"):
        main(["--out", str(tmp_path / "d"), "--run", str(tmp_path)])
    assert not (tmp_path / "d").exists()


def test_ar_groups_weights_by_targets():
    scores = {"per_object": {"1": {"ar": 1.0, "targets": 3}, "2": {"ar": 0.0, "targets": 1}, "5": {"ar": 0.5, "targets": 1}}}
    g = _ar_groups(json.loads(json.dumps(scores)), {2, 5})
    assert g["asymmetric"] == 1.0 and g["symmetric"] == 0.25


def test_demo_with_the_shipped_model(tmp_path, capsys):
    """The default demo path: the shipped builtin model predicts every target, the AR table is
    printed and the pictures are written (a small library keeps it quick)."""
    from sc6d_jax import pretrained

    assert "builtin" in pretrained.available(), "the builtin model must ship with the package"
    out = tmp_path / "demo"
    rc = main(["--out", str(out), "--scenes", "1", "--images-per-scene", "2", "--library-size", "20000"])
    assert rc == 0
    text = capsys.readouterr().out
    assert "AR symmetric objects" in text and "AR asymmetric objects" in text
    assert "pose errors (" in text and "rotation median" in text  # the overall breakdown line
    scores = json.loads((out / "scores.json").read_text())
    assert 0.0 <= scores["bop19_average_recall"] <= 1.0
    assert scores["breakdown"]["overall"]["n"] == scores["counts"]["targets"]
    pngs = sorted(p.name for p in (out / "figures").glob("*.png"))
    assert any(n.startswith("poses_") for n in pngs) and any(n.startswith("rotdist_") for n in pngs)
    assert "ar_per_object.png" in pngs and "worst_targets.png" in pngs
