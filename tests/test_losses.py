"""Tests of the SC6D losses (sc6d_jax.model._losses)."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sc6d_jax.geometry import random_rotations, rebase_negatives, sample_rotation_deltas, z_bin_centers
from sc6d_jax.model import (
    LossConfig,
    ModelConfig,
    bce_with_logits,
    candidate_logits,
    cross_entropy,
    downsample_mask,
    encode_rotations,
    focal_loss,
    info_nce,
    init,
    loss_fn,
    predict_z,
)

CFG = ModelConfig(
    n_objects=2, crop_size=32, backbone="tiny", width=8, decoder_width=16, feat_dim=8, emb_dim=8,
    n_z_bins=16, pose_width=8, head_hidden=16, so3_hidden=16, ipdf_hidden=16, gn_groups=4,
    conv_impl="lax",  # as the cpu and tiny presets: compiles ~40 % faster than im2col (test_model compares them)
)
Z_RANGE = (0.2, 1.0)


def _batch(cfg: ModelConfig, b: int = 4, seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    s = cfg.crop_size
    return {
        "rgb": rng.integers(0, 256, (b, s, s, 3), dtype=np.uint8),
        "pe": rng.uniform(-0.5, 0.5, (b, s, s, 2)).astype(np.float32),
        "mask_visib": (rng.uniform(size=(b, s, s)) > 0.5).astype(np.uint8),
        "R_allo": np.asarray(random_rotations(jax.random.key(seed), b)),
        "delta_xy": rng.uniform(-0.1, 0.1, (b, 2)).astype(np.float32),
        "delta_z": rng.uniform(*Z_RANGE, b).astype(np.float32),
        "obj_idx": (np.arange(b) % cfg.n_objects).astype(np.int32),
    }


def _apply_seeing_the_pose_decoder(p, mcfg, batch):
    """(apply's outputs, the pose decoder's own outputs in that call) for a check by hand."""
    from sc6d_jax.model import apply
    from sc6d_jax.model._pose_decoder import pose_decoder

    import sc6d_jax.model._network as net

    inner = {}

    def spy(*args, **kw):
        inner["res"] = pose_decoder(*args, **kw)
        return inner["res"]

    orig = net.pose_decoder
    net.pose_decoder = spy
    try:
        out = apply(p, mcfg, batch["rgb"], batch["pe"], batch["obj_idx"])
    finally:
        net.pose_decoder = orig
    return out, inner["res"]


def test_info_nce_hand_computed():
    logits = jnp.asarray([[2.0, 1.0, 0.0], [0.0, 3.0, -1.0]])
    expected = (np.log(np.exp(2) + np.exp(1) + 1) - 2 + np.log(1 + np.exp(3) + np.exp(-1)) - 0) / 2
    np.testing.assert_allclose(info_nce(logits), expected, rtol=1e-6)


def test_focal_and_ce_equal_the_formulas():
    rng = np.random.default_rng(0)
    logits = rng.normal(size=(5, 7)) * 3
    labels = rng.integers(0, 7, 5)
    p = np.exp(logits) / np.exp(logits).sum(-1, keepdims=True)
    pt = p[np.arange(5), labels]
    np.testing.assert_allclose(
        focal_loss(jnp.asarray(logits), jnp.asarray(labels), 0.5, 2.0), np.mean(-0.5 * (1 - pt) ** 2 * np.log(pt)), rtol=1e-5
    )
    np.testing.assert_allclose(focal_loss(jnp.asarray(logits), jnp.asarray(labels), 1.0, 0.0), np.mean(-np.log(pt)), rtol=1e-5)
    np.testing.assert_allclose(cross_entropy(jnp.asarray(logits), jnp.asarray(labels)), np.mean(-np.log(pt)), rtol=1e-5)


def test_bce_with_logits_matches_naive_formula():
    x = np.array([-30.0, -2.0, 0.0, 1.5, 40.0])
    y = np.array([0.0, 1.0, 0.5, 0.25, 1.0])
    sig = 1 / (1 + np.exp(-x))
    naive = -(y * np.log(np.clip(sig, 1e-300, 1)) + (1 - y) * np.log(np.clip(1 - sig, 1e-300, 1)))
    np.testing.assert_allclose(bce_with_logits(jnp.asarray(x), jnp.asarray(y)), naive.mean(), rtol=1e-5, atol=1e-6)


def test_downsample_mask():
    m = np.zeros((1, 8, 8), np.uint8)
    m[0, :4, :2] = 255  # block (0,0): half foreground
    m[0, 6, 6] = 1  # block (1,1): pixel (6,6) = nearest sample
    area = np.asarray(downsample_mask(jnp.asarray(m), 4, "area"))
    np.testing.assert_allclose(area[0], [[0.5, 0.0], [0.0, 1 / 16]])
    near = np.asarray(downsample_mask(jnp.asarray(m), 4, "nearest"))
    np.testing.assert_array_equal(near[0], [[0.0, 0.0], [0.0, 1.0]])
    with pytest.raises(ValueError):
        downsample_mask(jnp.zeros((1, 6, 6)), 4)


def test_predict_z_modes():
    k = 5
    centers = np.asarray(z_bin_centers(k, *Z_RANGE))
    logits = np.array([[0.0, 5.0, 1.0, 0.0, -1.0]], np.float32)
    out = {"z_logits": jnp.asarray(logits)}
    np.testing.assert_allclose(predict_z(out, LossConfig(z_mode="classification"), Z_RANGE), centers[1:2], rtol=1e-6)
    p = np.exp(logits[0]) / np.exp(logits[0]).sum()
    np.testing.assert_allclose(predict_z(out, LossConfig(z_mode="expectation"), Z_RANGE), [p @ centers], rtol=1e-5)
    np.testing.assert_allclose(predict_z(out, LossConfig(z_mode="regression"), Z_RANGE), [0.2 + 0.8 * 0.0], atol=1e-7)


def test_loss_config_validation():
    for bad in ({"z_mode": "ordinal"}, {"z_loss": "mse"}, {"tau": 0.0}, {"n_negatives": 0}, {"w_xy": -1.0}, {"mask_downsample": "max"}):
        with pytest.raises(ValueError):
            LossConfig(**bad)


@pytest.fixture(scope="module")
def params():
    return init(jax.random.key(0), CFG)


def _out(b: int, seed: int = 1) -> dict:
    e = jax.random.normal(jax.random.key(seed), (b, CFG.emb_dim))
    return {"rot_emb": e / jnp.linalg.norm(e, axis=-1, keepdims=True)}


def test_info_nce_of_candidates_hand_computed(params):
    """Authors' negatives: the loss equals logsumexp over [gt, deltas @ gt] computed by hand."""
    b, q, tau = 3, 6, 0.1
    lcfg = LossConfig(n_negatives=q, tau=tau)
    out = _out(b)
    R = jnp.asarray(random_rotations(jax.random.key(5), b))
    obj = jnp.asarray([0, 1, 1], jnp.int32)
    key = jax.random.key(9)
    logits = candidate_logits(params, CFG, lcfg, out, R, obj, key)
    assert logits.shape == (b, q + 1)
    deltas = np.asarray(sample_rotation_deltas(key, q))
    loss = 0.0
    for i in range(b):
        cands = np.concatenate([np.asarray(R[i])[None], deltas @ np.asarray(R[i])])
        emb = np.asarray(encode_rotations(params, CFG, jnp.asarray(cands), int(obj[i])))
        lg = emb @ np.asarray(out["rot_emb"][i]) / tau
        np.testing.assert_allclose(logits[i], lg, rtol=1e-4, atol=1e-4)
        loss += np.log(np.exp(lg).sum()) - lg[0]
    np.testing.assert_allclose(info_nce(logits), loss / b, rtol=1e-5)


