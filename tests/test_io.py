"""sc6d_jax._io: the PNG helper every picture goes through."""

import cv2
import numpy as np
import pytest

from sc6d_jax._io import atomic_write_png, png_bytes


def test_png_round_trips_rgb_bgr_grey_and_uint16(tmp_path):
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (5, 7, 3), dtype=np.uint8)
    p = atomic_write_png(tmp_path / "sub" / "a.png", rgb)
    np.testing.assert_array_equal(cv2.imread(str(p), cv2.IMREAD_UNCHANGED)[..., ::-1], rgb)  # files are RGB
    bgr = cv2.imdecode(np.frombuffer(png_bytes(rgb, rgb=False), np.uint8), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(bgr, rgb)  # rgb=False writes the array's channels as they are
    depth = rng.integers(0, 65536, (4, 6), dtype=np.uint16)
    np.testing.assert_array_equal(cv2.imdecode(np.frombuffer(png_bytes(depth), np.uint8), cv2.IMREAD_UNCHANGED), depth)


def test_png_refuses_what_it_cannot_encode_and_writes_nothing(tmp_path):
    with pytest.raises(ValueError, match=r"shape \(0, 4, 3\)"):
        atomic_write_png(tmp_path / "a.png", np.zeros((0, 4, 3), np.uint8))
    with pytest.raises(ValueError, match="float64"):
        png_bytes(np.zeros((4, 4, 3), np.float64) + 0.5)
    assert list(tmp_path.iterdir()) == []
