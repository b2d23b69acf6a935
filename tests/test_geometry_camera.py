"""Tests for crops, K_B, the PE map, translation encoding and allocentric rotations (float64)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from sc6d_jax import geometry as g

SETTINGS = settings(max_examples=15, deadline=None)
B = 8
S = 64
Z = np.array([0.0, 0.0, 1.0])


@pytest.fixture(autouse=True, scope="module")
def x64():
    """Enable float64 for this module only, restoring the previous setting afterwards."""
    with jax.enable_x64(True):
        yield


def _u(lo, hi):
    return arrays(np.float64, (B,), elements=st.floats(lo, hi, allow_nan=False, allow_subnormal=False))


@st.composite
def scenes(draw):
    """Random K (with unequal focal lengths), box and translation, batched by B."""
    fx, fy = draw(_u(200, 2000)), draw(_u(200, 2000))
    cx, cy = draw(_u(100, 700)), draw(_u(100, 500))
    K = np.zeros((B, 3, 3))
    K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2], K[:, 2, 2] = fx, fy, cx, cy, 1
    box = np.stack([draw(_u(-50, 600)), draw(_u(-50, 400)), draw(_u(2, 300)), draw(_u(2, 300))], -1)
    t = np.stack([draw(_u(-800, 800)), draw(_u(-800, 800)), draw(_u(50, 3000))], -1)
    return K, box, t


quats = arrays(np.float64, (B, 4), elements=st.floats(-1, 1)).filter(lambda q: np.all(np.linalg.norm(q, axis=-1) > 0.1))


def _project(K, t):
    h = np.einsum("...ij,...j->...i", K, t)
    return h[..., :2] / h[..., 2:]


@SETTINGS
@given(scenes())
def test_translation_roundtrip(scene):
    K, box, t = scene
    center, side = g.crop_box(box)
    dxy, dz = g.encode_translation(t, K, center, side, S)
    assert dxy.shape == (B, 2) and dz.shape == (B,) and dxy.dtype == jnp.float64
    t2 = np.asarray(g.decode_translation(dxy, dz, K, center, side, S))
    np.testing.assert_allclose(t2, t, rtol=1e-6, atol=1e-9 * np.abs(t).max())
    # definitions: delta_xy = (proj - centre) / s_B and delta_z = t_z / r with r = S / s_B
    np.testing.assert_allclose(dxy, (_project(K, t) - center) / np.asarray(side)[:, None], rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(dz, t[:, 2] / (S / np.asarray(side)), rtol=1e-12)


@SETTINGS
@given(scenes())
def test_K_B_projects_origin_where_T_maps_the_image_projection(scene):
    K, box, t = scene
    center, side = g.crop_box(box)
    T = np.asarray(g.crop_transform(center, side, S))
    K_B = np.asarray(g.crop_intrinsics(K, T))
    p_img = _project(K, t)
    p_crop = _project(K_B, t)
    via_T = np.einsum("bij,bj->bi", T, np.concatenate([p_img, np.ones((B, 1))], -1))[:, :2]
    np.testing.assert_allclose(p_crop, via_T, rtol=1e-10, atol=1e-8)
    # and that crop pixel is the crop centre plus S * delta_xy
    dxy, _ = g.encode_translation(t, K, center, side, S)
    np.testing.assert_allclose(p_crop, (S - 1) / 2 + S * np.asarray(dxy), rtol=1e-10, atol=1e-8)
    # the REFERENCE decode formula, with its box-centre-at-0 K_B
    K_B0 = K_B.copy()
    K_B0[:, :2, 2] -= (S - 1) / 2
    _, dz = g.encode_translation(t, K, center, side, S)
    r = S / np.asarray(side)
    vec = np.concatenate([S * np.asarray(dxy), np.ones((B, 1))], -1)
    t_ref = (r * np.asarray(dz))[:, None] * np.linalg.solve(K_B0, vec[..., None])[..., 0]
    np.testing.assert_allclose(t_ref, t, rtol=1e-8, atol=1e-6)


def test_crop_box_and_transform_pixel_convention():
    box = jnp.array([[10.0, 20.0, 40.0, 30.0], [0.0, 0.0, 7.0, 9.0]])
    center, side = g.crop_box(box)
    np.testing.assert_allclose(center, [[30.0, 35.0], [3.5, 4.5]])
    np.testing.assert_allclose(side, [60.0, 13.5])
    T = np.asarray(g.crop_transform(center, side, S))
    for b in range(2):
        c, s = np.asarray(center[b]), float(side[b])
        corners = np.array([[c[0] - s / 2, c[1] - s / 2, 1], [c[0], c[1], 1], [c[0] + s / 2, c[1] + s / 2, 1]])
        mapped = corners @ T[b].T
        # crop square edges -> crop image edges, centre -> centre (pixel centres are integers)
        np.testing.assert_allclose(mapped[:, :2], [[-0.5, -0.5], [(S - 1) / 2] * 2, [S - 0.5, S - 0.5]], atol=1e-12)
    assert g.crop_transform(jnp.zeros((3, 2), jnp.float32), jnp.ones(3, jnp.float32), S).dtype == jnp.float32


def test_jitter_box_matches_authors_ranges():
    box = jnp.broadcast_to(jnp.array([100.0, 50.0, 40.0, 80.0]), (4000, 4))
    key = jax.random.key(3)
    jb = np.asarray(g.jitter_box(key, box))
    np.testing.assert_array_equal(jb, g.jitter_box(key, box))
    c0 = np.array([120.0, 90.0])
    shift = (jb[:, :2] + jb[:, 2:] / 2 - c0) / np.array([40.0, 80.0])
    factor = jb[:, 2] / 40.0
    assert np.all(np.abs(shift) <= 0.25 + 1e-12) and np.abs(shift).max() > 0.24
    assert np.all((factor >= 0.75) & (factor <= 1.25)) and factor.min() < 0.76 and factor.max() > 1.24
    np.testing.assert_allclose(jb[:, 3] / jb[:, 2], 2.0, rtol=1e-12)  # one factor for w and h
    assert abs(np.corrcoef(shift[:, 0], factor)[0, 1]) < 0.1  # independent draws


def _ray_image(K: np.ndarray, width: int, height: int) -> np.ndarray:
    x, y = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    return np.stack([(x - K[0, 2]) / K[0, 0], (y - K[1, 2]) / K[1, 1]], -1)


@settings(max_examples=10, deadline=None)
@given(scenes())
def test_pe_map_is_the_ray_of_the_original_pixel(scene):
    K, box, _ = scene
    center, side = g.crop_box(box)
    T = np.asarray(g.crop_transform(center, side, S))
    pe = np.asarray(g.pe_map(K, T, S))
    assert pe.shape == (B, S, S, 2)
    u, v = np.meshgrid(np.arange(S), np.arange(S))  # [row = v, col = u]
    p = np.stack([u, v, np.ones_like(u)], -1).astype(np.float64)
    src = np.einsum("bij,hwj->bhwi", np.linalg.inv(T), p)  # image pixel each crop pixel came from
    ray = np.stack([(src[..., 0] - K[:, None, None, 0, 2]) / K[:, None, None, 0, 0],
                    (src[..., 1] - K[:, None, None, 1, 2]) / K[:, None, None, 1, 1]], -1)
    np.testing.assert_allclose(pe, ray, rtol=1e-10, atol=1e-12)
    # the PE is K_B^-1 applied to the crop pixel
    K_B = np.asarray(g.crop_intrinsics(K, T))
    kb = np.einsum("bij,hwj->bhwi", np.linalg.inv(K_B), p)
    np.testing.assert_allclose(pe, kb[..., :2] / kb[..., 2:], rtol=1e-10, atol=1e-12)


def test_pe_map_agrees_with_warped_ray_image():
    K = np.array([[572.4, 0, 325.3], [0, 573.6, 242.0], [0, 0, 1]])
    W, H = 640, 480
    rays = _ray_image(K, W, H).astype(np.float32)
    boxes = np.array([[100.0, 80.0, 60.0, 90.0], [400.0, 300.0, 120.0, 50.0], [5.0, 400.0, 30.0, 70.0]])
    center, side = g.crop_box(boxes)
    T = np.asarray(g.crop_transform(center, side, S))
    warped = g.warp_crop(rays, T, S)
    pe = np.asarray(g.pe_map(K, T, S))
    u, v = np.meshgrid(np.arange(S), np.arange(S))
    src = np.einsum("bij,hwj->bhwi", np.linalg.inv(T), np.stack([u, v, np.ones_like(u)], -1).astype(float))
    inside = (src[..., 0] >= 0) & (src[..., 0] <= W - 1) & (src[..., 1] >= 0) & (src[..., 1] <= H - 1)
    assert inside.sum() > 0.8 * inside.size
    # OpenCV bilinear weights are quantised to 1/32 pixel
    tol = 1 / (32 * K[0, 0]) + 1e-6
    assert np.abs(warped - pe)[inside].max() < tol
    outside = (src[..., 0] < -1) | (src[..., 0] > W) | (src[..., 1] < -1) | (src[..., 1] > H)
    assert outside.any() and np.all(warped[outside] == 0)  # border value outside the image


def test_warp_crop_pixel_convention_and_dtypes():
    W, H = 50, 40
    x, y = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
    coords = np.stack([x, y], -1)
    T = np.asarray(g.crop_transform(jnp.array([20.3, 17.9]), jnp.array(23.0), 16))
    src = np.einsum("ij,hwj->hwi", np.linalg.inv(T), np.stack([*np.meshgrid(np.arange(16), np.arange(16)), np.ones((16, 16))], -1))[..., :2]
    lin = g.warp_crop(coords, T, 16, "linear")
    np.testing.assert_allclose(lin, src, atol=1 / 32 + 1e-5)
    near = g.warp_crop(coords, T, 16, "nearest")
    assert np.all(np.abs(near - src) <= 0.5 + 1 / 32)
    np.testing.assert_allclose(near, np.round(near))  # nearest never blends
    mask = np.zeros((H, W), bool)
    mask[10:30, 15:35] = True
    m = g.warp_crop(mask, T, 16, "nearest")
    assert m.dtype == bool and m.shape == (16, 16)
    # nearest: crop pixel is set iff round(T^-1 p) hits the mask (up to OpenCV's 1/32 px rounding)
    def box(e):
        return (src[..., 0] > 14.5 + e) & (src[..., 0] < 34.5 - e) & (src[..., 1] > 9.5 + e) & (src[..., 1] < 29.5 - e)
    assert box(0.05).any() and (~box(-0.05)).any()
    assert np.all(m[box(0.05)]) and not np.any(m[~box(-0.05)])
    rgb = (np.random.default_rng(0).random((H, W, 6)) * 255).astype(np.uint8)  # > 4 channels
    out = g.warp_crop(rgb, np.stack([T, T]), 16)
    assert out.shape == (2, 16, 16, 6) and out.dtype == np.uint8
    np.testing.assert_array_equal(out[0, ..., 4:], g.warp_crop(rgb[..., 4:], T, 16))


def test_supersampled_crops_average_samples_spread_over_each_pixel():
    """``warp_crop(..., supersample=f)``: each crop pixel is the mean of f x f samples placed
    symmetrically about the pixel's centre, so a linear ramp (bilinear sampling is exact on
    it) gives exactly the one-sample crop, while a step edge falling inside a pixel gives the
    covered fraction instead of 0 or 1; ``area_downsample`` is the block mean and
    ``supersample_transform`` keeps the crop's pixel centres where they were."""
    W, H = 120, 100
    x, y = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    ramp = (0.3 * x - 0.7 * y + 5.0).astype(np.float32)
    T = np.asarray(g.crop_transform(jnp.array([61.3, 48.9]), jnp.array(70.0), 16))
    one = g.warp_crop(ramp, T, 16)
    for f in (2, 3, 4):
        np.testing.assert_allclose(g.warp_crop(ramp, T, 16, supersample=f), one, atol=2e-3)
        Tf = g.supersample_transform(T, f)
        # crop pixel u's centre is the mean of its f fine pixels' centres
        p = np.array([5.0, 7.0, 1.0])
        fine = np.array([[f * 5 + i, f * 7 + j, 1.0] for i in range(f) for j in range(f)])
        np.testing.assert_allclose(np.linalg.inv(Tf) @ fine.mean(0), np.linalg.inv(T) @ p, atol=1e-9)
    # a vertical edge at image x = 60.0 (pixels 0..59 dark): one crop pixel per 70/16 image pixels
    edge = (x >= 60).astype(np.float32)
    T2 = np.asarray(g.crop_transform(jnp.array([60.0, 50.0]), jnp.array(64.0), 16))  # 4 image px per crop px
    hard = g.warp_crop(edge, T2, 16)
    soft = g.warp_crop(edge, T2, 16, supersample=4)
    row_h, row_s = hard[8], soft[8]
    assert set(np.round(row_s, 3)) - {0.0, 1.0}  # a pixel partly covered reads between
    np.testing.assert_allclose(row_s.sum(), row_h.sum(), atol=1.0)  # the same area, spread
    # block means; bool = majority; a wrong size names the problem
    a = (2 * np.arange(16)).astype(np.uint8).reshape(4, 4)
    np.testing.assert_array_equal(g.area_downsample(a, 2), [[5, 9], [21, 25]])
    np.testing.assert_allclose(g.area_downsample(a.astype(np.float32), 2), [[5, 9], [21, 25]])
    assert g.area_downsample(a, 1) is a
    m = np.zeros((4, 4), bool)
    m[:2, :1] = True
    m[2:, 2:] = True
    np.testing.assert_array_equal(g.area_downsample(m, 2), [[True, False], [False, True]])
    with pytest.raises(ValueError, match="blocks"):
        g.area_downsample(np.zeros((5, 4)), 2)
    with pytest.raises(ValueError, match="supersample"):
        g.warp_crop(ramp, T, 16, supersample=0)