@pytest.mark.parametrize("per_sample", [False, True])
@pytest.mark.parametrize("rebase", [False, True])
def test_negative_modes(params, per_sample, rebase):
    b, q = 4, 5
    lcfg = LossConfig(n_negatives=q, per_sample_negatives=per_sample, rebase_negatives=rebase)
    out = _out(b)
    R = jnp.asarray(random_rotations(jax.random.key(2), b))
    obj = jnp.asarray([0, 1, 0, 1], jnp.int32)
    logits = candidate_logits(params, CFG, lcfg, out, R, obj, jax.random.key(3))
    assert logits.shape == (b, q + 1)
    gt = jnp.einsum("be,be->b", out["rot_emb"], encode_rotations(params, CFG, R, obj)) / lcfg.tau
    np.testing.assert_allclose(logits[:, 0], gt, rtol=1e-4, atol=1e-4)
    # shared negatives without rebasing: the same Q rotations for every sample
    if not per_sample and not rebase:
        deltas = sample_rotation_deltas(jax.random.key(3), q)
        for i in range(b):
            e = encode_rotations(params, CFG, deltas, int(obj[i]))
            np.testing.assert_allclose(logits[i, 1:], e @ out["rot_emb"][i] / lcfg.tau, rtol=1e-4, atol=1e-4)
    if per_sample:  # independent rolls per sample: negatives of two same-object samples differ
        shared = candidate_logits(params, CFG, dataclasses.replace(lcfg, per_sample_negatives=False), out, R, obj, jax.random.key(3))
        assert not np.allclose(logits[:, 1:], shared[:, 1:])


@pytest.fixture(scope="module")
def grad_fn():
    return jax.jit(jax.value_and_grad(loss_fn, has_aux=True), static_argnums=(1, 2, 5))


@pytest.mark.parametrize(
    "lcfg,mcfg",
    [
        (LossConfig(n_negatives=8), CFG),
        (LossConfig(n_negatives=8, z_mode="regression", rebase_negatives=False, mask_downsample="nearest"),
         dataclasses.replace(CFG, use_pe=False, rot_head="ipdf")),
    ],
    ids=["paper", "ablations"],
)
def test_loss_fn_terms_and_finite_gradients(grad_fn, lcfg, mcfg):
    p = init(jax.random.key(0), mcfg)
    batch = _batch(mcfg)
    if not mcfg.use_pe:
        del batch["pe"]
    (loss, aux), grads = grad_fn(p, mcfg, lcfg, batch, jax.random.key(1), Z_RANGE)
    total = lcfg.w_rot * aux["loss_rot"] + lcfg.w_xy * aux["loss_xy"] + lcfg.w_z * aux["loss_z"] + lcfg.w_mask * aux["loss_mask"]
    np.testing.assert_allclose(loss, total, rtol=1e-5)
    for k in ("loss_rot", "loss_xy", "loss_z", "loss_mask"):
        assert np.isfinite(float(aux[k])) and float(aux[k]) >= 0, k
    assert jax.tree.structure(grads) == jax.tree.structure(p)
    leaves = jax.tree.leaves(grads)
    assert all(np.all(np.isfinite(np.asarray(g))) for g in leaves)
    assert sum(float(jnp.sum(jnp.abs(g))) for g in leaves) > 0
    # deterministic: same inputs and key -> same loss, bit for bit
    (loss2, _), _ = grad_fn(p, mcfg, lcfg, batch, jax.random.key(1), Z_RANGE)
    assert float(loss) == float(loss2)


