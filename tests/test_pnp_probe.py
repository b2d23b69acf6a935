"""experiments/pnp_probe.py: poses by PnP from object coordinates, checked on the stream's own
rendered coordinates (where PnP must give back the label), and bad input."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "experiments"))

import pnp_probe  # noqa: E402


def test_pnp_on_rendered_object_coordinates_gives_back_the_pose(models):
    """The stream's dense xyz targets (the rendered surface in the object's frame, block means at
    S/4) of cells wholly on the object, with the cells' centres and the crop's K_B: RANSAC PnP
    recovers the labelled rotation and depth (cells at the object's edge, whose mean point and
    centre differ, are what the mask threshold leaves out)."""
    from sc6d_jax.bop import load_models_info
    from sc6d_jax.data import CropStream, StreamConfig
    from sc6d_jax.geometry import crop_intrinsics, crop_transform

    cfg = StreamConfig(str(models), crop_size=64, batch_size=16, workers=0, seed=3, obj_ids=(1,), augment=False,
                       dense=True, dense_xyz=True, box_shift=0.0, box_scale=(1.0, 1.0))
    with CropStream(cfg) as s:
        b = s.batch(0)
    T = np.asarray(crop_transform(b["center"], b["side"], 64), np.float64)
    K_B = np.asarray(crop_intrinsics(b["K"], T), np.float64)
    np.testing.assert_allclose(K_B, b["K_B"], rtol=1e-5, atol=1e-3)
    diam = np.full(16, load_models_info(models)[1].diameter)
    R, t, ok = pnp_probe.pnp_poses(b["dense"][..., -3:], b["dense_w"], K_B, diam, 64, min_mask=0.99)
    assert ok.sum() >= 12
    rot = pnp_probe.rot_deg(R[ok], b["R"][ok].astype(np.float64))
    depth = np.abs(t[ok, 2] - b["t"][ok, 2]) / b["t"][ok, 2]
    assert np.median(rot) < 0.5 and np.median(depth) < 0.005, (rot, depth)
    # all the cells the object touches: the edge cells' offsets cost precision
    R2, t2, ok2 = pnp_probe.pnp_poses(b["dense"][..., -3:], b["dense_w"], K_B, diam, 64, min_mask=0.5)
    assert np.median(pnp_probe.rot_deg(R2[ok2], b["R"][ok2].astype(np.float64))) > np.median(rot)


def test_rot_deg_of_known_turns():
    from scipy.spatial.transform import Rotation

    A = Rotation.random(5, random_state=0).as_matrix()
    B = A @ Rotation.from_rotvec([[0, 0, np.radians(d)] for d in (0, 10, 45, 90, 180)]).as_matrix()
    np.testing.assert_allclose(pnp_probe.rot_deg(A, B), [0, 10, 45, 90, 180], atol=1e-4)


def test_refuses_what_is_not_a_run(tmp_path, models):
    r = subprocess.run([sys.executable, str(REPO / "experiments" / "pnp_probe.py"), "--run", str(tmp_path / "nothing"),
                        "--models", str(models), "--out", str(tmp_path / "out")], capture_output=True, text=True)
    assert r.returncode != 0 and "nothing" in r.stderr
    assert not (tmp_path / "out").exists()
