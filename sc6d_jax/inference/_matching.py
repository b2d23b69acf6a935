"""Matching crop embeddings against a rotation library, block by block.

A library of N unit embeddings (N x E, float32; 480,000 x 32 by default) is stored transposed in
blocks, ``(nb, E, block)``, so each step of the scan is a plain ``(B, E) @ (E, block)`` product.
A running top-k (value and index) and a running sum of ``exp((score - |q|) / tau)`` are kept,
so no more than one block of scores (B x block) is ever materialised, whatever N. The
probabilities are the softmax over the whole library of cosine / tau, the same distribution
InfoNCE trained. The fixed shift ``|q|`` (Cauchy-Schwarz: no library row has norm above 1)
replaces a running maximum: one fused pass over each block, no overflow.

For k = 1 the scan keeps only the maximum of every sub-block of 256 rows per query (a cheap
reduction, no index bookkeeping); the argmax is then searched again inside each query's best
sub-block only (256 rows, gathered per query).

Several objects: ``blocks`` may be ``(O, nb, E, block)``, one library per object; each query
is matched against its own object's library only, and each library is scanned with only the
queries of its object (sorted by object, in groups of static power-of-two sizes); an object
with no query in the batch costs nothing.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

SUB_BLOCK = 256  # rows per sub-block of the k = 1 search


class MatchResult(NamedTuple):
    index: jax.Array  # (B, k) int32 library rows, best first
    score: jax.Array  # (B, k) cosine similarities
    prob: jax.Array  # (B, k) softmax(cosine / tau) over the whole library


def pad_library(library: np.ndarray | jax.Array, block: int) -> tuple[jax.Array, int]:
    """Zero-pad N to a multiple of ``block`` and transpose: ``(nb, E, block)`` and N.

    A ``(O, N, E)`` stack of per-object libraries gives ``(O, nb, E, block)``."""
    lib = jnp.asarray(library)
    if lib.ndim not in (2, 3):
        raise ValueError(f"library must be (N, E) or (O, N, E), got shape {lib.shape}")
    n, e = lib.shape[-2:]
    block = int(min(block, max(n, 1)))
    nb = -(-n // block)
    pad = nb * block - n
    if pad:
        lib = jnp.concatenate([lib, jnp.zeros(lib.shape[:-2] + (pad, e), lib.dtype)], axis=-2)
    lib = lib.reshape(lib.shape[:-2] + (nb, block, e))
    return jnp.swapaxes(lib, -1, -2), n


def auto_block(batch: int, n: int) -> int:
    """Block rows for a batch of ``batch`` queries: about 256k scores per block (L2-sized),
    between 2,048 and 32,768 rows, a power of two (measured on 2 CPU cores)."""
    target = 262144 // max(int(batch), 1)
    bs = 1 << max(int(np.floor(np.log2(max(target, 1)))), 0)
    return int(min(max(bs, 2048), 32768, max(n, 1)))


@functools.partial(jax.jit, static_argnames=("k", "n_valid", "with_prob"))
def match_blocks(
    queries: jax.Array, blocks: jax.Array, n_valid: int, k: int = 1, tau: float = 0.1, with_prob: bool = True,
    obj_idx: jax.Array | None = None,
) -> MatchResult:
    """Top-k library rows for each query. ``blocks`` is ``(nb, E, block)`` from
    :func:`pad_library`, or ``(O, nb, E, block)`` with ``obj_idx`` (B,) naming each query's
    library."""
    return _match_blocks(queries, blocks, n_valid, k, tau, with_prob, obj_idx)


def _match_blocks(queries, blocks, n_valid: int, k: int, tau, with_prob: bool, obj_idx=None) -> MatchResult:
    """Traceable body of :func:`match_blocks` (for use inside other jitted functions)."""
    if blocks.ndim == 3:
        return _match_one(queries, blocks[None], jnp.int32(0), n_valid, k, tau, with_prob)
    n_obj, b = blocks.shape[0], queries.shape[0]
    if obj_idx is None:
        raise ValueError("per-object blocks (O, nb, E, block) need obj_idx")
    obj_idx = jnp.asarray(obj_idx, jnp.int32)
    if n_obj == 1:
        return _match_one(queries, blocks, jnp.int32(0), n_valid, k, tau, with_prob)
    return _match_per_object(queries, blocks, obj_idx, n_valid, k, tau, with_prob)


def _chunk_sizes(b: int) -> tuple[int, ...]:
    """Static query-group sizes for per-object matching: 8, 16, ... up to ``b`` (the whole batch
    only when ``b`` is symbolic, as under jax.export)."""
    if not isinstance(b, int):
        return (b,)
    sizes, s = [], 8
    while s < b:
        sizes.append(s)
        s *= 2
    return tuple(sizes) + (b,)


def _match_per_object(queries, blocks, obj_idx, n_valid: int, k: int, tau, with_prob: bool) -> MatchResult:
    """Each object's library is scanned once, with only that object's queries.

    The queries are sorted by object; object o's run of n_o queries is matched as one group of
    the smallest static size in :func:`_chunk_sizes` that holds it (at most 2x padding), so a
    batch spread over many objects costs about one scan of each of their libraries with its own
    queries, not with the whole batch; an object without queries is skipped.
    """
    n_obj, b, e = blocks.shape[0], queries.shape[0], queries.shape[1]
    sizes = _chunk_sizes(b)
    order = jnp.argsort(obj_idx, stable=True).astype(jnp.int32)
    counts = jnp.bincount(obj_idx, length=n_obj).astype(jnp.int32)
    starts = (jnp.cumsum(counts) - counts).astype(jnp.int32)
    pad = sizes[-1]
    q_sorted = jnp.concatenate([queries[order], jnp.zeros((pad, e), queries.dtype)])
    dest_sorted = jnp.concatenate([order, jnp.full((pad,), b, jnp.int32)])  # b: dropped
    smaller = jnp.asarray(sizes[:-1], jnp.int32)  # concrete; the last size is the batch

    def group(size):
        def run(o, carry):
            st, n = starts[o], counts[o]
            qs = jax.lax.dynamic_slice_in_dim(q_sorted, st, size, axis=0)
            r = _match_one(qs, blocks, o, n_valid, k, tau, with_prob)
            dest = jax.lax.dynamic_slice_in_dim(dest_sorted, st, size, axis=0)
            dest = jnp.where(jnp.arange(size, dtype=jnp.int32) < n, dest, b)
            return tuple(a.at[dest].set(v, mode="drop") for a, v in zip(carry, r))
        return run

    branches = [lambda o, carry: carry] + [group(sz) for sz in sizes]

    def body(o, carry):
        n = counts[o]
        cls = jnp.where(n == 0, 0, 1 + jnp.sum(smaller < n))  # index of the smallest group >= n
        return jax.lax.switch(cls, branches, o, carry)

    init = (jnp.zeros((b, k), jnp.int32), jnp.zeros((b, k), jnp.float32), jnp.zeros((b, k), jnp.float32))
    index, score, prob = jax.lax.fori_loop(0, n_obj, body, init)
    return MatchResult(index=index, score=score, prob=prob)


def _match_one(queries, blocks, o, n_valid: int, k: int, tau, with_prob: bool) -> MatchResult:
    """Match every query against library ``o`` of ``blocks`` (O, nb, E, bs)."""
    _, nb, _, bs = blocks.shape
    b = queries.shape[0]
    q = queries.astype(blocks.dtype)
    inv_tau = jnp.asarray(1.0 / tau, jnp.float32)
    shift = jnp.linalg.norm(q.astype(jnp.float32), axis=1)  # >= every score (unit library rows)
    neg = jnp.float32(-jnp.inf)
    ragged = nb * bs != n_valid
    sub = SUB_BLOCK if bs % SUB_BLOCK == 0 else bs
    ns = bs // sub

    def block(j):
        return jax.lax.dynamic_index_in_dim(jax.lax.dynamic_index_in_dim(blocks, o, 0, False), j, 0, False)

    def scores(j):
        s = jnp.dot(q, block(j), preferred_element_type=jnp.float32)  # (B, bs): the only block alive
        if ragged:
            s = jnp.where(jnp.arange(bs, dtype=jnp.int32)[None, :] < n_valid - j * bs, s, neg)
        return s

    def body(carry, j):
        best_v, best_i, z = carry
        s = scores(j)
        if with_prob:
            z = z + jnp.sum(jnp.exp((s - shift[:, None]) * inv_tau), axis=1)
        if k == 1:
            return (best_v, best_i, z), jnp.max(s.reshape(b, ns, sub), axis=2)
        v, i = jax.lax.top_k(s, min(k, bs))
        allv = jnp.concatenate([best_v, v], axis=1)
        alli = jnp.concatenate([best_i, (j * bs + i).astype(jnp.int32)], axis=1)
        best_v, sel = jax.lax.top_k(allv, k)
        best_i = jnp.take_along_axis(alli, sel, axis=1)
        return (best_v, best_i, z), None

    init = (jnp.full((b, k), neg, jnp.float32), jnp.zeros((b, k), jnp.int32), jnp.zeros((b,), jnp.float32))
    (v, i, z), sub_max = jax.lax.scan(body, init, jnp.arange(nb, dtype=jnp.int32))
    if k == 1:
        # stage 2: argmax inside each query's best sub-block of `sub` rows
        js = jnp.argmax(jnp.transpose(sub_max, (1, 0, 2)).reshape(b, nb * ns), axis=1).astype(jnp.int32)
        jb, off = js // ns, (js % ns) * sub
        cols = jax.vmap(lambda j, c: jax.lax.dynamic_slice_in_dim(block(j), c, sub, axis=1))(jb, off)  # (B,E,sub)
        s = jnp.einsum("be,bek->bk", q, cols, preferred_element_type=jnp.float32)
        row = (jb * bs + off)[:, None] + jnp.arange(sub, dtype=jnp.int32)[None, :]
        s = jnp.where(row < n_valid, s, neg)
        ii = jnp.argmax(s, axis=1).astype(jnp.int32)
        v = jnp.take_along_axis(s, ii[:, None], axis=1)
        i = row[jnp.arange(b), ii][:, None]
    prob = jnp.exp((v - shift[:, None]) * inv_tau) / z[:, None] if with_prob else jnp.full_like(v, jnp.nan)
    return MatchResult(index=i, score=v, prob=prob)


def match(queries, library, k: int = 1, tau: float = 0.1, block: int | None = None) -> MatchResult:
    """Convenience wrapper: validate, pad and match (``block=None``: :func:`auto_block`)."""
    queries = jnp.asarray(queries)
    if queries.ndim != 2:
        raise ValueError(f"queries must be (B, E), got shape {queries.shape}")
    if block is None:
        block = auto_block(queries.shape[0], int(np.shape(library)[0]))
    if np.ndim(library) != 2:
        raise ValueError(f"library must be (N, E), got shape {np.shape(library)}")
    blocks, n = pad_library(library, block)
    if queries.shape[1] != blocks.shape[-2]:
        raise ValueError(f"query dimension {queries.shape[1]} != library dimension {blocks.shape[-2]}")
    if not 1 <= k <= n:
        raise ValueError(f"k must be in [1, {n}], got {k}")
    return match_blocks(queries, blocks, n_valid=n, k=k, tau=tau)


def match_dense(queries, library, k: int = 1, tau: float = 0.1) -> MatchResult:
    """Reference implementation materialising all B x N scores (for tests and benchmarks)."""
    s = jnp.asarray(queries) @ jnp.asarray(library).T
    v, i = jax.lax.top_k(s, k)
    lse = jax.nn.logsumexp(s / tau, axis=1)
    return MatchResult(index=i.astype(jnp.int32), score=v, prob=jnp.exp(v / tau - lse[:, None]))


# --------------------------------------------------------------------------- Implicit-PDF head
#: Scores (crops x rotations x hidden units) alive at once in :func:`ipdf_match_blocks`.
IPDF_CHUNK_ELEMS = 1 << 22


def ipdf_match_blocks(head: dict, queries, feat_blocks, obj_idx, n_valid: int, k: int = 1) -> MatchResult:
    """Top-k library rotations for an Implicit-PDF head (``rot_head="ipdf"``), whose score is an
    MLP of the crop embedding and the rotation, so nothing per rotation can be precomputed but
    its encoding.

    ``head``: the model's ``rot_head`` parameters (per-object leaves); ``queries`` (B, E) crop
    embeddings; ``feat_blocks`` ``(nb, D, block)``: the library's rotation encodings
    (:func:`sc6d_jax.model.rotation_features`, shared by all objects) packed by
    :func:`pad_library`; ``obj_idx`` (B,). Every block is scored in chunks of at most
    :data:`IPDF_CHUNK_ELEMS` hidden activations, with a running top-k and a running
    log-sum-exp: ``score`` is the head's logit, ``prob`` its softmax over the whole library
    (what training's InfoNCE normalised).
    """
    nb, d, bs = feat_blocks.shape
    b = queries.shape[0]
    obj_idx = jnp.asarray(obj_idx, jnp.int32)
    sel = jax.tree.map(lambda a: a[obj_idx], head)  # leaves (B, ...)
    h = sel["hidden"]["w"].shape[-1]
    a_img = jnp.einsum("be,beh->bh", queries.astype(jnp.float32), sel["img_in"]["w"]) + sel["rot_in"]["b"]
    sub = int(np.gcd(bs, 1 << max(int(np.log2(max(IPDF_CHUNK_ELEMS // max(b * h, 1), 1))), 0)))
    ns = bs // sub
    neg = jnp.float32(-jnp.inf)
    kk = min(k, sub)

    def body(carry, js):
        best_v, best_i, m, z = carry
        j, c = js // ns, js % ns
        f = jax.lax.dynamic_slice_in_dim(jax.lax.dynamic_index_in_dim(feat_blocks, j, 0, False), c * sub, sub, axis=1)
        x = jax.nn.relu(a_img[:, None, :] + jnp.einsum("dq,bdh->bqh", f, sel["rot_in"]["w"]))
        x = jax.nn.relu(jnp.einsum("bqh,bhg->bqg", x, sel["hidden"]["w"]) + sel["hidden"]["b"][:, None, :])
        s = jnp.einsum("bqg,bg->bq", x, sel["out"]["w"][..., 0]) + sel["out"]["b"]  # (B, sub)
        row = js * sub + jnp.arange(sub, dtype=jnp.int32)
        s = jnp.where(row[None, :] < n_valid, s, neg)
        m_new = jnp.maximum(m, jnp.max(s, axis=1))
        z = z * jnp.exp(m - m_new) + jnp.sum(jnp.exp(s - m_new[:, None]), axis=1)
        v, i = jax.lax.top_k(s, kk)
        allv = jnp.concatenate([best_v, v], axis=1)
        alli = jnp.concatenate([best_i, row[i]], axis=1)
        best_v, pick = jax.lax.top_k(allv, k)
        return (best_v, jnp.take_along_axis(alli, pick, axis=1), m_new, z), None

    init = (jnp.full((b, k), neg, jnp.float32), jnp.zeros((b, k), jnp.int32), jnp.full((b,), -1e30, jnp.float32),
            jnp.zeros((b,), jnp.float32))
    (v, i, m, z), _ = jax.lax.scan(body, init, jnp.arange(nb * ns, dtype=jnp.int32))
    return MatchResult(index=i, score=v, prob=jnp.exp(v - m[:, None]) / z[:, None])


def match_library(head: dict, rot_head: str, queries, blocks, n_valid: int, k: int, tau, with_prob: bool,
                  obj_idx) -> MatchResult:
    """Top-k library rotations of each query with the model's rotation head: cosine matching of
    per-object embedding blocks (``rot_head="so3"``, :func:`match_blocks`) or the Implicit-PDF
    head over the rotations' encodings (``(1, nb, D, block)``, :func:`ipdf_match_blocks`, which
    always gives probabilities). ``head``: the model's ``rot_head`` parameters."""
    if rot_head == "ipdf":
        return ipdf_match_blocks(head, queries, blocks[0], obj_idx, n_valid, k)
    return _match_blocks(queries, blocks, n_valid, k, tau, with_prob, obj_idx)
