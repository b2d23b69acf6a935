"""experiments/step_flops.py: XLA's operation count of one training step, per configuration."""

from __future__ import annotations

import csv
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "experiments"))

import step_flops  # noqa: E402


def test_fewer_negatives_count_fewer_operations(tmp_path, capsys):
    out = tmp_path / "flops.csv"
    rc = step_flops.main(["--preset", "tiny", "--n-objects", "2", "--config", "base:", "--config",
                          "few:loss.n_negatives=100", "--out", str(out)])
    assert rc == 0
    rows = list(csv.DictReader(open(out)))
    assert [r["config"] for r in rows] == ["base", "few"] and float(rows[0]["ratio"]) == 1.0
    assert 0.0 < float(rows[1]["gflop"]) < float(rows[0]["gflop"]) and float(rows[1]["ratio"]) < 1.0
    assert "GFLOP" in capsys.readouterr().out


def test_bad_arguments_error_cleanly(capsys):
    assert step_flops.main(["--config", "nocolon"]) == 2
    assert "NAME:KEY=VALUE" in capsys.readouterr().err
    assert step_flops.main(["--config", "a:loss.no_such_field=1"]) == 2
    assert step_flops.main(["--n-objects", "0"]) == 2