def test_z_bins():
    c = np.asarray(g.z_bin_centers(11, 0.5, 1.5))
    np.testing.assert_allclose(c, np.linspace(0.5, 1.5, 11), atol=1e-7)
    np.testing.assert_array_equal(g.z_bin_label(jnp.asarray(c), 11, 0.5, 1.5), np.arange(11))
    lab = np.asarray(g.z_bin_label(jnp.array([0.0, 0.54, 0.56, 1.0, 2.0]), 11, 0.5, 1.5))
    np.testing.assert_array_equal(lab, [0, 0, 1, 5, 10])
    logits = jnp.asarray(np.full((3, 11), -1e3)).at[jnp.arange(3), jnp.array([0, 4, 10])].set(0.0)
    np.testing.assert_allclose(g.z_expectation(logits, 0.5, 1.5), [0.5, 0.9, 1.5], atol=1e-12)
    np.testing.assert_allclose(g.z_expectation(jnp.zeros(11), 0.5, 1.5), 1.0, atol=1e-12)
    # two equal peaks average; jit-able with traced range
    two = jnp.full(11, -1e3).at[2].set(0.0).at[6].set(0.0)
    f = jax.jit(g.z_expectation)
    np.testing.assert_allclose(f(two, 0.5, 1.5), 0.9, atol=1e-12)
    assert g.z_expectation(jnp.zeros((2, 7), jnp.float32), 0.0, 1.0).dtype == jnp.float32


