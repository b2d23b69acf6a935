"""Tests of the SC6D network (sc6d_jax.model): layers, shapes per config switch, heads, weights."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sc6d_jax.geometry import random_rotations
from sc6d_jax.model import (
    BACKBONES,
    ModelConfig,
    apply,
    conv2d,
    count_params,
    encode_rotations,
    group_norm,
    init,
    load_resnet_weights,
    rotation_logits,
    upsample2x_bilinear,
)

TINY = ModelConfig(
    n_objects=3, crop_size=32, backbone="tiny", width=8, decoder_width=16, feat_dim=8, emb_dim=8,
    n_z_bins=16, pose_width=8, head_hidden=16, so3_hidden=16, ipdf_hidden=16, gn_groups=4,
)


@pytest.fixture
def x64():
    with jax.enable_x64(True):
        yield


def _inputs(cfg: ModelConfig, b: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    s = cfg.crop_size
    rgb = jnp.asarray(rng.uniform(0, 1, (b, s, s, 3)), jnp.float32)
    pe = jnp.asarray(rng.uniform(-0.5, 0.5, (b, s, s, 2)), jnp.float32)
    obj = jnp.asarray(np.arange(b) % cfg.n_objects, jnp.int32)
    return rgb, pe, obj


# ----------------------------------------------------------------------------- layers


@pytest.mark.parametrize("stride", [1, 2])
@pytest.mark.parametrize("dilation", [1, 2, 3, *(pytest.param(d, marks=pytest.mark.slow) for d in (4, 5, 6)), 7])
def test_im2col_matches_lax_values_and_grads(x64, stride, dilation):
    rng = np.random.default_rng(stride * 10 + dilation)
    x = jnp.asarray(rng.normal(size=(2, 9, 8, 3)))
    w = jnp.asarray(rng.normal(size=(3, 3, 3, 4)))
    b = jnp.asarray(rng.normal(size=(4,)))

    def f(impl):
        return lambda x, w, b: jnp.sum(jnp.sin(conv2d(x, w, b, stride=stride, dilation=dilation, impl=impl)))

    y1 = conv2d(x, w, b, stride=stride, dilation=dilation, impl="im2col")
    y2 = conv2d(x, w, b, stride=stride, dilation=dilation, impl="lax")
    assert y1.dtype == jnp.float64 and y1.shape == y2.shape
    assert y1.shape[1] == (9 - 1) // stride + 1
    np.testing.assert_allclose(y1, y2, rtol=1e-12, atol=1e-12)
    g1 = jax.grad(f("im2col"), argnums=(0, 1, 2))(x, w, b)
    g2 = jax.grad(f("lax"), argnums=(0, 1, 2))(x, w, b)
    for a, c in zip(g1, g2):
        np.testing.assert_allclose(a, c, rtol=1e-11, atol=1e-11)


@pytest.mark.parametrize("k,stride", [(1, 1), (1, 2), (7, 2), (5, 1)])
def test_im2col_matches_lax_other_kernels(x64, k, stride):
    rng = np.random.default_rng(k)
    x = jnp.asarray(rng.normal(size=(2, 10, 10, 5)))
    w = jnp.asarray(rng.normal(size=(k, k, 5, 6)))
    np.testing.assert_allclose(
        conv2d(x, w, stride=stride, impl="im2col"), conv2d(x, w, stride=stride, impl="lax"), rtol=1e-12, atol=1e-12
    )


def test_per_sample_kernels_match_individual_convs(x64):
    rng = np.random.default_rng(3)
    x = jnp.asarray(rng.normal(size=(3, 6, 6, 2)))
    w = jnp.asarray(rng.normal(size=(3, 3, 3, 2, 4)))
    b = jnp.asarray(rng.normal(size=(3, 4)))
    for impl in ("im2col", "lax"):
        y = conv2d(x, w, b, stride=2, dilation=2, impl=impl)
        for i in range(3):
            yi = conv2d(x[i : i + 1], w[i], b[i], stride=2, dilation=2, impl="lax")
            np.testing.assert_allclose(y[i : i + 1], yi, rtol=1e-12, atol=1e-12)


def test_conv_rejects_bad_input():
    x = jnp.zeros((1, 4, 4, 3))
    with pytest.raises(ValueError, match="channels"):
        conv2d(x, jnp.zeros((3, 3, 2, 4)))
    with pytest.raises(ValueError, match="impl"):
        conv2d(x, jnp.zeros((3, 3, 3, 4)), impl="fft")
    with pytest.raises(ValueError, match="odd"):
        conv2d(x, jnp.zeros((2, 2, 3, 4)))


def test_upsample_matches_jax_image_resize(x64):
    x = jnp.asarray(np.random.default_rng(0).normal(size=(2, 3, 5, 4)))
    ref = jax.image.resize(x, (2, 6, 10, 4), method="bilinear")
    np.testing.assert_allclose(upsample2x_bilinear(x), ref, rtol=1e-12, atol=1e-12)


def test_group_norm_matches_numpy(x64):
    rng = np.random.default_rng(1)
    x = rng.normal(size=(2, 4, 4, 6)) * 3 + 1
    scale, bias = rng.normal(size=6), rng.normal(size=6)
    y = group_norm(jnp.asarray(x), jnp.asarray(scale), jnp.asarray(bias), groups=3)
    np.testing.assert_allclose(y, _group_norm_ref(x, scale, bias, 3), rtol=1e-10, atol=1e-10)


def _group_norm_ref(x, scale, bias, groups):
    """The textbook two-pass GroupNorm in float64 numpy; scale/bias (C,) or per sample (B,C)."""
    B, C = x.shape[0], x.shape[-1]
    xg = x.reshape(B, -1, groups, C // groups)
    y = ((xg - xg.mean(axis=(1, 3), keepdims=True)) / np.sqrt(xg.var(axis=(1, 3), keepdims=True) + 1e-5)).reshape(x.shape)
    if scale.ndim == 2:
        extra = (1,) * (x.ndim - 2)
        scale, bias = scale.reshape(B, *extra, C), bias.reshape(B, *extra, C)
    return y * scale + bias


def test_group_norm_per_sample_affine_and_flat_input(x64):
    """Per-sample scale and bias (B,C) on NHWC input, and (B,C) input (the pose decoder's heads)."""
    rng = np.random.default_rng(2)
    x = rng.normal(size=(3, 5, 4, 8)) * 2 - 1
    scale, bias = rng.normal(size=(3, 8)), rng.normal(size=(3, 8))
    y = group_norm(jnp.asarray(x), jnp.asarray(scale), jnp.asarray(bias), groups=4)
    np.testing.assert_allclose(y, _group_norm_ref(x, scale, bias, 4), rtol=1e-10, atol=1e-10)
    v = rng.normal(size=(6, 16)) + 3
    s1, b1 = rng.normal(size=16), rng.normal(size=16)
    np.testing.assert_allclose(group_norm(jnp.asarray(v), jnp.asarray(s1), jnp.asarray(b1), groups=4),
                               _group_norm_ref(v, s1, b1, 4), rtol=1e-10, atol=1e-10)


def test_group_norm_float32_one_pass_statistics_and_gradient():
    """The one-pass variance (E[x^2] - E[x]^2) in float32 stays within float32 noise of the
    float64 textbook form when a group's squared mean is 900 times its variance (in trained models
    the worst group's is under 8: experiments/bench_group_norm.py --stats), and so does its gradient."""
    rng = np.random.default_rng(3)
    x = rng.normal(size=(4, 16, 16, 16)) * 0.5 + 15.0
    scale, bias = rng.normal(size=16), rng.normal(size=16)
    w = rng.normal(size=x.shape)
    y = group_norm(jnp.asarray(x, jnp.float32), jnp.asarray(scale, jnp.float32), jnp.asarray(bias, jnp.float32), 4)
    ref = _group_norm_ref(x, scale, bias, 4)
    np.testing.assert_allclose(np.asarray(y, np.float64), ref, atol=2e-3 * np.abs(ref).max())
    with jax.enable_x64(True):
        g64 = jax.grad(lambda x: jnp.sum(jax.nn.relu(group_norm(x, jnp.asarray(scale), jnp.asarray(bias), 4)) * w))(
            jnp.asarray(x))
    g32 = jax.grad(lambda x: jnp.sum(jax.nn.relu(group_norm(x, jnp.asarray(scale, jnp.float32),
                                                            jnp.asarray(bias, jnp.float32), 4)) * jnp.asarray(w, jnp.float32)))(
        jnp.asarray(x, jnp.float32))
    np.testing.assert_allclose(np.asarray(g32, np.float64), np.asarray(g64), atol=5e-3 * np.abs(np.asarray(g64)).max())


# ----------------------------------------------------------------------------- config and shapes


def test_model_config_validation():
    with pytest.raises(ValueError, match="backbone"):
        ModelConfig(backbone="vgg")
    with pytest.raises(ValueError, match="rot_head"):
        ModelConfig(rot_head="quat")
    with pytest.raises(ValueError, match="crop_size"):
        ModelConfig(crop_size=40)
    with pytest.raises(ValueError, match="conv_impl"):
        ModelConfig(conv_impl="cudnn")
    with pytest.raises(ValueError, match="n_objects"):
        ModelConfig(n_objects=0)
    with pytest.raises(ValueError, match="pose_downsample"):
        ModelConfig(pose_downsample=3)
    assert hash(TINY) == hash(dataclasses.replace(TINY))


SWITCHES = [
    {},
    {"use_pe": False},
    {"per_object_decoder": False},
    {"rot_head": "ipdf"},
    {"rot_head": "ipdf", "ipdf_pe_freqs": 3, "n_objects": 1},
    {"conv_impl": "lax"},
    {"conv_impl": "im2col"},
    {"n_objects": 1},
    {"crop_size": 48},
    {"pose_downsample": 1, "crop_size": 64},
    {"pose_downsample": 0, "crop_size": 64},
    {"rot_readout": True},
    {"z_ray_input": True, "z_size_input": True, "z_scale_input": True},
] + [{"backbone": name} for name in BACKBONES]


@pytest.mark.parametrize("switch", SWITCHES, ids=lambda d: ",".join(f"{k}={v}" for k, v in d.items()) or "default")
def test_output_shapes_for_every_switch(switch):
    cfg = dataclasses.replace(TINY, **switch)
    params = init(jax.random.key(0), cfg)
    rgb, pe, obj = _inputs(cfg, 4)
    out = jax.eval_shape(lambda p: apply(p, cfg, rgb, pe if cfg.use_pe else None, obj), params)
    m = cfg.crop_size // 4
    assert out["rot_emb"].shape == (4, cfg.emb_dim)
    assert out["delta_xy"].shape == (4, 2)
    assert out["z_logits"].shape == (4, cfg.n_z_bins)
    assert out["mask_logit"].shape == (4, m, m)
    assert params["backbone"]["stem"]["conv"]["w"].shape[2] == (5 if cfg.use_pe else 3)
    for cands in (jax.ShapeDtypeStruct((7, 3, 3), jnp.float32), jax.ShapeDtypeStruct((4, 7, 3, 3), jnp.float32)):
        lg = jax.eval_shape(lambda p, o, r: rotation_logits(p, cfg, o, r, obj), params, out, cands)
        assert lg.shape == (4, 7)


def test_z_ray_input_reads_the_crop_centres_ray_and_moves_only_the_depth():
    """ray_features: the mean of the PE map (its centre's ray) and its second-order terms; with
    z_ray_input the depth logits see where the same crop lies in the image; the rotation
    embedding is the one of the model without that input."""
    from sc6d_jax.geometry import crop_transform, pe_map
    from sc6d_jax.model._pose_decoder import ray_features

    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    pe = np.asarray(pe_map(K, crop_transform(np.array([570.0, 40.0]), 100.0, 32), 32))[None]
    x, y = 250.0 / 500.0, -200.0 / 500.0
    np.testing.assert_allclose(np.asarray(ray_features(pe))[0], [2 * x, 2 * y, 4 * x * x, 4 * y * y, 4 * x * y],
                               rtol=1e-5)
    cfg = dataclasses.replace(TINY, z_ray_input=True)
    params = init(jax.random.key(0), cfg)
    params["pose_decoder"]["z"]["ray"]["w"] = params["pose_decoder"]["z"]["ray"]["w"] + 0.5  # as if trained
    rgb, pe1, obj = _inputs(cfg, 2)
    pe2 = pe1 + jnp.asarray([0.3, -0.2], pe1.dtype)  # the same crops elsewhere in the image
    a, b = apply(params, cfg, rgb, pe1, obj), apply(params, cfg, rgb, pe2, obj)
    assert float(jnp.max(jnp.abs(a["z_logits"] - b["z_logits"]))) > 1e-4
    # the new input feeds the depth head alone
    np.testing.assert_array_equal(np.asarray(a["rot_emb"]), np.asarray(
        apply({**params, "pose_decoder": {**params["pose_decoder"], "z": {
            k: v for k, v in params["pose_decoder"]["z"].items() if k != "ray"}}},
              dataclasses.replace(cfg, z_ray_input=False), rgb, pe1, obj)["rot_emb"]))
    with pytest.raises(ValueError, match="z_ray_input needs use_pe"):
        dataclasses.replace(TINY, z_ray_input=True, use_pe=False)


def test_z_scale_input_reads_the_crops_angular_size_and_moves_only_the_depth():
    """scale_features: the log of the crop's angular side (side / f for a square crop, whatever
    its place in the image and its quarter turns) minus the reference; with z_scale_input the
    depth logits see how large an angle the same crop spans; the rotation embedding does not."""
    from sc6d_jax.geometry import crop_transform, pe_map, turn_pe
    from sc6d_jax.model._pose_decoder import SCALE_LOG_REF, scale_features

    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    for centre, side in (((570.0, 40.0), 100.0), ((320.0, 240.0), 300.0)):
        pe = np.asarray(pe_map(K, crop_transform(np.array(centre), side, 32), 32))[None]
        want = np.log(side / 500.0) - SCALE_LOG_REF
        for k in range(4):
            np.testing.assert_allclose(np.asarray(scale_features(np.asarray(turn_pe(pe, k))))[0], [want], atol=1e-4)
    cfg = dataclasses.replace(TINY, z_scale_input=True)
    params = init(jax.random.key(0), cfg)
    params["pose_decoder"]["z"]["scale"]["w"] = params["pose_decoder"]["z"]["scale"]["w"] + 0.5  # as if trained
    rgb, pe1, obj = _inputs(cfg, 2)
    pe2 = pe1 * 1.5  # the same crops, a wider angle
    a, b = apply(params, cfg, rgb, pe1, obj), apply(params, cfg, rgb, pe2, obj)
    assert float(jnp.max(jnp.abs(a["z_logits"] - b["z_logits"]))) > 1e-4
    np.testing.assert_array_equal(np.asarray(a["rot_emb"]), np.asarray(
        apply({**params, "pose_decoder": {**params["pose_decoder"], "z": {
            k: v for k, v in params["pose_decoder"]["z"].items() if k != "scale"}}},
              dataclasses.replace(cfg, z_scale_input=False), rgb, pe1, obj)["rot_emb"]))
    with pytest.raises(ValueError, match="z_scale_input needs use_pe"):
        dataclasses.replace(TINY, z_scale_input=True, use_pe=False)


def test_pose_downsample_gives_the_heads_a_map_twice_the_size_per_step():
    """64-px crops: features 16x16; the heads' conv reads 4x4 -> 2x2 (pose_downsample=2), 8x8 ->
    4x4 (1) or 16x16 -> 8x8 (0), so the flattened input of each head's FC layer grows four times
    per step; the other layers keep their shapes (and, from one key, their values)."""
    base = dataclasses.replace(TINY, crop_size=64)
    p2 = init(jax.random.key(0), base)
    pw = base.pose_width
    assert p2["pose_decoder"]["rot"]["fc"]["w"].shape[0] == 2 * 2 * pw
    rgb, pe, obj = _inputs(base, 2)
    for pd, side in ((1, 4), (0, 8)):
        cfg = dataclasses.replace(base, pose_downsample=pd)
        p = init(jax.random.key(0), cfg)
        assert p["pose_decoder"]["rot"]["fc"]["w"].shape[0] == side * side * pw
        for k in ("down1", "down2", "dilated"):
            for a, b in zip(jax.tree.leaves(p2["pose_decoder"][k]), jax.tree.leaves(p["pose_decoder"][k])):
                np.testing.assert_array_equal(a, b)
        out = apply(p, cfg, rgb, pe, obj)
        assert np.isfinite(np.asarray(out["z_logits"])).all()


def test_paper_model_size():
    """The paper's configuration (ResNet34, 256 px, one object) has about 38 M parameters (REFERENCE)."""
    cfg = ModelConfig()
    params = init(jax.random.key(0), cfg)
    n = sum(int(np.prod(x.shape)) for x in jax.tree.leaves(params))
    assert 30e6 < n < 45e6, n


def test_apply_validates_inputs():
    params = init(jax.random.key(0), TINY)
    rgb, pe, obj = _inputs(TINY, 2)
    with pytest.raises(ValueError, match="rgb"):
        apply(params, TINY, rgb[:, :16], pe, obj)
    with pytest.raises(ValueError, match="pe"):
        apply(params, TINY, rgb, None, obj)
    with pytest.raises(ValueError, match="obj_idx"):
        apply(params, TINY, rgb, pe, obj[:1])


# ----------------------------------------------------------------------------- params and forward


def test_init_is_deterministic():
    a = init(jax.random.key(7), TINY)
    b = init(jax.random.key(7), TINY)
    c = init(jax.random.key(8), TINY)
    assert jax.tree.structure(a) == jax.tree.structure(b)
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        assert x.dtype == y.dtype and np.array_equal(np.asarray(x), np.asarray(y))
    assert any(not np.array_equal(np.asarray(x), np.asarray(y)) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(c)))
    assert count_params(a) == count_params(b) > 0


