"""Dense geometry targets (surface normals, depth relative to the centre) and their loss."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sc6d_jax import geometry as G
from sc6d_jax import model
from sc6d_jax.data import CropStream, StreamConfig
from sc6d_jax.data._stream import dense_targets


def _plane_depth(n: np.ndarray, c: float, K: np.ndarray, S: int) -> np.ndarray:
    """Depth (S,S) of the plane n . P = c seen through K (pixel centres at integers)."""
    v, u = np.mgrid[0:S, 0:S].astype(np.float64)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    return c / (rays @ n)


def test_normals_and_relative_depth_of_a_tilted_plane():
    S = 32
    K = np.array([[60.0, 0, 15.5], [0, 60.0, 15.5], [0, 0, 1]])
    th = np.deg2rad(30.0)
    n = np.array([np.sin(th), 0.0, -np.cos(th)])  # faces the camera (n . P < 0 for P in front)
    depth = _plane_depth(n, -500.0 * np.cos(th), K, S)  # passes through (0, 0, 500)
    mask = np.ones((1, S, S), np.uint8)
    eye = np.eye(3)[None]
    dense, w = dense_targets(depth[None], mask, K[None], eye, eye, np.array([[0.0, 0.0, 480.0]]), np.array([100.0]))
    assert dense.shape == (1, 8, 8, 4) and w.shape == (1, 8, 8)
    # the image's outer pixels lack a neighbour: edge blocks keep 12 of 16 pixels, corners 9
    expect = np.ones((8, 8))
    expect[[0, -1], :] *= 0.75
    expect[:, [0, -1]] *= 0.75
    np.testing.assert_allclose(w[0], expect)
    np.testing.assert_allclose(dense[0][w[0] > 0][:, :3], np.broadcast_to(n, (64, 3)), atol=1e-4)
    # relative depth: (Z - t_z) / diameter, averaged over the block
    rel = (depth - 480.0) / 100.0
    blocks = rel.reshape(8, 4, 8, 4).mean(axis=(1, 3))
    np.testing.assert_allclose(dense[0, 2:6, 2:6, 3], blocks[2:6, 2:6], atol=1e-4)

    # the normal is expressed in the frame of the rotation label: R_allo R^T n
    Rz = np.asarray(G.rot_z(np.pi / 2))
    dense2, _ = dense_targets(depth[None], mask, K[None], eye, Rz[None], np.array([[0.0, 0.0, 480.0]]), np.array([100.0]))
    np.testing.assert_allclose(dense2[0, 3, 3, :3], Rz @ n, atol=1e-4)


def test_object_frame_points_of_a_plane():
    """xyz=True: three more channels, R^T (P - t) / diameter of the visible points (block means);
    the first four are unchanged; a turned object gives the same points turned back."""
    S = 32
    K = np.array([[60.0, 0, 15.5], [0, 60.0, 15.5], [0, 0, 1]])
    depth = np.full((1, S, S), 500.0)
    mask = np.ones((1, S, S), np.uint8)
    t = np.array([[10.0, -20.0, 480.0]])
    eye = np.eye(3)[None]
    dense4, _ = dense_targets(depth, mask, K[None], eye, eye, t, np.array([100.0]))
    Rz = np.asarray(G.rot_z(0.3))
    dense, w = dense_targets(depth, mask, K[None], Rz[None], eye, t, np.array([100.0]), xyz=True)
    assert dense.shape == (1, 8, 8, 7)
    np.testing.assert_allclose(dense[..., 3], dense4[..., 3], atol=1e-6)
    v, u = np.mgrid[0:S, 0:S].astype(np.float64)
    P = np.stack([(u - 15.5) / 60 * 500, (v - 15.5) / 60 * 500, np.full_like(u, 500.0)], -1) - t[0]
    obj = (P @ Rz) / 100.0  # R^T p for each row p
    # an inner block (all 16 pixels weighted): the mean of its pixels' points
    np.testing.assert_allclose(dense[0, 3, 4, 4:], obj[12:16, 16:20].reshape(-1, 3).mean(0), atol=1e-4)
    np.testing.assert_allclose(dense[0, 3, 4, 4:] @ Rz.T * 100 + t[0], [P[12:16, 16:20, i].mean() + t[0, i] for i in range(3)],
                               atol=1e-3)


def test_no_target_means_zero_weight_and_zero_target():
    S = 16
    K = np.array([[40.0, 0, 7.5], [0, 40.0, 7.5], [0, 0, 1]])
    depth = np.full((1, S, S), 300.0)
    mask = np.zeros((1, S, S), np.uint8)
    mask[0, 4:12, 4:12] = 1  # only the middle is the target; the rest (an occluder) is masked out
    eye = np.eye(3)[None]
    dense, w = dense_targets(depth, mask, K[None], eye, eye, np.array([[0.0, 0.0, 300.0]]), np.array([50.0]))
    assert w[0, 0, 0] == 0 and np.all(dense[0, 0, 0] == 0)
    # the target's outer pixels lack a visible neighbour: each of its 4 blocks keeps 3 x 3 pixels
    np.testing.assert_allclose(w[0, 1:3, 1:3], 9 / 16)
    np.testing.assert_allclose(dense[0, 1, 1, :3], [0, 0, -1], atol=1e-6)  # fronto-parallel: facing the camera


def test_stream_dense_targets_follow_the_crop(models):
    """dense=True adds the targets without changing anything else; the 90-degree turns of the
    augmentation turn the maps and the normals with the crop."""
    kw = dict(crop_size=32, batch_size=6, workers=0, obj_ids=(1, 5), seed=3)
    with CropStream(StreamConfig(str(models), augment=False, dense=True, **kw)) as s:
        plain = s.batch(2)
    with CropStream(StreamConfig(str(models), augment=False, **kw)) as s:
        without = s.batch(2)
    with CropStream(StreamConfig(str(models), augment=True, dense=True, **kw)) as s:
        aug = s.batch(2)
    assert "dense" not in without
    for k in without:
        np.testing.assert_array_equal(plain[k], without[k])
    d, w = plain["dense"], plain["dense_w"]
    assert d.shape == (6, 8, 8, 4) and w.shape == (6, 8, 8) and d.dtype == np.float32
    assert np.all(w[plain["mask_visib"].reshape(6, 8, 4, 8, 4).max(axis=(2, 4)) == 0] == 0)
    assert (w > 0).sum() > 6 * 4
    norms = np.linalg.norm(d[..., :3][w > 0], axis=-1)
    np.testing.assert_allclose(norms, 1.0, atol=1e-4)
    # normals of a convex-ish object seen from the front face the camera on average
    assert np.mean(d[..., 2][w > 0]) < -0.3
    for j in range(6):
        D = aug["R_allo"][j] @ plain["R_allo"][j].T  # Rz(90k)
        k = int(np.round(np.arctan2(D[1, 0], D[0, 0]) / (np.pi / 2))) % 4
        np.testing.assert_array_equal(aug["dense_w"][j], np.rot90(w[j], -k))
        turned = np.rot90(d[j], -k).copy()
        turned[..., :3] = turned[..., :3] @ D.T
        np.testing.assert_allclose(aug["dense"][j], turned, atol=1e-5)
    # object-frame points: three more channels that turn with the crop's pixels, not their values
    with CropStream(StreamConfig(str(models), augment=False, dense=True, dense_xyz=True, **kw)) as s:
        plain7 = s.batch(2)
    with CropStream(StreamConfig(str(models), augment=True, dense=True, dense_xyz=True, **kw)) as s:
        aug7 = s.batch(2)
    np.testing.assert_array_equal(plain7["dense"][..., :4], d)
    assert np.abs(plain7["dense"][..., 4:][w > 0]).max() <= 0.5 + 1e-3  # within the radius: diameter / 2
    for j in range(6):
        D = aug7["R_allo"][j] @ plain7["R_allo"][j].T
        k = int(np.round(np.arctan2(D[1, 0], D[0, 0]) / (np.pi / 2))) % 4
        np.testing.assert_allclose(aug7["dense"][j][..., 4:], np.rot90(plain7["dense"][j][..., 4:], -k), atol=1e-6)
    with pytest.raises(ValueError, match="dense_xyz"):
        StreamConfig(str(models), dense_xyz=True)


def test_dense_loss_trains_the_head_and_checks_its_inputs(micro_model):
    mcfg = micro_model(dense_head=True)
    lcfg = model.LossConfig(n_negatives=16, rebase_negatives=False, w_dense=1.0)
    params = model.init(jax.random.PRNGKey(0), mcfg)
    rng = np.random.default_rng(0)
    b = 2
    nrm = rng.normal(size=(b, 8, 8, 3))
    batch = {
        "rgb": rng.integers(0, 256, (b, 32, 32, 3)).astype(np.uint8),
        "pe": rng.normal(size=(b, 32, 32, 2)).astype(np.float32),
        "mask_visib": np.ones((b, 32, 32), np.uint8),
        "R_allo": np.tile(np.eye(3, dtype=np.float32), (b, 1, 1)),
        "delta_xy": np.zeros((b, 2), np.float32),
        "delta_z": np.full((b,), 1.5, np.float32),
        "obj_idx": np.zeros((b,), np.int32),
        "dense": np.concatenate([nrm / np.linalg.norm(nrm, axis=-1, keepdims=True), rng.normal(size=(b, 8, 8, 1))], -1).astype(np.float32),
        "dense_w": rng.uniform(0, 1, (b, 8, 8)).astype(np.float32),
    }
    key = jax.random.PRNGKey(1)

    grad_fn = jax.jit(jax.value_and_grad(lambda p, bt: model.loss_fn(p, mcfg, lcfg, bt, key, (1.0, 2.0)), has_aux=True))
    (loss, aux), grads = grad_fn(params, batch)
    assert np.isfinite(float(aux["loss_dense"])) and float(aux["loss_dense"]) > 0
    assert float(jnp.abs(grads["dense_head"]["w"]).sum()) > 0
    # the total is the weighted sum of the terms, the dense term included
    total = sum(getattr(lcfg, "w_" + k) * float(aux["loss_" + k]) for k in ("rot", "xy", "z", "mask", "dense"))
    np.testing.assert_allclose(float(loss), total, rtol=1e-5)
    with pytest.raises(ValueError, match="dense_w"):
        model.loss_fn(params, mcfg, lcfg, {k: v for k, v in batch.items() if k != "dense_w"}, key, (1.0, 2.0))
    with pytest.raises(ValueError, match="dense_head"):
        model.loss_fn(model.init(jax.random.PRNGKey(0), dataclasses.replace(mcfg, dense_head=False)),
                      dataclasses.replace(mcfg, dense_head=False), lcfg, batch, key, (1.0, 2.0))

    # object-frame points: three more head channels, their own term and weight
    mxyz = dataclasses.replace(mcfg, dense_xyz=True)
    lxyz = dataclasses.replace(lcfg, w_dense=0.0, w_dense_xyz=2.0)
    p7 = model.init(jax.random.PRNGKey(0), mxyz)
    b7 = dict(batch, dense=np.concatenate([batch["dense"], rng.normal(size=(b, 8, 8, 3)).astype(np.float32)], -1))
    (loss7, aux7), g7 = jax.jit(jax.value_and_grad(lambda p: model.loss_fn(p, mxyz, lxyz, b7, key, (1.0, 2.0)), has_aux=True))(p7)
    assert "loss_dense" not in aux7 and float(aux7["loss_dense_xyz"]) > 0
    total7 = sum(getattr(lxyz, "w_" + k) * float(aux7["loss_" + k]) for k in ("rot", "xy", "z", "mask", "dense_xyz"))
    np.testing.assert_allclose(float(loss7), total7, rtol=1e-5)
    assert float(jnp.abs(g7["dense_head"]["w"][:, 4:]).sum()) > 0 and float(jnp.abs(g7["dense_head"]["w"][:, :4]).sum()) == 0
    with pytest.raises(ValueError, match="dense_xyz=True"):
        model.loss_fn(params, mcfg, lxyz, b7, key, (1.0, 2.0))
    with pytest.raises(ValueError, match="dense_head=True"):
        model.ModelConfig(n_objects=1, dense_xyz=True)


def test_optional_heads_leave_the_other_parameters_unchanged(micro_model):
    """dense_head and xy_vote add their own parameters without changing how the others are
    drawn, and so3_pe_freqs widens only the SO(3) encoder's input layer."""
    mcfg = micro_model(n_objects=2)
    a = model.init(jax.random.PRNGKey(3), mcfg)
    for field, name in (("dense_head", "dense_head"), ("xy_vote", "xy_vote")):
        b = model.init(jax.random.PRNGKey(3), dataclasses.replace(mcfg, **{field: True}))
        assert set(b) == set(a) | {name}
        for x, y in zip(jax.tree.leaves(a), jax.tree.leaves({k: b[k] for k in a})):
            np.testing.assert_array_equal(x, y)
    c = model.init(jax.random.PRNGKey(3), dataclasses.replace(mcfg, so3_pe_freqs=3))
    assert c["rot_head"]["fc1"]["w"].shape == (9 * 7, 16)
    R = np.asarray(G.rot_z(0.3))[None].repeat(2, 0)
    e = model.encode_rotations(c, dataclasses.replace(mcfg, so3_pe_freqs=3), jnp.asarray(R), jnp.array([0, 1]))
    np.testing.assert_allclose(np.linalg.norm(np.asarray(e), axis=-1), 1.0, atol=1e-5)