def test_z_loss_variants_and_switches_eager(params):
    """ce vs focal changes exactly the z term; batch validation (no jit: cheap for a tiny model)."""
    batch = _batch(CFG, b=2)
    key = jax.random.key(4)
    base = LossConfig(n_negatives=4)
    _, a_focal = loss_fn(params, CFG, base, batch, key, Z_RANGE)
    _, a_ce = loss_fn(params, CFG, dataclasses.replace(base, z_loss="ce"), batch, key, Z_RANGE)
    for k in ("loss_rot", "loss_xy", "loss_mask"):
        np.testing.assert_allclose(a_focal[k], a_ce[k], rtol=1e-6)
    # with alpha 0.5, gamma 2: focal = 0.5 (1-p)^2 CE per sample < CE
    assert float(a_focal["loss_z"]) < float(a_ce["loss_z"])
    with pytest.raises(ValueError, match="missing"):
        loss_fn(params, CFG, base, {k: v for k, v in batch.items() if k != "R_allo"}, key, Z_RANGE)
    bad = dict(batch, delta_xy=np.zeros((2, 3), np.float32))
    with pytest.raises(ValueError, match="delta_xy"):
        loss_fn(params, CFG, base, bad, key, Z_RANGE)


# ----------------------------------------------------------------------------- the cpu recipe's terms
def test_focal_normalised_depth_code_round_trips_and_removes_the_focal_length():
    """The code delta_z * F_REF / f is the same for two cameras that see the same crop content."""
    from sc6d_jax.model import F_REF, code_to_delta_z, z_code

    lcfg = LossConfig(z_norm="focal")
    K = np.array([np.diag([500.0, 500.0, 1.0]), np.diag([700.0, 700.0, 1.0])], np.float32)
    # the same object at the same distance: its image (and the crop box around it) grows with f,
    # so both crops show the same thing, yet delta_z = t_z s_B / S differs by 700/500
    tz, side, S = np.array([1000.0, 1000.0]), np.array([100.0, 140.0]), 64
    dz = tz * side / S
    code = np.asarray(z_code(jnp.asarray(dz, jnp.float32), K, lcfg))
    np.testing.assert_allclose(code[0], code[1], rtol=1e-6)  
    np.testing.assert_allclose(code[0], dz[0] * F_REF / 500.0, rtol=1e-6)
    np.testing.assert_allclose(code_to_delta_z(code, K, lcfg), dz, rtol=1e-6)
    plain = LossConfig()
    np.testing.assert_allclose(z_code(jnp.asarray(dz), K, plain), dz)
    with pytest.raises(ValueError, match="needs the image intrinsics"):
        z_code(jnp.asarray(dz), None, lcfg)


def test_log_bins_decode_and_gaussian_labels():
    from sc6d_jax.model import gaussian_bin_targets

    lcfg = LossConfig(z_bins="log", z_mode="classification")
    n = 9
    logits = jnp.full((1, n), -30.0).at[0, 4].set(30.0)  # the middle bin of 9
    z = float(predict_z({"z_logits": logits}, lcfg, (1.0, 4.0))[0])
    assert z == pytest.approx(2.0, rel=1e-5)  # the geometric middle of [1, 4]
    lin = float(predict_z({"z_logits": logits}, dataclasses.replace(lcfg, z_bins="linear"), (1.0, 4.0))[0])
    assert lin == pytest.approx(2.5, rel=1e-5)
    soft = np.asarray(gaussian_bin_targets(jnp.array([3.5]), n, 1.0))[0]
    assert soft.sum() == pytest.approx(1.0, abs=1e-6)
    assert soft[3] == pytest.approx(soft[4]) and soft[3] > soft[2] > soft[1]
    np.testing.assert_allclose(np.sum(soft * np.arange(n)), 3.5, atol=1e-3)


def test_local_negatives_lie_in_their_angle_band(params):
    from sc6d_jax.geometry import geodesic_angle
    from sc6d_jax.model import local_rotation_deltas

    d = local_rotation_deltas(jax.random.key(0), (4, 50), 5.0, 20.0)
    assert d.shape == (4, 50, 3, 3)
    np.testing.assert_allclose(np.asarray(d @ jnp.swapaxes(d, -1, -2)), np.broadcast_to(np.eye(3), d.shape), atol=1e-5)
    ang = np.degrees(np.asarray(geodesic_angle(d, jnp.broadcast_to(jnp.eye(3), d.shape))))
    assert ang.min() >= 5.0 - 1e-3 and ang.max() <= 20.0 + 1e-3
    # they add M columns to the candidate logits, after the ground truth and the shared set
    batch = _batch(CFG, b=2)
    lcfg = LossConfig(n_negatives=6, rebase_negatives=False, n_local_negatives=5)
    from sc6d_jax.model import apply

    out = jax.jit(apply, static_argnums=1)(params, CFG, batch["rgb"], batch["pe"], batch["obj_idx"])  # eager: 4x slower
    logits = candidate_logits(params, CFG, lcfg, out, jnp.asarray(batch["R_allo"]), jnp.asarray(batch["obj_idx"]), jax.random.key(2))
    assert logits.shape == (2, 1 + 6 + 5)


def test_cpu_recipe_loss_is_finite_and_uses_K(grad_fn):
    mcfg = dataclasses.replace(CFG, mask_gate=True)
    lcfg = LossConfig(n_negatives=8, rebase_negatives=False, z_norm="focal", z_bins="log", z_loss="gauss",
                      z_label_sigma=1.5, w_z_l1=1.0, n_local_negatives=4)
    p = init(jax.random.key(0), mcfg)
    batch = _batch(mcfg)
    batch["K"] = np.broadcast_to(np.diag([600.0, 600.0, 1.0]).astype(np.float32), (4, 3, 3)).copy()
    (loss, aux), grads = grad_fn(p, mcfg, lcfg, batch, jax.random.key(1), Z_RANGE)
    assert np.isfinite(float(loss)) and float(aux["z_rel_err"]) >= 0
    assert all(np.all(np.isfinite(np.asarray(g))) for g in jax.tree.leaves(grads))
    with pytest.raises(ValueError, match="needs the image intrinsics"):
        loss_fn(p, mcfg, lcfg, {k: v for k, v in batch.items() if k != "K"}, jax.random.key(1), Z_RANGE)
    with pytest.raises(ValueError, match="z_norm"):
        LossConfig(z_norm="metric")
    with pytest.raises(ValueError, match="local_min_deg"):
        LossConfig(local_min_deg=40.0, local_max_deg=30.0)


