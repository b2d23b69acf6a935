"""experiments/cue_probe.py: the dumbbell cube's side by hand, the probe on known data, a real run."""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "experiments"))

import cue_probe  # noqa: E402


def test_cube_side_of_hand_made_poses():
    """The bar (object z) along the image's u axis, the cube (object x) towards +v or -v."""
    K = np.array([[100.0, 0, 32], [0, 100.0, 32], [0, 0, 1]])
    up = np.array([[0.0, 0, 1], [1, 0, 0], [0, 1, 0]])  # columns: x -> +v, y -> +z, z -> +u
    down = up @ np.diag([-1.0, -1.0, 1.0])  # turned half a turn about the bar
    side, dist = cue_probe.cube_side(np.stack([up, down]), np.array([[0.0, 0, 500]] * 2), np.stack([K, K]))
    np.testing.assert_array_equal(side, [1.0, -1.0])
    np.testing.assert_allclose(dist, [100 * 14 / 500] * 2, rtol=1e-9)
    # seen end-on (the bar along the line of sight... here the cube along it): no offset
    along = np.array([[0.0, 0, 1], [0, 1, 0], [1, 0, 0]]) @ np.diag([1.0, -1.0, 1.0])  # x -> +z (depth)
    assert np.isclose(np.linalg.det(along), 1.0)
    _, d = cue_probe.cube_side(along[None], np.array([[0.0, 0, 500]]), K[None])
    assert d[0] < 1e-9


def test_probe_tells_a_linear_label_and_not_a_random_one():
    rng = np.random.default_rng(0)
    X = rng.normal(size=(800, 40))
    w = rng.normal(size=40)
    y = np.sign(X @ w + 0.3 * rng.normal(size=800))
    assert cue_probe.probe_accuracy(X, y) > 0.9
    assert 0.38 < cue_probe.probe_accuracy(X, rng.choice([-1.0, 1.0], 800)) < 0.62
    Z = rng.normal(size=(200, 5))  # more features than crops (the dual form), of a few factors
    wide = Z @ rng.normal(size=(5, 500)) + 0.1 * rng.normal(size=(200, 500))
    assert cue_probe.probe_accuracy(wide, np.sign(Z[:, 0])) > 0.85


def test_probe_of_a_real_run_and_refusals(tmp_path, models, capsys):
    from sc6d_jax.train import preset, train

    cfg = preset("tiny", steps=2, log_every=1, checkpoint_every=2, val_crops=0)
    cfg = cfg.replace(model=dataclasses.replace(cfg.model, n_objects=2),
                      stream=cfg.stream.__class__(batch_size=4, obj_ids=(1, 13)))
    train(cfg, models, tmp_path / "run", progress=False, verbose=False, workers=0)
    out = tmp_path / "p.json"
    args = ["--run", str(tmp_path / "run"), "--models", str(models), "--crops", "128"]
    assert cue_probe.main([*args, "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    got = json.loads(out.read_text())
    assert set(got["accuracy"]) == set(cue_probe.LAYERS) and all(0 <= v <= 1 for v in got["accuracy"].values())
    assert 64 < got["crops"] <= 128 and "rot_emb" in printed
    assert cue_probe.main([*args[:4], "--crops", "8"]) == 2
    assert "--crops" in capsys.readouterr().err
    # a run of obj 1 alone (an untrained checkpoint: the refusal reads the run's objects)
    import jax

    from sc6d_jax.model import init
    from sc6d_jax.train import save_checkpoint

    cfg1 = preset("tiny")
    cfg1 = cfg1.replace(stream=cfg1.stream.__class__(batch_size=4, obj_ids=(1,)))
    one = tmp_path / "one"
    save_checkpoint(one, 1, init(jax.random.PRNGKey(0), cfg1.model), {}, np.zeros(2, np.uint32), cfg1.to_dict(),
                    extra_meta={"models_dir": str(models)})
    (one / "config.json").write_text(json.dumps(cfg1.to_dict()))
    assert cue_probe.main(["--run", str(one), "--models", str(models)]) == 2
    assert "did not train the dumbbell" in capsys.readouterr().err
