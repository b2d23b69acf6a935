"""The README's set-up script is idempotent: run again on a set-up machine, it installs nothing."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.skipif(
    Path(sys.prefix).resolve() != (ROOT / ".venv").resolve() or not (ROOT / ".venv" / ".sc6d-installed").is_file(),
    reason="runs only inside the .venv that experiments/bootstrap.sh made (it would create one otherwise)",
)
def test_bootstrap_installs_nothing_the_second_time():
    for _ in range(5):  # the system-package check once failed at random (a SIGPIPE race)
        out = subprocess.run(
            ["bash", str(ROOT / "experiments" / "bootstrap.sh"), "shell", "-c", "sc6d --version"],
            capture_output=True, text=True, timeout=120,
        )
        assert out.returncode == 0, out.stderr
        assert "installing" not in out.stderr, out.stderr
        assert out.stdout.startswith("sc6d "), out.stdout
