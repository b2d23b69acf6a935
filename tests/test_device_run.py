"""experiments/device_run.sh, the prepared GPU-lease script, run here on the CPU at a tiny budget:
smoke crop, a real training, the run packed for the way back."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tarfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_device_script_trains_and_packs_a_resumable_run(tmp_path):
    from sc6d_jax import objects

    models = tmp_path / "models"
    objects.write_models(models)
    out, run = tmp_path / "out", tmp_path / "run"
    out.mkdir()
    env = {**os.environ, "SKIP_INSTALL": "1", "PY": sys.executable, "OUT": str(out), "RUN_DIR": str(run),
           "MODELS": str(models), "PRESET": "tiny", "TRAIN_STEPS": "12", "TRAIN_BATCH": "4", "WORKERS": "0",
           "BENCH": "0", "TRAIN_S": "240"}
    res = subprocess.run(["bash", str(ROOT / "experiments" / "device_run.sh")], cwd=ROOT, env=env,
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "crop batch" in (out / "smoke.log").read_text()
    assert "train exit 0" in (out / "train.log").read_text()
    with tarfile.open(out / "gpu_run.tar.gz") as tar:
        names = tar.getnames()
        tar.extractall(tmp_path / "back", filter="data")
    assert "run/config.json" in names and "run/checkpoints/ckpt_00000012/state.npz" in names
    back = tmp_path / "back" / "run"
    assert json.loads((back / "config.json").read_text())["steps"] == 12
    recs = [json.loads(x) for x in (back / "metrics.jsonl").read_text().splitlines()]
    assert recs[-1]["step"] == 12 and "val_ar" in recs[-1]
    shares = [json.loads(x) for x in (back / "val_shares.jsonl").read_text().splitlines()]
    assert shares[-1]["step"] == 12 and len(shares[-1]["shares"]) > 0  # paired comparisons travel too
    assert "'step': 12" in res.stdout  # the validation records printed for the reply's tail
