"""experiments/ab_stream.py: a same-run A/B of the stream between two checkouts."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "experiments" / "ab_stream.py"


def test_ab_of_a_checkout_against_itself(tmp_path):
    out = subprocess.run(
        [sys.executable, str(SCRIPT), str(ROOT), "--rounds", "1", "--size", "32", "--workers", "1", "--crops", "64"],
        capture_output=True, text=True, timeout=300, cwd=tmp_path,
    )
    assert out.returncode == 0, out.stderr
    lines = out.stdout.strip().splitlines()
    assert [ln.split()[2] for ln in lines[:2]] == ["other", "this"]
    assert all(float(ln.split()[3]) > 0 for ln in lines[:2])
    assert "32x32, 1 workers, 1 rounds" in lines[-1] and "ratio" in lines[-1]


def test_other_must_be_a_checkout(tmp_path):
    out = subprocess.run([sys.executable, str(SCRIPT), str(tmp_path)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and "not a checkout of this project" in out.stderr