def test_turn_negatives_are_the_ground_truth_turned_about_the_object_axes(params):
    from sc6d_jax.geometry import geodesic_angle
    from sc6d_jax.model import apply, rotation_logits
    from sc6d_jax.model._losses import axis_turns

    T = np.asarray(axis_turns(), np.float64)
    assert T.shape == (9, 3, 3)
    np.testing.assert_allclose(T @ np.swapaxes(T, -1, -2), np.broadcast_to(np.eye(3), T.shape), atol=1e-6)
    np.testing.assert_allclose(np.linalg.det(T), 1.0, atol=1e-6)
    ang = np.degrees(np.asarray(geodesic_angle(jnp.asarray(T), jnp.broadcast_to(jnp.eye(3), T.shape))))
    np.testing.assert_allclose(np.sort(ang), [90] * 6 + [180] * 3, atol=1e-3)
    for k, axis in enumerate(np.repeat(np.eye(3), 3, axis=0)):  # each turn keeps its own axis fixed
        np.testing.assert_allclose(T[k] @ axis, axis, atol=1e-6)
    assert len({tuple(np.round(t, 6).ravel()) for t in T}) == 9

    batch = _batch(CFG, b=3)
    R = jnp.asarray(batch["R_allo"])
    lcfg = LossConfig(n_negatives=6, rebase_negatives=False, n_local_negatives=2, turn_negatives=True)
    out = jax.jit(apply, static_argnums=1)(params, CFG, batch["rgb"], batch["pe"], batch["obj_idx"])  # eager: 4x slower
    oi = jnp.asarray(batch["obj_idx"])
    cand = jax.jit(candidate_logits, static_argnums=(1, 2))
    logits = cand(params, CFG, lcfg, out, R, oi, jax.random.key(2))
    assert logits.shape == (3, 1 + 6 + 2 + 9)
    want = rotation_logits(params, CFG, out, R[:, None] @ jnp.asarray(T, jnp.float32), oi, lcfg.tau)
    np.testing.assert_allclose(np.asarray(logits[:, -9:]), np.asarray(want), rtol=1e-5, atol=1e-5)
    # the rest is what the loss was without them (same key)
    base = cand(params, CFG, dataclasses.replace(lcfg, turn_negatives=False), out, R, oi, jax.random.key(2))
    np.testing.assert_allclose(np.asarray(logits[:, :-9]), np.asarray(base), rtol=1e-6)
    with pytest.raises(ValueError, match="turn_negatives"):
        LossConfig(turn_negatives="yes")


def test_axis_negatives_turn_the_ground_truth_about_one_object_axis(params):
    from sc6d_jax.geometry import geodesic_angle
    from sc6d_jax.model import apply, axis_ring_deltas, rotation_logits

    d = np.asarray(axis_ring_deltas(jax.random.key(0), (4, 60), 30.0), np.float64)
    assert d.shape == (4, 60, 3, 3)
    np.testing.assert_allclose(d @ np.swapaxes(d, -1, -2), np.broadcast_to(np.eye(3), d.shape), atol=1e-5)
    np.testing.assert_allclose(np.linalg.det(d), 1.0, atol=1e-5)
    fixed = np.abs(np.einsum("...ii->...i", d) - 1.0) < 1e-5  # the axis it turns about is left alone
    assert np.all(fixed.sum(-1) >= 1) and set(np.argmax(fixed, -1).ravel().tolist()) == {0, 1, 2}
    ang = np.degrees(np.asarray(geodesic_angle(jnp.asarray(d, jnp.float32), jnp.broadcast_to(jnp.eye(3), d.shape))))
    assert ang.min() >= 30.0 - 1e-2 and ang.max() <= 180.0 + 1e-3 and ang.max() > 150.0
    # M more columns at the end, R_gt @ delta scored as any candidate; the rest as without them
    batch = _batch(CFG, b=3)
    R, oi = jnp.asarray(batch["R_allo"]), jnp.asarray(batch["obj_idx"])
    lcfg = LossConfig(n_negatives=6, rebase_negatives=False, n_axis_negatives=5)
    out = jax.jit(apply, static_argnums=1)(params, CFG, batch["rgb"], batch["pe"], batch["obj_idx"])
    cand = jax.jit(candidate_logits, static_argnums=(1, 2))
    logits = cand(params, CFG, lcfg, out, R, oi, jax.random.key(2))
    assert logits.shape == (3, 1 + 6 + 5)
    ring = axis_ring_deltas(jax.random.fold_in(jax.random.key(2), 2), (3, 5), 30.0)
    want = rotation_logits(params, CFG, out, R[:, None] @ ring, oi, lcfg.tau)
    np.testing.assert_allclose(np.asarray(logits[:, -5:]), np.asarray(want), rtol=1e-5, atol=1e-5)
    base = cand(params, CFG, dataclasses.replace(lcfg, n_axis_negatives=0), out, R, oi, jax.random.key(2))
    np.testing.assert_allclose(np.asarray(logits[:, :-5]), np.asarray(base), rtol=1e-6)
    for bad in ({"n_axis_negatives": -1}, {"axis_min_deg": 0.0}, {"axis_min_deg": 180.0}):
        with pytest.raises(ValueError, match="axis"):
            LossConfig(**bad)


