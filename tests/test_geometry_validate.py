"""Bad input to sc6d_jax.geometry raises ValueError naming the problem (outside jit only)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sc6d_jax import geometry as g

K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
BOX = np.array([100.0, 100, 50, 80])


def _K(**changes):
    k = K.copy()
    for (i, j), v in changes.get("set", {}).items():
        k[i, j] = v
    return k


@pytest.mark.parametrize(
    ("bad", "match"),
    [
        (_K(set={(0, 0): 0.0}), "singular"),
        (_K(set={(1, 1): -500.0}), "negative focal"),
        (_K(set={(2, 2): 0.0}), "last row"),
        (_K(set={(0, 2): np.nan}), "non-finite"),
        (np.eye(4), r"shape \[..., 3, 3\]"),
        (np.zeros((3,)), r"shape \[..., 3, 3\]"),
    ],
)
def test_bad_K(bad, match):
    with pytest.raises(ValueError, match=match):
        g.validate_K(bad)
    # every public function taking K checks it when given concrete values
    center, side = g.crop_box(BOX)
    T = g.crop_transform(center, side, 32)
    for call in (
        lambda: g.crop_intrinsics(bad, T),
        lambda: g.pe_map(bad, T, 32),
        lambda: g.encode_translation(jnp.array([0.0, 0, 500]), bad, center, side, 32),
        lambda: g.decode_translation(jnp.zeros(2), 1.0, bad, center, side, 32),
    ):
        with pytest.raises(ValueError, match="K"):
            call()


@pytest.mark.parametrize(
    ("bad", "match"),
    [
        (np.array([0.0, 0, 0, 10]), "positive width and height"),
        (np.array([0.0, 0, 10, -1]), "positive width and height"),
        (np.array([np.nan, 0, 10, 10]), "non-finite"),
        (np.array([0.0, 0, 10]), r"shape \[..., 4\]"),
        (np.array([700.0, 10, 10, 10]), "wholly outside"),
        (np.array([10.0, -50, 10, 10]), "wholly outside"),
    ],
)
def test_bad_boxes(bad, match):
    with pytest.raises(ValueError, match=match):
        g.validate_boxes(bad, image_size=(640, 480))
    if "outside" not in match:  # crop functions do not know the image size
        with pytest.raises(ValueError, match="box_xywh"):
            g.crop_box(bad)
        with pytest.raises(ValueError, match="box_xywh"):
            g.jitter_box(jax.random.key(0), bad)


def test_boxes_touching_the_image_are_fine():
    ok = np.array([[-20.0, -20, 20, 20], [639.0, 479, 30, 30], [100, 100, 5, 5]])
    np.testing.assert_array_equal(g.validate_boxes(ok, image_size=(640, 480)), ok)


@pytest.mark.parametrize(
    ("bad", "match"),
    [
        (np.diag([1.0, 1.0, -1.0]), "determinant -1"),
        (2 * np.eye(3), "not orthonormal"),
        (np.full((3, 3), np.nan), "non-finite"),
        (np.eye(3)[:2], r"shape \[..., 3, 3\]"),
    ],
)
def test_bad_rotation(bad, match):
    with pytest.raises(ValueError, match=match):
        g.validate_rotation(bad)


def test_validate_translation_and_good_inputs_pass():
    with pytest.raises(ValueError, match="t_z > 0"):
        g.validate_translation(np.array([0.0, 0, -5]))
    with pytest.raises(ValueError, match="non-finite"):
        g.validate_translation(np.array([np.inf, 0, 5]))
    g.validate_translation(np.array([[1.0, 2, 3]]))
    g.validate_rotation(np.asarray(g.random_rotations(jax.random.key(0), 5)))
    g.validate_K(np.stack([K, K]))


def test_other_bad_arguments():
    center, side = g.crop_box(BOX)
    T = np.asarray(g.crop_transform(center, side, 32))
    cases = [
        (lambda: g.crop_box(BOX, pad=0.0), "pad must be positive"),
        (lambda: g.crop_transform(center, -side, 32), "side must be positive"),
        (lambda: g.crop_transform(jnp.array([np.nan, 1.0]), side, 32), "center contains NaN"),
        (lambda: g.crop_transform(center, side, 0), "out_size must be a positive int"),
        (lambda: g.pe_map(K, T, 32.5), "out_size must be a positive int"),
        (lambda: g.jitter_box(jax.random.key(0), BOX, scale=(1.2, 0.8)), "scale"),
        (lambda: g.warp_crop(np.zeros((10, 10, 3)), T, 32, "cubic"), "interpolation"),
        (lambda: g.warp_crop(np.zeros((10,)), T, 32), "image must be"),
        (lambda: g.warp_crop(np.zeros((10, 10)), np.zeros((3, 3)), 32), "affine"),
        (lambda: g.so3_grid(0, 10), "n_views must be a positive int"),
        (lambda: g.so3_grid(10, 10, seed=1.5), "seed must be an int"),
        (lambda: g.fibonacci_sphere(-1), "n must be a positive int"),
        (lambda: g.random_rotations(jax.random.key(0), 0), "n must be a positive int"),
        (lambda: g.covering_radius(np.zeros((0, 3, 3)), jax.random.key(0), 10), r"grid must have shape \[N, 3, 3\]"),
        (lambda: g.z_bin_centers(10, 2.0, 1.0), "d_lo < d_hi"),
        (lambda: g.z_bin_label(jnp.zeros(3), 0, 0.0, 1.0), "n_bins must be a positive int"),
        (lambda: g.z_expectation(jnp.zeros(5), 1.0, 1.0), "d_lo < d_hi"),
        (lambda: g.rebase_negatives(jnp.zeros((2, 3, 3, 3)), jnp.eye(3)), r"deltas must have shape \[Q, 3, 3\]"),
        (lambda: g.allocentric_to_egocentric(jnp.eye(3), jnp.zeros(2)), r"t must have shape \[..., 3\]"),
    ]
    for call, match in cases:
        with pytest.raises(ValueError, match=match):
            call()


def test_core_functions_stay_jittable():
    """Under jit the value checks are skipped (they cannot see values); the math still runs."""
    f = jax.jit(lambda box, K: g.pe_map(K, g.crop_transform(*g.crop_box(box), 16), 16))
    assert f(jnp.asarray(BOX), jnp.asarray(K)).shape == (16, 16, 2)
    h = jax.jit(lambda t, K, box: g.decode_translation(*g.encode_translation(t, K, *g.crop_box(box), 16),
                                                       K, *g.crop_box(box), 16))
    np.testing.assert_allclose(h(jnp.array([10.0, -5, 700]), jnp.asarray(K), jnp.asarray(BOX)), [10, -5, 700], rtol=1e-5)
    j = jax.jit(lambda key, box: g.jitter_box(key, box))
    assert j(jax.random.key(0), jnp.asarray(BOX)).shape == (4,)