@pytest.fixture(scope="module")
def tiny_forward():
    params = init(jax.random.key(0), TINY)
    rgb, pe, obj = _inputs(TINY, 3)
    fwd = jax.jit(apply, static_argnums=1)
    return params, fwd, rgb, pe, obj, fwd(params, TINY, rgb, pe, obj)


def test_forward_values_finite_and_unit_embeddings(tiny_forward):
    _, _, _, _, _, out = tiny_forward
    for v in out.values():
        assert np.all(np.isfinite(np.asarray(v)))
    np.testing.assert_allclose(np.linalg.norm(np.asarray(out["rot_emb"]), axis=-1), 1.0, rtol=1e-5)


def test_per_object_decoders_are_selected_per_sample(tiny_forward):
    """A sample's outputs depend only on its own image and object (GroupNorm is per sample)."""
    params, fwd, rgb, pe, obj, out = tiny_forward
    i = 1
    other = jnp.asarray([(int(obj[i]) + 1) % TINY.n_objects], jnp.int32)
    single = fwd(params, TINY, rgb[i : i + 1], pe[i : i + 1], obj[i : i + 1])
    np.testing.assert_allclose(single["z_logits"][0], out["z_logits"][i], rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(single["mask_logit"][0], out["mask_logit"][i], rtol=1e-4, atol=1e-5)
    swapped = fwd(params, TINY, rgb[i : i + 1], pe[i : i + 1], other)
    assert not np.allclose(swapped["mask_logit"][0], out["mask_logit"][i], atol=1e-6)


def test_uint8_and_float_rgb_agree(tiny_forward):
    params, fwd, rgb, pe, obj, _ = tiny_forward
    rgb8 = jnp.asarray(np.round(np.asarray(rgb) * 255), jnp.uint8)
    a = fwd(params, TINY, rgb8, pe, obj)
    b = fwd(params, TINY, rgb8.astype(jnp.float32) / 255.0, pe, obj)
    np.testing.assert_allclose(a["z_logits"], b["z_logits"], rtol=1e-5, atol=1e-6)


# ----------------------------------------------------------------------------- rotation heads


@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 2**16), n_obj=st.sampled_from([1, 2, 5]))
def test_so3_embeddings_are_unit_norm(seed, n_obj):
    cfg = dataclasses.replace(TINY, n_objects=n_obj)
    params = init(jax.random.key(seed), cfg)
    R = random_rotations(jax.random.key(seed + 1), 6)
    for obj in (0, jnp.arange(6) % n_obj):
        e = encode_rotations(params, cfg, R, obj)
        assert e.shape == (6, cfg.emb_dim)
        np.testing.assert_allclose(np.linalg.norm(np.asarray(e), axis=-1), 1.0, rtol=1e-5)