def test_rotation_readout_reads_the_embedding_per_object_and_its_loss():
    """model.rot_readout adds a per-object linear map of the unit embedding to 6 numbers (the
    other parameters are drawn as without it); loss.w_rot_readout is the mean squared distance
    to the ground truth's first two columns."""
    from sc6d_jax.model import apply

    mcfg = dataclasses.replace(CFG, rot_readout=True)
    p0, p = init(jax.random.key(0), CFG), init(jax.random.key(0), mcfg)
    assert set(p) == set(p0) | {"rot_readout"} and p["rot_readout"]["w"].shape == (CFG.n_objects, CFG.emb_dim, 6)
    for a, b in zip(jax.tree.leaves(p0), jax.tree.leaves({k: v for k, v in p.items() if k != "rot_readout"})):
        np.testing.assert_array_equal(a, b)
    batch = _batch(mcfg)
    out = jax.jit(apply, static_argnums=1)(p, mcfg, batch["rgb"], batch["pe"], batch["obj_idx"])
    w, b = np.asarray(p["rot_readout"]["w"]), np.asarray(p["rot_readout"]["b"])
    emb = np.asarray(out["rot_emb"])
    want = np.stack([emb[i] @ w[o] + b[o] for i, o in enumerate(batch["obj_idx"])])
    np.testing.assert_allclose(np.asarray(out["rot_6d"]), want, rtol=1e-5, atol=1e-6)
    lcfg = LossConfig(n_negatives=8, w_rot_readout=0.5)
    f = jax.jit(loss_fn, static_argnums=(1, 2, 5))
    loss, aux = f(p, mcfg, lcfg, batch, jax.random.key(1), Z_RANGE)
    R = np.asarray(batch["R_allo"])
    target = np.concatenate([R[:, :, 0], R[:, :, 1]], axis=1)
    np.testing.assert_allclose(float(aux["loss_rot_readout"]), np.mean(np.sum((want - target) ** 2, -1)), rtol=1e-4)
    rest = lcfg.w_rot * aux["loss_rot"] + lcfg.w_xy * aux["loss_xy"] + lcfg.w_z * aux["loss_z"] + lcfg.w_mask * aux["loss_mask"]
    np.testing.assert_allclose(float(loss), float(rest + 0.5 * aux["loss_rot_readout"]), rtol=1e-5)
    with pytest.raises(ValueError, match="model.rot_readout=True"):
        loss_fn(p0, CFG, lcfg, batch, jax.random.key(1), Z_RANGE)
    with pytest.raises(ValueError, match="w_rot_readout"):
        LossConfig(w_rot_readout=-1.0)


def _random_z_prior(p: dict) -> dict:
    """``p`` with the depth prior's parameters drawn at random (a fresh prior outputs zeros)."""
    rng = np.random.default_rng(3)
    return {**p, "z_rot": jax.tree.map(lambda a: jnp.asarray(rng.normal(size=a.shape).astype(np.float32) * 0.3), p["z_rot"])}


def test_depth_prior_from_rotation_adds_to_the_z_logits():
    """model.z_rot adds a per-object MLP of the allocentric rotation (9 -> h -> h -> n_z_bins) to
    the image's z logits; it starts at zero (a fresh prior changes nothing, the other
    parameters are drawn as without it). Its losses: the slow test below."""
    from sc6d_jax.model import apply, with_rotation_priors

    mcfg = dataclasses.replace(CFG, z_rot=True)
    p0, p = init(jax.random.key(0), CFG), init(jax.random.key(0), mcfg)
    assert set(p) == set(p0) | {"z_rot"}
    for a, b in zip(jax.tree.leaves(p0), jax.tree.leaves({k: v for k, v in p.items() if k != "z_rot"})):
        np.testing.assert_array_equal(a, b)
    assert p["z_rot"]["fc1"]["w"].shape == (CFG.n_objects, 9, CFG.head_hidden)
    assert p["z_rot"]["out"]["w"].shape == (CFG.n_objects, CFG.head_hidden, CFG.n_z_bins)
    assert not np.any(np.asarray(p["z_rot"]["out"]["w"]))
    batch = _batch(mcfg)
    out = jax.jit(apply, static_argnums=1)(p, mcfg, batch["rgb"], batch["pe"], batch["obj_idx"])
    R = jnp.asarray(batch["R_allo"])
    np.testing.assert_array_equal(np.asarray(with_rotation_priors(p, mcfg, out, R, batch["obj_idx"])["z_logits"]),
                                  np.asarray(out["z_logits"]))
    assert with_rotation_priors(p, CFG, out, R, batch["obj_idx"]) is out  # without the option: untouched

    p = _random_z_prior(p)
    zr = jax.tree.map(np.asarray, p["z_rot"])
    got = np.asarray(with_rotation_priors(p, mcfg, out, R, batch["obj_idx"])["z_logits"] - out["z_logits"])
    relu = lambda x: np.maximum(x, 0.0)
    for i, o in enumerate(np.asarray(batch["obj_idx"])):
        h = relu(np.asarray(R[i]).reshape(9) @ zr["fc1"]["w"][o] + zr["fc1"]["b"][o])
        h = relu(h @ zr["fc2"]["w"][o] + zr["fc2"]["b"][o])
        np.testing.assert_allclose(got[i], h @ zr["out"]["w"][o] + zr["out"]["b"][o], rtol=1e-4, atol=1e-4)
    with pytest.raises(ValueError, match="z_rot_noise_deg"):
        LossConfig(z_rot_noise_deg=-1.0)
    with pytest.raises(ValueError, match="z_rot_separate"):
        LossConfig(z_rot_separate=1)


