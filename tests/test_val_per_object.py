"""``experiments/val_per_object.py``: each object's part of a run's validation AR, paired per crop
with another run; the crops' objects come from the run's own validator, rendered for real."""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "experiments"))

import val_per_object as vpo  # noqa: E402

IDS = (1, 5)


def _run(tmp_path: Path, models: Path) -> Path:
    from sc6d_jax.data import StreamConfig, delta_z_range
    from sc6d_jax.train import preset

    cfg = preset("tiny")
    cfg = cfg.replace(stream=dataclasses.replace(cfg.stream, obj_ids=IDS), val_crops=24,
                      model=dataclasses.replace(cfg.model, n_objects=len(IDS)))
    z = delta_z_range(StreamConfig(models_dir=str(models), crop_size=cfg.model.crop_size, obj_ids=IDS), n=200)
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text(cfg.replace(z_range=z).to_json())
    return run


def _write_shares(path: Path, records: list[tuple[int, str, np.ndarray]]) -> None:
    path.write_text("".join(json.dumps({"step": s, "crops": c, "shares": [float(x) for x in v]}) + "\n"
                            for s, c, v in records))


def test_per_object_ar_and_paired_difference_from_a_base(tmp_path, models, capsys):
    run = _run(tmp_path, models)
    digest, obj = vpo.crop_objects(run, models)
    assert len(obj) == 24 and set(obj.tolist()) == set(IDS)  # both objects among the crops
    one = (obj == 1).astype(float)  # every crop of object 1 right, every crop of object 5 wrong
    rng = np.random.default_rng(0)
    later = rng.choice([0.0, 0.5, 1.0], size=24)
    # step 10 validated twice (a resumed run): the last record counts
    _write_shares(run / "val_shares.jsonl", [(10, digest, np.zeros(24)), (10, digest, one), (20, digest, later)])
    base = tmp_path / "base_shares.jsonl"
    _write_shares(base, [(10, digest, np.full(24, 0.5)), (30, digest, np.ones(24))])
    out = tmp_path / "per_object.csv"
    assert vpo.main(["--run", str(run), "--models", str(models), "--base", str(base), "--csv", str(out)]) == 0
    rows = {(r["step"], r["obj_id"]): r for r in csv.DictReader(out.open())}
    assert set(rows) == {(s, o) for s in ("10", "20") for o in ("1", "5", "all")}  # step 30: the base's alone
    r = rows[("10", "1")]
    assert float(r["ar"]) == 1.0 and float(r["base_ar"]) == 0.5 and float(r["diff"]) == 0.5
    assert int(r["crops"]) == int((obj == 1).sum()) and float(r["diff_se"]) == 0.0
    assert float(rows[("10", "5")]["diff"]) == -0.5
    d = one - 0.5
    assert float(rows[("10", "all")]["ar"]) == pytest.approx(one.mean())
    assert float(rows[("10", "all")]["diff_se"]) == pytest.approx(np.std(d, ddof=1) / math.sqrt(24))
    assert float(rows[("20", "5")]["ar"]) == pytest.approx(later[obj == 5].mean())
    assert rows[("20", "5")]["diff"] == "" and rows[("20", "all")]["base_ar"] == ""  # no base at step 20
    printed = capsys.readouterr().out
    assert "paired difference" in printed and "+0.50" in printed and "-0.50" in printed


def test_shares_of_other_crops_are_refused_and_nothing_is_written(tmp_path, models, capsys):
    run = _run(tmp_path, models)
    digest, _ = vpo.crop_objects(run, models)
    _write_shares(run / "val_shares.jsonl", [(10, digest, np.ones(24))])
    base = tmp_path / "base_shares.jsonl"
    _write_shares(base, [(10, "0123456789abcdef", np.ones(24))])
    out = tmp_path / "per_object.csv"
    assert vpo.main(["--run", str(run), "--models", str(models), "--base", str(base), "--csv", str(out)]) == 2
    assert "the base validated on other crops" in capsys.readouterr().err and not out.exists()
    _write_shares(run / "val_shares.jsonl", [(10, digest, np.ones(23))])  # one crop short
    assert vpo.main(["--run", str(run), "--models", str(models)]) == 2
    assert "23 logged shares for the validator's 24 crops" in capsys.readouterr().err
    _write_shares(run / "val_shares.jsonl", [(10, "fedcba9876543210", np.ones(24))])
    assert vpo.main(["--run", str(run), "--models", str(models)]) == 2
    assert "of other crops (fedcba9876543210) than the run's validator renders" in capsys.readouterr().err
    assert vpo.main(["--run", str(tmp_path), "--models", str(models)]) == 2
    assert "not a training folder" in capsys.readouterr().err