@pytest.mark.parametrize("rot_head", ["so3", "ipdf"])
@pytest.mark.parametrize("n_obj", [1, 2, 6])
def test_shared_and_per_sample_candidates_agree(rot_head, n_obj):
    """The shared-candidate fast paths equal the generic per-sample path (and the direct formula)."""
    cfg = dataclasses.replace(TINY, n_objects=n_obj, rot_head=rot_head, ipdf_pe_freqs=2)
    params = init(jax.random.key(1), cfg)
    b, q = 4, 9
    img = jax.random.normal(jax.random.key(2), (b, cfg.emb_dim))
    out = {"rot_emb": img / jnp.linalg.norm(img, axis=-1, keepdims=True)}
    obj = jnp.asarray([0, n_obj - 1, 1 % n_obj, 0], jnp.int32)
    R = random_rotations(jax.random.key(3), q)
    shared = rotation_logits(params, cfg, out, R, obj, tau=0.1)
    per = rotation_logits(params, cfg, out, jnp.broadcast_to(R, (b, q, 3, 3)), obj, tau=0.1)
    np.testing.assert_allclose(shared, per, rtol=1e-5, atol=1e-5)
    if rot_head == "so3":
        emb = encode_rotations(params, cfg, jnp.broadcast_to(R, (b, q, 3, 3)), obj[:, None])
        direct = jnp.einsum("be,bqe->bq", out["rot_emb"], emb) / 0.1
        np.testing.assert_allclose(shared, direct, rtol=1e-5, atol=1e-5)
        assert np.all(np.abs(np.asarray(shared)) <= 10.0 + 1e-4)