@pytest.mark.slow  # ~60 s of compiles on 2 cores for an option that stays off (README: "Depth from the rotation")
def test_depth_prior_losses_joint_noisy_and_separate():
    """The loss feeds the prior the ground truth (perturbed by up to loss.z_rot_noise_deg, by the
    step key), only the depth term changes, and with loss.z_rot_separate the image head's depth
    loss is the one without the prior while the prior has its own; the gradient reaches it."""
    mcfg = dataclasses.replace(CFG, z_rot=True)
    p0, p = init(jax.random.key(0), CFG), _random_z_prior(init(jax.random.key(0), mcfg))
    batch = _batch(mcfg)
    f = jax.jit(loss_fn, static_argnums=(1, 2, 5))
    lcfg = LossConfig(n_negatives=8)
    key = jax.random.key(1)
    _, a0 = f(p0, CFG, lcfg, batch, key, Z_RANGE)
    _, a1 = f(p, mcfg, lcfg, batch, key, Z_RANGE)
    _, a2 = f(p, mcfg, dataclasses.replace(lcfg, z_rot_noise_deg=20.0), batch, key, Z_RANGE)
    _, a3 = f(p, mcfg, dataclasses.replace(lcfg, z_rot_noise_deg=20.0), batch, key, Z_RANGE)
    for k in ("loss_rot", "loss_xy", "loss_mask"):  # the prior only touches depth
        np.testing.assert_allclose(float(a1[k]), float(a0[k]), rtol=1e-5)
    assert abs(float(a1["loss_z"]) - float(a0["loss_z"])) > 1e-3  # the prior of the ground truth counts
    assert abs(float(a2["loss_z"]) - float(a1["loss_z"])) > 1e-5  # a perturbed rotation gives other logits
    assert float(a2["loss_z"]) == float(a3["loss_z"])  # the perturbation is the key's
    # trained separately: the image head's depth loss is the one without the prior, the prior
    # has its own (the same loss of its logits alone), and the total adds it with w_z
    sep = dataclasses.replace(lcfg, z_rot_separate=True)
    loss4, a4 = f(p, mcfg, sep, batch, key, Z_RANGE)
    np.testing.assert_allclose(float(a4["loss_z"]), float(a0["loss_z"]), rtol=1e-5)
    p_bias = {**p, "z_rot": {**p["z_rot"], "out": {"w": jnp.zeros_like(p["z_rot"]["out"]["w"]),
                                                  "b": jnp.zeros_like(p["z_rot"]["out"]["b"])}}}
    flat = dataclasses.replace(sep, z_loss="gauss", w_z_l1=0.0, z_mode="expectation")
    _, a5 = f(p_bias, mcfg, flat, batch, key, Z_RANGE)  # flat prior logits: cross-entropy log(n_bins)
    np.testing.assert_allclose(float(a5["loss_z_prior"]), np.log(CFG.n_z_bins), rtol=1e-5)
    assert "loss_z_prior" not in a1
    rest = sep.w_rot * a4["loss_rot"] + sep.w_xy * a4["loss_xy"] + sep.w_z * a4["loss_z"] + sep.w_mask * a4["loss_mask"]
    np.testing.assert_allclose(float(loss4), float(rest + sep.w_z * a4["loss_z_prior"]), rtol=1e-5)
    g = jax.grad(lambda q: f(q, mcfg, sep, batch, key, Z_RANGE)[0])(p)
    assert all(float(jnp.abs(x).max()) > 0 for x in jax.tree.leaves(g["z_rot"]))


def test_rotation_grid_classifier_reads_the_rotation_head_and_its_loss():
    """model.rot_cls adds a per-object linear classifier of the rotation head's hidden layer over
    a fixed grid (rot_cls_grid: proper rotations, deterministic; the other parameters are drawn
    as without it); loss.w_rot_cls is the cross-entropy against the grid rotation nearest to the
    allocentric ground truth, found here by hand."""
    from sc6d_jax.model import apply, rot_cls_grid

    G = rot_cls_grid(64)
    assert 48 <= len(G) <= 80 and np.array_equal(G, rot_cls_grid(64))
    np.testing.assert_allclose(np.einsum("kji,kjl->kil", G, G), np.broadcast_to(np.eye(3), G.shape), atol=1e-5)
    np.testing.assert_allclose(np.linalg.det(G), 1.0, atol=1e-5)
    mcfg = dataclasses.replace(CFG, rot_cls=64)
    p0, p = init(jax.random.key(0), CFG), init(jax.random.key(0), mcfg)
    assert set(p) == set(p0) | {"rot_cls"} and p["rot_cls"]["w"].shape == (CFG.n_objects, CFG.head_hidden, len(G))
    for a, b in zip(jax.tree.leaves(p0), jax.tree.leaves({k: v for k, v in p.items() if k != "rot_cls"})):
        np.testing.assert_array_equal(a, b)
    # random classifier weights, so that the logits differ between classes and objects
    rng = np.random.default_rng(5)
    p = {**p, "rot_cls": jax.tree.map(lambda a: jnp.asarray(rng.normal(size=a.shape).astype(np.float32)), p["rot_cls"])}
    batch = _batch(mcfg)
    out = jax.jit(apply, static_argnums=1)(p, mcfg, batch["rgb"], batch["pe"], batch["obj_idx"])
    assert out["rot_cls_logits"].shape == (batch["rgb"].shape[0], len(G))
    # the hidden layer the classifier reads, as the pose decoder gave it
    h = np.asarray(_apply_seeing_the_pose_decoder(p, mcfg, batch)[1][3])
    w, b = np.asarray(p["rot_cls"]["w"]), np.asarray(p["rot_cls"]["b"])
    logits = np.stack([h[i] @ w[o] + b[o] for i, o in enumerate(batch["obj_idx"])])
    np.testing.assert_allclose(np.asarray(out["rot_cls_logits"]), logits, rtol=1e-4, atol=1e-4)
    lcfg = LossConfig(n_negatives=8, w_rot_cls=0.5)
    loss, aux = jax.jit(loss_fn, static_argnums=(1, 2, 5))(p, mcfg, lcfg, batch, jax.random.key(1), Z_RANGE)
    R = np.asarray(batch["R_allo"], np.float64)
    ang = np.arccos(np.clip((np.einsum("kji,bjl->bkil", G, R).trace(axis1=2, axis2=3) - 1) / 2, -1, 1))
    nearest = np.argmin(ang, axis=1)
    ls = logits - logits.max(1, keepdims=True)
    logp = ls - np.log(np.exp(ls).sum(1, keepdims=True))
    want = -np.mean(logp[np.arange(len(nearest)), nearest])
    np.testing.assert_allclose(float(aux["loss_rot_cls"]), want, rtol=1e-4)
    rest = lcfg.w_rot * aux["loss_rot"] + lcfg.w_xy * aux["loss_xy"] + lcfg.w_z * aux["loss_z"] + lcfg.w_mask * aux["loss_mask"]
    np.testing.assert_allclose(float(loss), float(rest + 0.5 * aux["loss_rot_cls"]), rtol=1e-5)
    with pytest.raises(ValueError, match="model.rot_cls"):
        loss_fn(p0, CFG, lcfg, batch, jax.random.key(1), Z_RANGE)
    for bad in (-1, 3, 2.5):
        with pytest.raises(ValueError, match="rot_cls"):
            dataclasses.replace(CFG, rot_cls=bad)
    with pytest.raises(ValueError, match="w_rot_cls"):
        LossConfig(w_rot_cls=-1.0)
    with pytest.raises(ValueError, match="size"):
        rot_cls_grid(4)