directions = arrays(np.float64, (B, 3), elements=st.floats(-1, 1)).filter(lambda v: np.all(np.linalg.norm(v, axis=-1) > 0.1))


@SETTINGS
@given(quats, directions, st.sampled_from([None, "axis", "antiparallel", "near-axis"]))
def test_allocentric_roundtrip_and_ray_rotation(q, tdir, case):
    R = g.quat_to_matrix(q)
    t = tdir * 1000.0
    if case == "axis":
        t[:, :2] = 0.0
        t[:, 2] = np.abs(t[:, 2]) + 1
    elif case == "antiparallel":
        t[:, :2] = 0.0
        t[:, 2] = -np.abs(t[:, 2]) - 1
    elif case == "near-axis":
        t[:, 2] = 1000.0
        t[:, :2] *= 1e-9
    Ra = g.egocentric_to_allocentric(R, t)
    np.testing.assert_allclose(g.allocentric_to_egocentric(Ra, t), R, atol=1e-12)
    np.testing.assert_allclose(g.egocentric_to_allocentric(g.allocentric_to_egocentric(R, t), t), R, atol=1e-12)
    Rc = np.asarray(g.ray_rotation(t))
    np.testing.assert_allclose(Rc @ Z, t / np.linalg.norm(t, axis=-1, keepdims=True), atol=1e-12)
    np.testing.assert_allclose(np.swapaxes(Rc, -1, -2) @ Rc, np.broadcast_to(np.eye(3), Rc.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(Rc), 1, atol=1e-12)
    if case == "axis":
        np.testing.assert_array_equal(Rc, np.broadcast_to(np.eye(3), Rc.shape))
    if case is None:  # the REFERENCE formula, evaluated directly
        n = t / np.linalg.norm(t, axis=-1, keepdims=True)
        v, c = np.cross(Z, n), n[:, 2]
        Vx = np.asarray(g.skew(v))
        ok = c > -0.9
        ref = np.eye(3) + Vx + Vx @ Vx / (1 + c)[:, None, None]
        np.testing.assert_allclose(Rc[ok], ref[ok], atol=1e-12)


@SETTINGS
@given(quats, directions, directions, st.floats(300, 3000))
def test_moving_sideways_at_fixed_allocentric_rotation_looks_the_same(q, d1, d2, dist):
    """Two poses with the same R_allo and distance, different directions in front of the camera.

    What truly holds: seen by a camera turned to look at the object centre (a pure rotation
    R_c^T of the camera, i.e. an image homography), both poses give identical camera-frame points
    R_allo X + dist z. Equivalently the image of pose 2 mapped by the homography
    K R_c1 R_c2^T K^-1 coincides with the image of pose 1. Holding R_ego fixed instead breaks it.
    """
    front = lambda d: d * np.array([0.5, 0.5, 0.0]) + np.array([0, 0, 1.0])  # within ~35 deg of the axis
    n1 = front(d1) / np.linalg.norm(front(d1), axis=-1, keepdims=True)
    n2 = front(d2) / np.linalg.norm(front(d2), axis=-1, keepdims=True)
    t1, t2 = dist * n1, dist * n2
    R_allo = np.asarray(g.quat_to_matrix(q))
    X = np.random.default_rng(0).uniform(-60, 60, size=(20, 3))  # model points, mm
    R1 = np.asarray(g.allocentric_to_egocentric(R_allo, t1))
    R2 = np.asarray(g.allocentric_to_egocentric(R_allo, t2))
    Y1 = np.einsum("bij,nj->bni", R1, X) + t1[:, None]
    Y2 = np.einsum("bij,nj->bni", R2, X) + t2[:, None]
    Rc1, Rc2 = np.asarray(g.ray_rotation(t1)), np.asarray(g.ray_rotation(t2))
    V1 = np.einsum("bji,bnj->bni", Rc1, Y1)
    V2 = np.einsum("bji,bnj->bni", Rc2, Y2)
    np.testing.assert_allclose(V1, V2, atol=1e-9)
    np.testing.assert_allclose(V1, np.einsum("bij,nj->bni", R_allo, X) + dist * Z, atol=1e-9)
    K = np.array([[600.0, 0, 320], [0, 620, 240], [0, 0, 1]])
    Hm = K @ Rc1 @ np.swapaxes(Rc2, -1, -2) @ np.linalg.inv(K)
    img2 = np.einsum("ij,bnj->bni", K, Y2)
    warped = np.einsum("bij,bnj->bni", Hm, img2)
    img1 = np.einsum("ij,bnj->bni", K, Y1)
    np.testing.assert_allclose(warped[..., :2] / warped[..., 2:], img1[..., :2] / img1[..., 2:], atol=1e-7)
    # control: fixed egocentric rotation changes the relative view whenever the rays differ enough
    far = np.arccos(np.clip(np.einsum("bi,bi->b", n1, n2), -1, 1)) > 0.2
    V2_ego = np.einsum("bji,bnj->bni", Rc2, np.einsum("bij,nj->bni", R1, X) + t2[:, None])
    assert np.all(np.abs(V2_ego - V1).max(axis=(1, 2))[far] > 1.0)


@pytest.mark.parametrize("k", [0, 1, 2, 3])
def test_turn_pe_is_the_pe_map_of_the_rolled_camera(k):
    """A crop turned by k quarter turns (rot90(crop, -k)) is what the camera rolled by Rz(90 k)
    about its optical axis sees: the image turns about the principal point, the box centre with
    it. turn_pe of the crop's PE map equals the rolled camera's own PE map of its crop."""
    K = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
    c, side = np.array([470.0, 95.0]), 88.0  # off-axis: the ray is about 20 degrees from the axis
    pe = g.pe_map(K, g.crop_transform(c, side, S), S)
    Rz = np.asarray(g.rot_z(k * np.pi / 2))[:2, :2]
    c_rolled = K[:2, 2] + Rz @ (c - K[:2, 2])
    expected = np.asarray(g.pe_map(K, g.crop_transform(c_rolled, side, S), S))
    np.testing.assert_allclose(np.asarray(g.turn_pe(pe, k)), expected, atol=1e-9)
    np.testing.assert_allclose(g.turn_pe(np.asarray(pe), k), expected, atol=1e-9)  # numpy too
    assert isinstance(g.turn_pe(np.asarray(pe), k), np.ndarray)
    if k:  # the unturned map (the authors' augmentation) is not that camera's
        assert np.abs(np.asarray(pe) - expected).max() > 0.1


def test_turn_pe_batched_and_bad_shape():
    pe = np.random.default_rng(0).normal(size=(3, 8, 8, 2))
    out = g.turn_pe(pe, 1)
    for i in range(3):
        np.testing.assert_array_equal(out[i], g.turn_pe(pe[i], 1))
    np.testing.assert_array_equal(g.turn_pe(pe, 4), pe)
    with pytest.raises(ValueError, match="pe must have shape"):
        g.turn_pe(np.zeros((8, 8, 3)), 1)