def test_encode_rotations_rejects_ipdf_and_bad_shapes():
    cfg = dataclasses.replace(TINY, rot_head="ipdf")
    with pytest.raises(ValueError, match="so3"):
        encode_rotations(init(jax.random.key(0), cfg), cfg, jnp.eye(3), 0)
    params = init(jax.random.key(0), TINY)
    with pytest.raises(ValueError, match="3, 3"):
        encode_rotations(params, TINY, jnp.zeros((4, 9)), 0)
    out = {"rot_emb": jnp.ones((2, TINY.emb_dim))}
    with pytest.raises(ValueError, match="R_candidates"):
        rotation_logits(params, TINY, out, jnp.zeros((3, 3, 3, 3)), jnp.zeros(2, jnp.int32))


# ----------------------------------------------------------------------------- weight loading


def _torchvision_file(path, cfg: ModelConfig, rng, extra: dict | None = None):
    """A torchvision-style ResNet state dict (OIHW convs + BN + fc) for cfg's backbone."""
    blocks, _ = BACKBONES[cfg.backbone]
    widths = cfg.stage_widths
    d = {"conv1.weight": rng.normal(size=(widths[0], 3, cfg.stem_kernel, cfg.stem_kernel)).astype(np.float32)}
    d.update({"bn1.weight": np.ones(widths[0]), "bn1.running_mean": np.zeros(widths[0]), "fc.weight": np.zeros((10, widths[-1]))})
    cin = widths[0]
    for s, (n, c) in enumerate(zip(blocks, widths)):
        for i in range(n):
            pre = f"layer{s + 1}.{i}"
            d[f"{pre}.conv1.weight"] = rng.normal(size=(c, cin, 3, 3)).astype(np.float32)
            d[f"{pre}.conv2.weight"] = rng.normal(size=(c, c, 3, 3)).astype(np.float32)
            d[f"{pre}.bn2.bias"] = np.zeros(c)
            if i == 0 and (s > 0 or cin != c):
                d[f"{pre}.downsample.0.weight"] = rng.normal(size=(c, cin, 1, 1)).astype(np.float32)
                d[f"{pre}.downsample.1.weight"] = np.ones(c)
            cin = c
    d.update(extra or {})
    np.savez(path, **d)
    return d