def test_view_head_decodes_the_clean_view_from_the_rotation_head_and_its_bootstrapped_loss():
    """model.view_head=V adds a linear decoder of the rotation head's hidden layer to a (V,V,3)
    view (the other parameters are drawn as without it); loss.w_view is the mean over crops of
    the mean of each crop's largest per-pixel squared errors against view / 255, found by hand."""
    from sc6d_jax.model import view_loss

    V = 8
    mcfg = dataclasses.replace(CFG, view_head=V)
    p0, p = init(jax.random.key(0), CFG), init(jax.random.key(0), mcfg)
    assert set(p) == set(p0) | {"view_head"} and p["view_head"]["w"].shape == (CFG.head_hidden, V * V * 3)
    for a, b in zip(jax.tree.leaves(p0), jax.tree.leaves({k: v for k, v in p.items() if k != "view_head"})):
        np.testing.assert_array_equal(a, b)
    rng = np.random.default_rng(3)
    p = {**p, "view_head": jax.tree.map(lambda a: jnp.asarray(rng.normal(size=a.shape).astype(np.float32) * 0.1),
                                        p["view_head"])}
    batch = _batch(mcfg)
    batch["view"] = rng.integers(0, 256, (4, V, V, 3), dtype=np.uint8)
    out, res = _apply_seeing_the_pose_decoder(p, mcfg, batch)
    h = np.asarray(res[3], np.float64)
    want_view = (h @ np.asarray(p["view_head"]["w"], np.float64) + np.asarray(p["view_head"]["b"])).reshape(4, V, V, 3)
    np.testing.assert_allclose(np.asarray(out["view"]), want_view, rtol=1e-4, atol=1e-4)
    err = ((want_view - batch["view"] / 255.0) ** 2).sum(-1).reshape(4, -1)
    k = int(np.ceil(0.25 * V * V))
    want = np.mean(np.sort(err, axis=1)[:, -k:])
    np.testing.assert_allclose(float(view_loss(out["view"], batch["view"], 0.25)), want, rtol=1e-4)
    np.testing.assert_allclose(float(view_loss(out["view"], batch["view"], 1.0)), err.mean(), rtol=1e-4)
    lcfg = LossConfig(n_negatives=8, w_view=2.0)
    loss, aux = jax.jit(loss_fn, static_argnums=(1, 2, 5))(p, mcfg, lcfg, batch, jax.random.key(1), Z_RANGE)
    np.testing.assert_allclose(float(aux["loss_view"]), want, rtol=1e-4)
    rest = lcfg.w_rot * aux["loss_rot"] + lcfg.w_xy * aux["loss_xy"] + lcfg.w_z * aux["loss_z"] + lcfg.w_mask * aux["loss_mask"]
    np.testing.assert_allclose(float(loss), float(rest + 2.0 * aux["loss_view"]), rtol=1e-5)
    with pytest.raises(ValueError, match="model.view_head"):
        loss_fn(p0, CFG, lcfg, batch, jax.random.key(1), Z_RANGE)
    with pytest.raises(ValueError, match="'view'"):
        loss_fn(p, mcfg, lcfg, {k: v for k, v in batch.items() if k != "view"}, jax.random.key(1), Z_RANGE)
    for bad in (-1, 5, 2.5):
        with pytest.raises(ValueError, match="view_head"):
            dataclasses.replace(CFG, view_head=bad)
    for bad in (0.0, 1.5):
        with pytest.raises(ValueError, match="view_top"):
            LossConfig(view_top=bad)
    with pytest.raises(ValueError, match="w_view"):
        LossConfig(w_view=-1.0)


@pytest.mark.parametrize("source", ["map", "block"])
def test_view_head_from_a_map_decodes_each_cell_to_its_patch(source):
    """model.view_from="map" ("block"): each cell of the m x m map the rotation head flattens (of
    the dilated block's output that the three heads read) is decoded linearly to its (V/m)^2
    patch of the view, found here by hand through the pose decoder."""
    from sc6d_jax.model._pose_decoder import block_map_size, head_map_size

    base = dataclasses.replace(CFG, pose_downsample=1)  # the heads read a 2 x 2 map, the block is 4 x 4
    assert (head_map_size(base), block_map_size(base)) == (2, 4)
    m, c = (2, CFG.pose_width) if source == "map" else (4, 8 * CFG.pose_width)
    V, q = 8, 8 // m
    mcfg = dataclasses.replace(base, view_head=V, view_from=source)
    p = init(jax.random.key(0), mcfg)
    assert p["view_head"]["w"].shape == (c, 3 * q * q)
    rng = np.random.default_rng(4)
    p = {**p, "view_head": jax.tree.map(lambda a: jnp.asarray(rng.normal(size=a.shape).astype(np.float32)), p["view_head"])}
    batch = _batch(mcfg)
    out, res = _apply_seeing_the_pose_decoder(p, mcfg, batch)
    hm = np.asarray(res[4] if source == "map" else res[5], np.float64)
    assert hm.shape == (4, m, m, c)
    w, b = np.asarray(p["view_head"]["w"], np.float64), np.asarray(p["view_head"]["b"], np.float64)
    for i, j in ((0, 0), (m - 1, 0), (m - 1, m - 1)):
        patch = (hm[:, i, j] @ w + b).reshape(4, q, q, 3)
        np.testing.assert_allclose(np.asarray(out["view"])[:, q * i:q * i + q, q * j:q * j + q], patch, rtol=1e-4, atol=1e-4)
    with pytest.raises(ValueError, match="multiple"):
        init(jax.random.key(0), dataclasses.replace(base, view_head=2 if source == "block" else 1, view_from=source))
    with pytest.raises(ValueError, match="view_from"):
        dataclasses.replace(CFG, view_from="pooled")


