"""experiments/view_gallery.py: crops, clean views and the view head's reconstructions of a real run."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "experiments"))

import view_gallery  # noqa: E402


def test_gallery_draws_crops_views_and_reconstructions_of_a_run(tmp_path, models, capsys):
    from sc6d_jax.train import preset, train

    cfg = preset("tiny", steps=2, log_every=1, checkpoint_every=2, val_crops=0)
    cfg = cfg.replace(model=dataclasses.replace(cfg.model, view_head=16, n_objects=2), loss=dataclasses.replace(cfg.loss, w_view=1.0),
                      stream=cfg.stream.__class__(batch_size=4, obj_ids=(1, 13)))
    train(cfg, models, tmp_path / "run", progress=False, verbose=False, workers=0)
    out = tmp_path / "g" / "views.png"
    args = ["--run", str(tmp_path / "run"), "--models", str(models), "--crops", "5", "--seed", "4"]
    assert view_gallery.main([*args, "--out", str(out)]) == 0
    assert "view loss" in capsys.readouterr().out
    img = cv2.cvtColor(cv2.imread(str(out)), cv2.COLOR_BGR2RGB)
    S = 48
    tile = 3 * S + 4 + 8
    assert img.shape == (2 * S + 4, 4 * tile, 3)
    b = view_gallery.gallery_batch(cfg, models, 5, 4)
    np.testing.assert_array_equal(img[:S, :S], b["rgb"][0])  # the crop the network sees
    np.testing.assert_array_equal(img[:S, S + 2:2 * S + 2], np.repeat(np.repeat(b["view"][0], 3, 0), 3, 1))
    assert img[S + 4:, tile:].min() == 255  # the second row holds one triple
    for bad, msg in ((["--crops", "0", "--out", str(tmp_path / "x.png")], "--crops"),
                     (["--out", str(tmp_path / "x.jpg")], ".png")):
        assert view_gallery.main([*args[:4], *bad]) == 2
        assert msg in capsys.readouterr().err
    assert not (tmp_path / "x.png").exists() and not (tmp_path / "x.jpg").exists()
