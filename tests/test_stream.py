"""The training crop stream: labels consistent with the geometry, determinism, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from sc6d_jax import geometry as G
from sc6d_jax.data import CropStream, StreamConfig, delta_z_range



def test_batch_fields_and_labels(models):
    cfg = StreamConfig(str(models), crop_size=32, batch_size=6, workers=0, obj_ids=(1, 5, 9), augment=False)
    with CropStream(cfg) as s:
        b = next(s)
    S = 32
    assert b["rgb"].shape == (6, S, S, 3) and b["rgb"].dtype == np.uint8
    assert b["pe"].shape == (6, S, S, 2) and b["mask_visib"].shape == (6, S, S)
    assert set(b["obj_id"].tolist()) <= {1, 5, 9}
    np.testing.assert_array_equal(np.array([1, 5, 9])[b["obj_idx"]], b["obj_id"])
    for i in range(6):
        assert b["mask_visib"][i].sum() >= 50
        # labels decode back to the pose
        t = np.asarray(G.decode_translation(b["delta_xy"][i], b["delta_z"][i], b["K"][i], b["center"][i], b["side"][i], S))
        np.testing.assert_allclose(t, b["t"][i], rtol=1e-4)
        R = np.asarray(G.allocentric_to_egocentric(b["R_allo"][i], b["t"][i]))
        np.testing.assert_allclose(R, b["R"][i], atol=1e-4)
        # K_B projects the object origin where delta_xy says
        uv = b["K_B"][i] @ b["t"][i]
        np.testing.assert_allclose(uv[:2] / uv[2], (S - 1) / 2 + S * b["delta_xy"][i], atol=1e-2)
        # PE map = the ray of the original image pixel
        T = np.asarray(G.crop_transform(b["center"][i], b["side"][i], S))
        np.testing.assert_allclose(b["pe"][i], np.asarray(G.pe_map(b["K"][i], T, S)), atol=1e-6)


def test_rotation_augmentation_is_consistent(models):
    """With augmentation the labels follow the turned crop: R_allo <- Rz(90k) R_allo."""
    cfg = StreamConfig(str(models), crop_size=32, batch_size=8, workers=0, obj_ids=(1,), augment=True)
    with CropStream(cfg) as s:
        b = s.batch(3)
    turned = 0
    for i in range(8):
        R_allo_true = np.asarray(G.egocentric_to_allocentric(b["R"][i], b["t"][i]))
        D = b["R_allo"][i] @ R_allo_true.T  # Rz(90k)
        k = int(np.round(np.arctan2(D[1, 0], D[0, 0]) / (np.pi / 2))) % 4
        np.testing.assert_allclose(D, np.asarray(G.rot_z(k * np.pi / 2)), atol=1e-4)
        turned += k != 0
    assert turned > 0


def test_deterministic_and_worker_independent(models):
    cfg = StreamConfig(str(models), crop_size=32, batch_size=4, workers=0, seed=7)
    with CropStream(cfg, start_batch=2) as s:
        a = next(s)
    with CropStream(cfg) as s:
        b = s.batch(2)
        c = s.batch(3)
    with CropStream(StreamConfig(str(models), crop_size=32, batch_size=4, workers=2, seed=7), start_batch=2) as s:
        d = next(s)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])
        np.testing.assert_array_equal(a[k], d[k])
    assert not np.array_equal(a["rgb"], c["rgb"])


def test_delta_z_range_covers_samples(models):
    cfg = StreamConfig(str(models), crop_size=32, batch_size=16, workers=0)
    lo, hi = delta_z_range(cfg, n=500)
    assert 0 < lo < hi
    assert delta_z_range(cfg, n=500) == (lo, hi)
    with CropStream(cfg) as s:
        b = next(s)
    assert np.all((b["delta_z"] > lo) & (b["delta_z"] < hi))


def test_bad_input(tmp_path, models):
    with pytest.raises(FileNotFoundError, match="models folder"):
        CropStream(StreamConfig(str(tmp_path / "none"), workers=0))
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="no models"):
        CropStream(StreamConfig(str(tmp_path / "empty"), workers=0))
    with pytest.raises(ValueError, match="not in"):
        CropStream(StreamConfig(str(models), workers=0, obj_ids=(99,)))
    with pytest.raises(ValueError, match="crop_size"):
        StreamConfig(str(models), crop_size=30)


def test_curriculum_starts_plain_and_ends_full(models):
    cfg = StreamConfig(str(models), crop_size=32, batch_size=6, workers=0, augment=False, occlusion=1.0, curriculum=100)
    with CropStream(cfg) as s:
        easy, full = s.batch(0), s.batch(100)

    def plain(rgb, mask):
        bg = rgb[mask == 0]
        return len(np.unique(bg, axis=0)) == 1

    assert all(plain(easy["rgb"][i], easy["mask_visib"][i]) for i in range(6))
    assert not any(plain(full["rgb"][i], full["mask_visib"][i]) for i in range(6))
    with pytest.raises(ValueError, match="curriculum"):
        StreamConfig(str(models), curriculum=-1)