def test_view_head_per_object_decodes_each_crop_with_its_objects_decoder():
    """model.view_per_object: one view decoder per object, stacked; each crop's cells are decoded
    by its own object's decoder (found here by hand), the other parameters drawn as without it."""
    base = dataclasses.replace(CFG, pose_downsample=1, view_head=8, view_from="map")
    mcfg = dataclasses.replace(base, view_per_object=True)
    p, p1 = init(jax.random.key(0), mcfg), init(jax.random.key(0), base)
    m, c, q = 2, CFG.pose_width, 4
    assert p["view_head"]["w"].shape == (CFG.n_objects, c, 3 * q * q) and p["view_head"]["b"].shape == (CFG.n_objects, 3 * q * q)
    for a, b in zip(jax.tree.leaves({k: v for k, v in p.items() if k != "view_head"}),
                    jax.tree.leaves({k: v for k, v in p1.items() if k != "view_head"})):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    rng = np.random.default_rng(5)
    p = {**p, "view_head": jax.tree.map(lambda a: jnp.asarray(rng.normal(size=a.shape).astype(np.float32)), p["view_head"])}
    batch = _batch(mcfg)
    out, res = _apply_seeing_the_pose_decoder(p, mcfg, batch)
    hm = np.asarray(res[4], np.float64)
    w, b = np.asarray(p["view_head"]["w"], np.float64), np.asarray(p["view_head"]["b"], np.float64)
    assert len(set(batch["obj_idx"].tolist())) == CFG.n_objects
    for k, o in enumerate(batch["obj_idx"]):
        for i, j in ((0, 0), (m - 1, 0), (m - 1, m - 1)):
            patch = (hm[k, i, j] @ w[o] + b[o]).reshape(q, q, 3)
            np.testing.assert_allclose(np.asarray(out["view"])[k, q * i:q * i + q, q * j:q * j + q], patch, rtol=1e-4, atol=1e-4)
    with pytest.raises(ValueError, match="view_per_object"):
        dataclasses.replace(CFG, view_per_object=True)


def test_per_object_heads_read_each_crops_output_layers_off_the_shared_hidden_layers():
    """model.per_object_heads: the rotation, centre and depth heads' output layers are stacked per
    object; each crop's embedding is its object's layer of the shared hidden layer (by hand), and
    with every object's layers set to one shared model's, the outputs are that model's."""
    from sc6d_jax.model import apply

    base = dataclasses.replace(CFG, pose_downsample=1)
    mcfg = dataclasses.replace(base, per_object_heads=True)
    p, p1 = init(jax.random.key(0), mcfg), init(jax.random.key(0), base)
    hh = CFG.head_hidden
    for name, d in (("rot", CFG.emb_dim), ("xy", 2), ("z", CFG.n_z_bins)):
        assert p["pose_decoder"][name]["out"]["w"].shape == (CFG.n_objects, hh, d)
        assert p["pose_decoder"][name]["out"]["b"].shape == (CFG.n_objects, d)
    strip = lambda q: {**q, "pose_decoder": {k: ({kk: vv for kk, vv in v.items() if kk != "out"} if k in ("rot", "xy", "z") else v)
                                             for k, v in q["pose_decoder"].items()}}
    for a, b in zip(jax.tree.leaves(strip(p)), jax.tree.leaves(strip(p1))):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    rng = np.random.default_rng(6)
    pd = {k: v for k, v in p["pose_decoder"].items()}
    for name in ("rot", "xy", "z"):
        pd[name] = {**pd[name], "out": jax.tree.map(lambda a: jnp.asarray(rng.normal(size=a.shape).astype(np.float32)),
                                                    pd[name]["out"])}
    p = {**p, "pose_decoder": pd}
    batch = _batch(mcfg)
    out, res = _apply_seeing_the_pose_decoder(p, mcfg, batch)
    h = np.asarray(res[3], np.float64)
    w, b = np.asarray(pd["rot"]["out"]["w"], np.float64), np.asarray(pd["rot"]["out"]["b"], np.float64)
    e = np.stack([h[k] @ w[o] + b[o] for k, o in enumerate(batch["obj_idx"])])
    np.testing.assert_allclose(np.asarray(out["rot_emb"]), e / np.linalg.norm(e, axis=1, keepdims=True), rtol=1e-4, atol=1e-5)
    # every object's output layers = the shared model's: the shared model's outputs
    same = {**p1, "pose_decoder": {**p1["pose_decoder"], **{
        n: {**p1["pose_decoder"][n], "out": jax.tree.map(lambda a: jnp.stack([a] * CFG.n_objects), p1["pose_decoder"][n]["out"])}
        for n in ("rot", "xy", "z")}}}
    o1, o2 = apply(same, mcfg, batch["rgb"], batch["pe"], batch["obj_idx"]), apply(p1, base, batch["rgb"], batch["pe"], batch["obj_idx"])
    for k in ("rot_emb", "delta_xy", "z_logits"):
        np.testing.assert_allclose(np.asarray(o1[k]), np.asarray(o2[k]), rtol=1e-5, atol=1e-6)
    from sc6d_jax.model._pose_decoder import pose_decoder
    with pytest.raises(ValueError, match="obj_idx"):
        pose_decoder(p["pose_decoder"], mcfg, jnp.zeros((1, 8, 8, CFG.feat_dim)), jnp.zeros((1, 8, 8)), batch["pe"][:1])
