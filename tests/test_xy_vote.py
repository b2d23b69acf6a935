"""The projected centre read off votes of the decoder's cells (model.xy_vote, loss.w_xy_vote)."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sc6d_jax import model
from sc6d_jax.model._losses import downsample_mask, vote_loss
from sc6d_jax.model._network import vote_delta_xy, vote_grid


def test_grid_is_the_cells_centres_in_delta_xy_units_of_a_real_crop(models):
    """A cell's centre in crop-side units is where delta_xy puts a point there: the stream's
    delta_xy of a crop is the projected centre (K_B t, crop pixels) in the same units."""
    from sc6d_jax.data import CropStream, StreamConfig

    S = 64
    n = S // 4
    cells = (np.arange(n) * 4 + 1.5 - (S - 1) / 2) / S  # pixels 4k..4k+3, centre 4k + 1.5
    g = np.asarray(vote_grid(n))
    np.testing.assert_allclose(g[..., 0], np.broadcast_to(cells[None, :], (n, n)), atol=1e-7)  # x along a row
    np.testing.assert_allclose(g[..., 1], np.broadcast_to(cells[:, None], (n, n)), atol=1e-7)  # y down a column
    cfg = StreamConfig(models_dir=models, crop_size=S, batch_size=4, seed=5, obj_ids=(1, 11), augment=False, workers=0)
    b = CropStream(cfg).batch(0)
    h = np.einsum("bij,bj->bi", b["K_B"].astype(np.float64), b["t"].astype(np.float64))
    uv = h[:, :2] / h[:, 2:]
    np.testing.assert_allclose((uv - (S - 1) / 2) / S, b["delta_xy"], atol=2e-5)


def test_votes_decode_loss_and_quarter_turns():
    rng = np.random.default_rng(0)
    n, d = 16, np.array([[0.12, -0.2], [-0.05, 0.3]], np.float32)
    exact = d[:, None, None, :] - np.asarray(vote_grid(n))[None]
    conf = rng.normal(size=(2, n, n, 1)).astype(np.float32)
    mask_logit = rng.normal(size=(2, n, n)).astype(np.float32)
    votes = jnp.asarray(np.concatenate([exact, conf], -1))
    # exact votes give the centre whatever the weights; the loss is 0
    np.testing.assert_allclose(vote_delta_xy(votes, mask_logit), d, atol=1e-6)
    mask = (rng.uniform(size=(2, n, n)) > 0.5).astype(np.float32)
    assert float(vote_loss(votes, jnp.asarray(d), jnp.asarray(mask))) < 1e-6
    # an error of 0.1 in x on the cells off the mask costs nothing, on the mask exactly 0.1
    off = exact.copy()
    off[..., 0] += 0.1 * (1 - mask)
    assert float(vote_loss(jnp.asarray(np.concatenate([off, conf], -1)), jnp.asarray(d), jnp.asarray(mask))) < 1e-6
    on = exact.copy()
    on[..., 0] += 0.1 * mask
    np.testing.assert_allclose(float(vote_loss(jnp.asarray(np.concatenate([on, conf], -1)), jnp.asarray(d),
                                               jnp.asarray(mask))), 0.1, rtol=1e-5)
    # the weights follow the confidence and the mask: one confident cell on the mask decides
    noisy = exact + rng.normal(scale=0.2, size=exact.shape).astype(np.float32)
    c = np.full((2, n, n, 1), -30.0, np.float32)
    c[:, 3, 9] = 30.0
    got = vote_delta_xy(jnp.asarray(np.concatenate([noisy, c], -1)), jnp.zeros((2, n, n)))
    np.testing.assert_allclose(got, np.asarray(vote_grid(n))[3, 9] + noisy[:, 3, 9], atol=1e-5)
    # the stream turns a crop by k quarter turns clockwise (np.rot90(img, -k)) and its delta_xy
    # by Rz(90k): a map turned with the image, its offsets turned as vectors, decodes to the
    # turned centre (each cell's centre lands on the turned one's: the grid's convention is the
    # stream's)
    votes_n = np.concatenate([noisy, conf], -1)
    want = np.asarray(vote_delta_xy(jnp.asarray(votes_n), mask_logit))
    for k in (1, 2, 3):
        cs, sn = [(1, 0), (0, 1), (-1, 0), (0, -1)][k]
        Rz = np.array([[cs, -sn], [sn, cs]], np.float32)
        turned = np.rot90(votes_n, -k, axes=(1, 2)).copy()
        turned[..., :2] = turned[..., :2] @ Rz.T
        got = vote_delta_xy(jnp.asarray(turned), jnp.asarray(np.rot90(mask_logit, -k, axes=(1, 2)).copy()))
        np.testing.assert_allclose(got, want @ Rz.T, atol=1e-5)


def test_vote_head_trains_through_the_loss_and_checks_its_config(micro_model):
    mcfg = micro_model(xy_vote=True)
    lcfg = model.LossConfig(n_negatives=16, rebase_negatives=False, w_xy_vote=3.0)
    params = model.init(jax.random.PRNGKey(0), mcfg)
    assert set(params["xy_vote"]) == {"conv", "out"}
    rng = np.random.default_rng(0)
    b = 2
    batch = {
        "rgb": rng.integers(0, 256, (b, 32, 32, 3)).astype(np.uint8),
        "pe": rng.normal(size=(b, 32, 32, 2)).astype(np.float32),
        "mask_visib": np.pad(np.ones((b, 16, 16), np.uint8), ((0, 0), (8, 8), (8, 8))),
        "R_allo": np.tile(np.eye(3, dtype=np.float32), (b, 1, 1)),
        "delta_xy": np.array([[0.1, -0.1], [0.0, 0.2]], np.float32),
        "delta_z": np.full((b,), 1.5, np.float32),
        "obj_idx": np.zeros((b,), np.int32),
    }
    key = jax.random.PRNGKey(1)
    (loss, aux), grads = jax.jit(jax.value_and_grad(
        lambda p: model.loss_fn(p, mcfg, lcfg, batch, key, (1.0, 2.0)), has_aux=True))(params)
    assert float(aux["loss_xy_vote"]) > 0 and float(jnp.abs(grads["xy_vote"]["out"]["w"]).sum()) > 0
    total = sum(getattr(lcfg, "w_" + k) * float(aux["loss_" + k]) for k in ("rot", "xy", "z", "mask", "xy_vote"))
    np.testing.assert_allclose(float(loss), total, rtol=1e-5)
    # each vote weighs the visible fraction of its cell, also when the mask head's target is the
    # block's centre pixel (mask_downsample="nearest"): a mask edge through the blocks' middles
    half = dict(batch, mask_visib=np.pad(np.ones((b, 14, 14), np.uint8), ((0, 0), (9, 9), (9, 9))))
    out = model.apply(params, mcfg, jnp.asarray(half["rgb"]), jnp.asarray(half["pe"]), jnp.zeros(b, jnp.int32))
    f = 32 // out["xy_votes"].shape[1]
    area = vote_loss(out["xy_votes"], jnp.asarray(half["delta_xy"]), downsample_mask(jnp.asarray(half["mask_visib"]), f))
    nearest = vote_loss(out["xy_votes"], jnp.asarray(half["delta_xy"]),
                        downsample_mask(jnp.asarray(half["mask_visib"]), f, "nearest"))
    assert abs(float(area) - float(nearest)) > 1e-4  # the two weightings differ on this mask
    for mode in ("area", "nearest"):
        _, aux_m = model.loss_fn(params, mcfg, dataclasses.replace(lcfg, mask_downsample=mode), half, key, (1.0, 2.0))
        np.testing.assert_allclose(float(aux_m["loss_xy_vote"]), float(area), rtol=1e-5)
    # delta_xy is the votes' (the xy head is not read: no gradient reaches it)
    assert float(jnp.abs(grads["pose_decoder"]["xy"]["out"]["w"]).sum()) == 0
    with pytest.raises(ValueError, match="xy_vote=True"):
        off = micro_model()
        model.loss_fn(model.init(jax.random.PRNGKey(0), off), off, lcfg, batch, key, (1.0, 2.0))


def test_votes_from_the_dilated_block_are_weighted_by_the_mask_over_their_cells(micro_model):
    mcfg = micro_model(pose_downsample=1, xy_vote=True, xy_vote_from="block")
    params = model.init(jax.random.PRNGKey(0), mcfg)
    out = jax.jit(lambda p: model.apply(p, mcfg, jnp.zeros((2, 32, 32, 3)), jnp.zeros((2, 32, 32, 2)),
                                        jnp.zeros(2, jnp.int32)))(params)
    assert out["xy_votes"].shape == (2, 4, 4, 3) and out["delta_xy"].shape == (2, 2)
    # a mask on one 2x2 group of the 8x8 mask map alone: its 4x4 vote cell decides
    n, d = 4, np.array([[0.1, -0.2]], np.float32)
    votes = np.concatenate([np.zeros((1, n, n, 2), np.float32), np.zeros((1, n, n, 1), np.float32)], -1)
    votes[0, 1, 2, :2] = d[0] - np.asarray(vote_grid(n))[1, 2]
    mask_logit = np.full((1, 8, 8), -40.0, np.float32)
    mask_logit[0, 2:4, 4:6] = 40.0
    np.testing.assert_allclose(vote_delta_xy(jnp.asarray(votes), jnp.asarray(mask_logit)), d, atol=1e-5)
    with pytest.raises(ValueError, match="xy_vote_from"):
        model.ModelConfig(n_objects=1, xy_vote=True, xy_vote_from="pooled")


def test_centre_offset_from_the_rotation_adds_to_delta_xy_and_trains(micro_model):
    """model.xy_rot: a per-object MLP of the allocentric rotation (9 -> h -> h -> 2), zero at
    first, added to delta_xy wherever the rotation's priors are applied (training: the ground
    truth; inference and validation: the matched rotation); the centre's loss trains it."""
    from sc6d_jax.model import with_rotation_priors
    from sc6d_jax.model._rotation import rotation_prior_output

    mcfg = micro_model(xy_rot=True)
    p0, p = model.init(jax.random.PRNGKey(0), micro_model()), model.init(jax.random.PRNGKey(0), mcfg)
    assert set(p) == set(p0) | {"xy_rot"} and p["xy_rot"]["out"]["w"].shape == (1, 16, 2)
    for a, b in zip(jax.tree.leaves(p0), jax.tree.leaves({k: v for k, v in p.items() if k != "xy_rot"})):
        np.testing.assert_array_equal(a, b)
    rng = np.random.default_rng(2)
    out = {"delta_xy": jnp.asarray(rng.normal(size=(2, 2)).astype(np.float32)), "z_logits": jnp.zeros((2, 8))}
    R = jnp.asarray(np.stack([np.eye(3), np.diag([1.0, -1.0, -1.0])]).astype(np.float32))
    obj = jnp.zeros((2,), jnp.int32)
    np.testing.assert_array_equal(with_rotation_priors(p, mcfg, out, R, obj)["delta_xy"], out["delta_xy"])  # zero at first
    p = {**p, "xy_rot": jax.tree.map(lambda a: jnp.asarray(rng.normal(size=a.shape).astype(np.float32) * 0.3), p["xy_rot"])}
    got = with_rotation_priors(p, mcfg, out, R, obj)
    np.testing.assert_allclose(got["delta_xy"], out["delta_xy"] + rotation_prior_output(p["xy_rot"], R, obj), rtol=1e-6)
    np.testing.assert_array_equal(got["z_logits"], out["z_logits"])  # no depth prior without z_rot
    b = 2
    batch = {
        "rgb": rng.integers(0, 256, (b, 32, 32, 3)).astype(np.uint8),
        "pe": rng.normal(size=(b, 32, 32, 2)).astype(np.float32),
        "mask_visib": np.ones((b, 32, 32), np.uint8),
        "R_allo": np.asarray(R),
        "delta_xy": np.array([[0.1, -0.1], [0.0, 0.2]], np.float32),
        "delta_z": np.full((b,), 1.5, np.float32),
        "obj_idx": np.zeros((b,), np.int32),
    }
    lcfg = model.LossConfig(n_negatives=16, rebase_negatives=False)
    grads = jax.jit(jax.grad(lambda q: model.loss_fn(q, mcfg, lcfg, batch, jax.random.PRNGKey(1), (1.0, 2.0))[0]))(p)
    assert float(jnp.abs(grads["xy_rot"]["out"]["w"]).sum()) > 0
