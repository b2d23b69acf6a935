"""Blocked library matching equals the dense reference; refinement improves the cosine."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sc6d_jax.inference._matching import match, match_dense
from sc6d_jax.geometry import axis_angle_to_matrix
from sc6d_jax.inference._refine import refine_rotations


def _unit(x):
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


@pytest.mark.parametrize("n,block,k", [(1000, 128, 1), (1000, 300, 5), (777, 4096, 3), (50, 7, 50), (5000, 1024, 1), (2900, 512, 1)])
def test_blocked_matches_dense(n, block, k):
    rng = np.random.default_rng(n + k)
    lib = _unit(rng.normal(size=(n, 16))).astype(np.float32)
    q = _unit(rng.normal(size=(9, 16))).astype(np.float32)
    got = match(q, lib, k=k, tau=0.1, block=block)
    ref = match_dense(q, lib, k=k, tau=0.1)
    np.testing.assert_array_equal(np.asarray(got.index), np.asarray(ref.index))
    np.testing.assert_allclose(np.asarray(got.score), np.asarray(ref.score), rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(np.asarray(got.prob), np.asarray(ref.prob), rtol=1e-4, atol=1e-7)
    assert np.all(np.diff(np.asarray(got.score), axis=1) <= 0)  # best first


_SMALL = [2, 0, 2, 3, 0, 0, 2]  # 7 queries, object 1 absent
# 40 queries in shuffled order, per-object counts 0, 1, 9, 17, 13: groups of 8, 16, 32 (and 40)
_SPREAD = list(np.random.default_rng(5).permutation([1] * 1 + [2] * 9 + [3] * 17 + [4] * 13))


@pytest.mark.parametrize("k,objs", [(1, _SMALL), (4, _SMALL), (1, _SPREAD), (3, _SPREAD), (1, [3] * 40)])
def test_per_object_libraries_match_each_query_against_its_own(k, objs):
    """(O, nb, E, block) libraries: a query sees only its object's library; objects absent from
    the batch are skipped; results equal the dense reference per object, whatever the number
    of queries per object (grouped by object in static sizes)."""
    from sc6d_jax.inference import match_blocks, pad_library

    rng = np.random.default_rng(k)
    n_obj, n = 5, 1800
    libs = _unit(rng.normal(size=(n_obj, n, 16))).astype(np.float32)
    obj = np.asarray(objs, np.int32)
    q = _unit(rng.normal(size=(len(obj), 16))).astype(np.float32)
    blocks, nv = pad_library(libs, 512)
    assert blocks.shape == (n_obj, 4, 16, 512) and nv == n
    got = match_blocks(q, blocks, n_valid=nv, k=k, tau=0.1, obj_idx=obj)
    for i, o in enumerate(obj):
        ref = match_dense(q[i : i + 1], libs[o], k=k, tau=0.1)
        np.testing.assert_array_equal(np.asarray(got.index[i]), np.asarray(ref.index[0]))
        np.testing.assert_allclose(np.asarray(got.score[i]), np.asarray(ref.score[0]), rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(np.asarray(got.prob[i]), np.asarray(ref.prob[0]), rtol=1e-4, atol=1e-7)


def test_probabilities_sum_to_one_over_library():
    rng = np.random.default_rng(0)
    lib = _unit(rng.normal(size=(64, 8))).astype(np.float32)
    q = _unit(rng.normal(size=(3, 8))).astype(np.float32)
    got = match(q, lib, k=64, tau=0.5, block=16)
    np.testing.assert_allclose(np.asarray(got.prob).sum(axis=1), 1.0, rtol=1e-5)


def test_match_rejects_bad_shapes():
    lib = np.ones((10, 4), np.float32)
    with pytest.raises(ValueError, match="query dimension"):
        match(np.ones((2, 5), np.float32), lib)
    with pytest.raises(ValueError, match="k must be"):
        match(np.ones((2, 4), np.float32), lib, k=11)
    with pytest.raises(ValueError, match="queries must be"):
        match(np.ones(4, np.float32), lib)


def _random_embedder(seed: int, dim: int = 16):
    """A fixed smooth random feature map of R (random Fourier features of its 9 entries)."""
    rng = np.random.default_rng(seed)
    W = jnp.asarray(rng.normal(size=(9, dim)) * 1.5, jnp.float32)
    b = jnp.asarray(rng.uniform(0, 2 * np.pi, size=dim), jnp.float32)

    def embed(R, _obj=0):
        f = jnp.cos(R.reshape(9) @ W + b)
        return f / jnp.linalg.norm(f)

    return embed


def test_refinement_recovers_rotation_from_a_nearby_start():
    embed = _random_embedder(1)
    rng = np.random.default_rng(2)
    R_true = jnp.stack([axis_angle_to_matrix(jnp.asarray(w, jnp.float32)) for w in rng.normal(size=(4, 3))])
    queries = jax.vmap(embed)(R_true)
    R0 = jnp.stack([r @ axis_angle_to_matrix(jnp.asarray(d, jnp.float32)) for r, d in zip(R_true, 0.08 * rng.normal(size=(4, 3)))])
    R, cos = refine_rotations(embed, queries, R0, jnp.zeros(4, jnp.int32), max_steps=64)
    cos0 = jnp.einsum("be,be->b", queries, jax.vmap(embed)(R0))
    assert np.all(np.asarray(cos) >= np.asarray(cos0) - 1e-6)
    err = np.degrees(np.arccos(np.clip((np.trace(np.asarray(jnp.swapaxes(R, 1, 2) @ R_true), axis1=1, axis2=2) - 1) / 2, -1, 1)))
    err0 = np.degrees(np.arccos(np.clip((np.trace(np.asarray(jnp.swapaxes(R0, 1, 2) @ R_true), axis1=1, axis2=2) - 1) / 2, -1, 1)))
    assert np.median(err) < 0.25 * np.median(err0), (err, err0)
    np.testing.assert_allclose(np.asarray(R @ jnp.swapaxes(R, 1, 2)), np.broadcast_to(np.eye(3), (4, 3, 3)), atol=1e-5)
