"""Inference benchmark: matching vs its memory-bandwidth bound, and end-to-end latency.

    .venv/bin/python experiments/bench_infer.py [--sizes 20000,480000] [--batches 1,8,32,64]
                                                [--presets cpu,paper] [--repeats 5]

Prints medians (ms). Matching: ``match_blocks`` (k = 1, two-stage argmax) per query at each
batch, with and without the library-wide softmax probabilities, and the batch-1 ratio to the
bandwidth bound = library bytes / measured copy bandwidth (numpy copy of the same bytes).
Per-object libraries (``--objects 14``): a batch whose queries all belong to one object against
one spread over every object (each query is matched against its own object's library only, so
the cost grows with the number of distinct objects in the batch).
End-to-end: ``predict_crops`` (network + matching + translation; random parameters of the
preset's architecture, one object) per crop and crops/s, with and without TTA.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np


def med(f, *a, repeats=5):
    jax.block_until_ready(f(*a))
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(f(*a))
        ts.append(time.perf_counter() - t)
    return float(np.median(ts)) * 1e3


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", default="20000,60000,180000,480000,1440000")
    ap.add_argument("--batches", default="1,8,32,64")
    ap.add_argument("--presets", default="cpu,paper")
    ap.add_argument("--e2e-sizes", default="480000", help="library sizes for the end-to-end runs")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--objects", type=int, default=14, help="objects of the per-object matching run")
    ap.add_argument("--objects-size", type=int, default=480000, help="library size of the per-object matching run")
    ap.add_argument("--shipped", default=None,
                    help="also time Estimator.predict of a shipped model (e.g. builtin): batch 32, one object vs all")
    args = ap.parse_args()
    sizes = [int(s) for s in args.sizes.split(",")]
    batches = [int(b) for b in args.batches.split(",")]
    from sc6d_jax.inference import auto_block, match_blocks, pad_library

    rng = np.random.default_rng(0)
    E = 32
    print(f"jax {jax.__version__}, devices {jax.devices()}")
    print("\n== matching (k=1), ms per query; bound = library bytes / numpy copy bandwidth ==")
    for n in sizes:
        lib = rng.normal(size=(n, E)).astype(np.float32)
        lib /= np.linalg.norm(lib, axis=1, keepdims=True)
        nbytes = lib.nbytes
        t_copy = med(lambda a: a.copy(), lib, repeats=args.repeats)
        bw = nbytes / (t_copy * 1e-3)
        bound = nbytes / bw * 1e3  # = t_copy (read + write); read-only bound is about half
        row = [f"N={n:>8}", f"copy {t_copy:7.2f} ms ({bw / 1e9:5.1f} GB/s)"]
        for b in batches:
            q = jnp.asarray(lib[rng.integers(0, n, b)] + 0.01)
            blocks, nv = pad_library(lib, auto_block(b, n))
            t0 = med(lambda q, bl: match_blocks(q, bl, n_valid=nv, k=1, with_prob=False), q, blocks, repeats=args.repeats)
            t1 = med(lambda q, bl: match_blocks(q, bl, n_valid=nv, k=1, with_prob=True), q, blocks, repeats=args.repeats)
            row.append(f"B={b}: {t0 / b:6.3f} ({t1 / b:6.3f} w/ prob)")
            if b == 1:
                row.append(f"ratio to bound {t0 / bound:4.2f}")
        print("  ".join(row), flush=True)

    print(f"\n== matching with {args.objects} per-object libraries of {args.objects_size} (k=1, with probabilities), ms per query ==")
    libs = rng.normal(size=(args.objects, args.objects_size, E)).astype(np.float32)
    libs /= np.linalg.norm(libs, axis=2, keepdims=True)
    for b in batches:
        blocks, nv = pad_library(libs, auto_block(b, args.objects_size))
        q = jnp.asarray(libs[0, rng.integers(0, args.objects_size, b)] + 0.01)
        row = [f"B={b:3d}"]
        for name, obj in (("one object", np.zeros(b, np.int32)),
                          ("objects spread", (np.arange(b) % args.objects).astype(np.int32))):
            t = med(lambda q, bl, o: match_blocks(q, bl, n_valid=nv, k=1, obj_idx=o), q, blocks, jnp.asarray(obj),
                    repeats=args.repeats)
            row.append(f"{name}: {t / b:7.3f}")
        print("  ".join(row), flush=True)
    del libs

    from sc6d_jax.inference import pack_library, predict_crops
    from sc6d_jax.inference._library import embed_library, library_grid
    from sc6d_jax.geometry import so3_grid
    from sc6d_jax.model import init
    from sc6d_jax.train import preset

    print("\n== end to end predict_crops (1 object), ms per crop / crops per s ==")
    for name in args.presets.split(","):
        cfg = preset(name)
        mcfg = dataclasses.replace(cfg.model, n_objects=1)
        params = init(jax.random.PRNGKey(0), mcfg)
        S = mcfg.crop_size
        pb = [1, 4] if name == "paper" else batches
        for n in [int(s) for s in args.e2e_sizes.split(",")]:
            R = so3_grid(*library_grid(n))
            emb = embed_library(params, mcfg, R, progress=False)
            lib_R = jnp.asarray(R)
            for tta in (False, True):
                for b in pb:
                    blocks, nv = pack_library(emb, auto_block(b * (4 if tta else 1), n))
                    blocks = jnp.asarray(blocks)
                    rgb = jnp.asarray(rng.integers(0, 256, (b, S, S, 3), dtype=np.uint8))
                    K = jnp.broadcast_to(jnp.asarray([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]]), (b, 3, 3))
                    center = jnp.asarray(rng.uniform(200, 400, (b, 2)), jnp.float32)
                    side = jnp.full((b,), 120.0, jnp.float32)
                    obj = jnp.zeros((b,), jnp.int32)
                    f = lambda *a: predict_crops(params, blocks, lib_R, *a, mcfg=mcfg, lcfg=cfg.loss,
                                                 z_range=(50.0, 2000.0), n_valid=nv, tta=tta)
                    t = med(f, rgb, K, center, side, obj, repeats=args.repeats)
                    print(f"{name:6s} N={n:>8} tta={int(tta)} B={b:3d}: {t / b:8.2f} ms/crop  {1e3 * b / t:7.1f} crops/s",
                          flush=True)


    if args.shipped:
        shipped(args.shipped, args.repeats)


def shipped(name: str, repeats: int, batch: int = 32) -> None:
    """``Estimator.predict`` of a shipped model (crops, network, 480k matching, translation) on a
    random 640x480 image: ms per crop with every box of one object vs boxes over all objects."""
    from sc6d_jax import Estimator

    est = Estimator.load(name, progress=False)
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (480, 640, 3), dtype=np.uint8)
    K = np.array([[572.4, 0, 325.3], [0, 573.6, 242.0], [0, 0, 1]])
    ids_all = list(est.obj_ids)
    boxes = np.column_stack([rng.uniform(50, 400, batch), rng.uniform(50, 300, batch), rng.uniform(40, 120, (batch, 2))])
    print(f"\n== Estimator.predict, shipped model {name!r} ({len(ids_all)} objects, {est.library.size} rotations), batch {batch} ==")
    for label, ids in (("one object", [ids_all[0]] * batch),
                       ("all objects", [ids_all[i % len(ids_all)] for i in range(batch)])):
        t = med(lambda: est.predict(img, K, boxes, ids), repeats=repeats)
        print(f"{label:12s}: {t / batch:7.2f} ms per crop", flush=True)


if __name__ == "__main__":
    main()