def test_teacher_gate_replaces_the_predicted_mask_where_on(micro_model):
    """apply's teacher gate: off = the predicted gate; on with the predicted gate's own values =
    the same outputs; on with another mask = other outputs, for those samples only."""
    mcfg = micro_model(mask_gate=True)
    params = model.init(jax.random.PRNGKey(0), mcfg)
    rng = np.random.default_rng(1)
    rgb = jnp.asarray(rng.integers(0, 256, (2, 32, 32, 3)).astype(np.uint8))
    pe = jnp.asarray(rng.normal(size=(2, 32, 32, 2)).astype(np.float32))
    obj = jnp.zeros((2,), jnp.int32)
    fwd = jax.jit(lambda p, t: model.apply(p, mcfg, rgb, pe, obj, t))
    plain = jax.jit(lambda p: model.apply(p, mcfg, rgb, pe, obj))(params)
    own = jax.nn.sigmoid(plain["mask_logit"])
    off = fwd(params, (jnp.zeros_like(own), jnp.array([False, False])))
    same = fwd(params, (own, jnp.array([True, True])))
    box = jnp.zeros_like(own).at[:, 2:6, 3:7].set(1.0)  # a spatially varying (ground-truth-like) mask
    other = fwd(params, (box, jnp.array([True, False])))
    for k in ("rot_emb", "delta_xy", "z_logits"):
        np.testing.assert_allclose(off[k], plain[k], atol=1e-6)
        np.testing.assert_allclose(same[k], plain[k], atol=1e-5)
        assert np.abs(other[k][0] - plain[k][0]).max() > 1e-3 * np.abs(plain[k][0]).max(), k
        np.testing.assert_allclose(other[k][1], plain[k][1], atol=1e-6)