def test_load_resnet_weights(tmp_path):
    cfg = dataclasses.replace(TINY, backbone="resnet18")
    params = init(jax.random.key(0), cfg)
    d = _torchvision_file(tmp_path / "r18.npz", cfg, np.random.default_rng(0))
    new = load_resnet_weights(params, tmp_path / "r18.npz")
    bb = new["backbone"]
    stem = np.asarray(bb["stem"]["conv"]["w"])
    np.testing.assert_array_equal(stem[:, :, :3, :], d["conv1.weight"].transpose(2, 3, 1, 0))
    np.testing.assert_array_equal(stem[:, :, 3:, :], np.asarray(params["backbone"]["stem"]["conv"]["w"])[:, :, 3:, :])
    np.testing.assert_array_equal(bb["layer2"][1]["conv2"]["conv"]["w"], d["layer2.1.conv2.weight"].transpose(2, 3, 1, 0))
    np.testing.assert_array_equal(bb["layer3"][0]["down"]["conv"]["w"], d["layer3.0.downsample.0.weight"].transpose(2, 3, 1, 0))
    # GroupNorm params, the decoders and the input params are untouched
    np.testing.assert_array_equal(bb["layer1"][0]["conv1"]["gn"]["scale"], params["backbone"]["layer1"][0]["conv1"]["gn"]["scale"])
    np.testing.assert_array_equal(bb["layer2"][1]["conv2"]["gn"]["scale"], 1.0)  # residual branches on
    np.testing.assert_array_equal(params["backbone"]["layer2"][1]["conv2"]["gn"]["scale"], 0.0)  # input untouched
    assert new["decoder"] is params["decoder"]
    assert not np.array_equal(np.asarray(params["backbone"]["layer2"][1]["conv2"]["conv"]["w"]), bb["layer2"][1]["conv2"]["conv"]["w"])
    out = jax.jit(apply, static_argnums=1)(new, cfg, *_inputs(cfg, 2))
    assert np.all(np.isfinite(np.asarray(out["z_logits"])))


