"""experiments/dumbbell_variant.py: the dumbbell with a larger cube, written, rendered, refused."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "experiments" / "dumbbell_variant.py"


def _magenta_pixels(models: Path) -> float:
    from sc6d_jax.data import CropStream, StreamConfig

    cfg = StreamConfig(str(models), crop_size=64, batch_size=16, workers=0, seed=2, obj_ids=(13,), augment=False,
                       occlusion=0.0, background="plain", box_shift=0.0, box_scale=(1.0, 1.0))
    with CropStream(cfg) as s:
        b = s.batch(0)
    c = b["rgb"].astype(int)
    magenta = (b["mask_visib"] > 0) & (c[..., 0] > c[..., 1] + 40) & (c[..., 2] > c[..., 1] + 40)
    return float(magenta.sum(axis=(1, 2)).mean())


def test_writes_a_one_object_folder_with_a_larger_cube(tmp_path, models):
    import trimesh

    out = tmp_path / "m"
    r = subprocess.run([sys.executable, str(SCRIPT), "--out", str(out)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-2000:]
    assert sorted(p.name for p in out.iterdir()) == ["models_info.json", "obj_000013.ply"]
    info = json.loads((out / "models_info.json").read_text())
    assert list(info) == ["13"]
    assert not info["13"].get("symmetries_discrete") and not info["13"].get("symmetries_continuous")
    mesh = trimesh.load(out / "obj_000013.ply", process=False)
    base = trimesh.load(models / "obj_000013.ply", process=False)
    assert len(mesh.faces) == len(base.faces) + 12  # one box more
    lo, hi = mesh.bounds
    np.testing.assert_allclose((lo + hi) / 2, 0.0, atol=1e-6)  # centred on its box, as the built-ins
    # rendered by the stream, the same poses show several times as many cube pixels
    assert _magenta_pixels(out) > 2.5 * _magenta_pixels(models)


def test_refuses_bad_input(tmp_path):
    (tmp_path / "there").mkdir()
    r = subprocess.run([sys.executable, str(SCRIPT), "--out", str(tmp_path / "there")], capture_output=True, text=True)
    assert r.returncode != 0 and "exists" in r.stderr
    r = subprocess.run([sys.executable, str(SCRIPT), "--out", str(tmp_path / "new"), "--size", "0"], capture_output=True,
                       text=True)
    assert r.returncode != 0 and "--size" in r.stderr and not (tmp_path / "new").exists()