def test_load_resnet_weights_errors(tmp_path):
    cfg18 = dataclasses.replace(TINY, backbone="resnet18")
    cfg10 = dataclasses.replace(TINY, backbone="resnet10")
    rng = np.random.default_rng(1)
    _torchvision_file(tmp_path / "r18.npz", cfg18, rng)
    p10 = init(jax.random.key(0), cfg10)
    with pytest.raises(FileNotFoundError):
        load_resnet_weights(p10, tmp_path / "absent.npz")
    with pytest.raises(ValueError, match="no place"):
        load_resnet_weights(p10, tmp_path / "r18.npz")
    loaded = load_resnet_weights(p10, tmp_path / "r18.npz", strict=False)  # first block of each stage
    assert loaded["backbone"]["layer4"][0]["conv1"]["conv"]["w"].shape == (3, 3, 4 * TINY.width, 8 * TINY.width)
    with pytest.raises(ValueError, match="missing"):
        load_resnet_weights(init(jax.random.key(0), dataclasses.replace(TINY, backbone="resnet34")), tmp_path / "r18.npz")
    wide = dataclasses.replace(cfg18, width=16)
    with pytest.raises(ValueError, match="shape"):
        load_resnet_weights(init(jax.random.key(0), wide), tmp_path / "r18.npz")


def test_conv_impls_give_the_same_network_outputs():
    """lax, im2col and auto are interchangeable for a whole forward pass (multi-object decoders)."""
    rgb, pe, obj = _inputs(TINY, 3, seed=5)
    outs = []
    for impl in ("lax", "im2col", "auto"):
        cfg = dataclasses.replace(TINY, conv_impl=impl)
        params = init(jax.random.key(3), cfg)
        outs.append(jax.jit(apply, static_argnums=1)(params, cfg, rgb, pe, obj))
    for o in outs[1:]:
        for k in ("rot_emb", "delta_xy", "z_logits", "mask_logit"):
            np.testing.assert_allclose(o[k], outs[0][k], rtol=2e-3, atol=2e-4)
