"""Does a small library plus continuous refinement match a big library? (issue 5)

    .venv/bin/python experiments/bench_refine.py [--run builtin] [--objects 1,5,9] [--crops 64]
                                                 [--small 20000] [--big 1440000]

For crops rendered by the training stream (held-out seed), each object's crop embeddings are
matched against the SO(3) encoder's library of ``--small`` and of ``--big`` rotations, and the
small library's best rotation is refined on the manifold (optimistix BFGS, as ``--refine`` does
in ``sc6d predict``). Printed per object and overall (medians):

- the objective itself: the cosine reached by small, small + refinement and big;
- the share of crops where small + refinement reaches at least the big library's cosine;
- the angle between the rotation of small + refinement and that of the big library;
- the angle to the ground truth (allocentric; not symmetry-aware, so symmetric objects look worse
  than they are) for each;
- ms per crop of matching (+ refinement), same run.

The ground truth depends on how good the model is; the first three lines do not: they say whether
refinement finds what the big library finds.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", default="builtin", help="run directory or shipped model name (default builtin)")
    ap.add_argument("--models", type=Path, default=None, help="models folder (default: the built-in objects)")
    ap.add_argument("--objects", default="1,5,9", help="comma-separated object ids")
    ap.add_argument("--crops", type=int, default=64, help="crops per object")
    ap.add_argument("--small", type=int, default=20_000)
    ap.add_argument("--big", type=int, default=1_440_000)
    ap.add_argument("--seed", type=int, default=12345, help="stream seed (not the training seed)")
    a = ap.parse_args(argv)

    import jax
    import jax.numpy as jnp

    from sc6d_jax.checkpoint import load_checkpoint
    from sc6d_jax.data import CropStream, StreamConfig
    from sc6d_jax.geometry import geodesic_angle, so3_grid
    from sc6d_jax.inference import match, refine_rotations
    from sc6d_jax.inference._library import library_grid
    from sc6d_jax.model import apply, encode_rotations
    from sc6d_jax.pretrained import check_run

    params, cfg = load_checkpoint(check_run(a.run))
    params = jax.tree.map(jnp.asarray, params)
    mcfg = cfg.model
    trained = list(cfg.stream.obj_ids)
    ids = [int(x) for x in a.objects.split(",")]
    unknown = [i for i in ids if i not in trained]
    if unknown:
        raise SystemExit(f"objects {unknown} are not in the model (it knows {trained})")
    tmp = tempfile.TemporaryDirectory()
    models = a.models
    if models is None:
        from sc6d_jax.objects import write_models

        models = write_models(Path(tmp.name) / "models")
    tau = cfg.loss.tau

    def timed(f, *args):
        jax.block_until_ready(f(*args))  # compile
        t = time.perf_counter()
        out = jax.block_until_ready(f(*args))
        return out, (time.perf_counter() - t) * 1e3

    grids = {n: jnp.asarray(so3_grid(*library_grid(n))) for n in (a.small, a.big)}
    rows = []
    print(f"model {a.run}: {len(trained)} objects; libraries {a.small} and {a.big}; {a.crops} crops per object")
    for oid in ids:
        o = trained.index(oid)
        scfg = StreamConfig(str(models), crop_size=mcfg.crop_size, batch_size=a.crops, seed=a.seed, workers=0,
                            obj_ids=(oid,), augment=False)
        with CropStream(scfg) as stream:
            b = stream.batch(0)
        out = apply(params, mcfg, jnp.asarray(b["rgb"]), jnp.asarray(b["pe"]) if mcfg.use_pe else None,
                    jnp.full((a.crops,), o, jnp.int32))
        q = out["rot_emb"]
        R_gt = jnp.asarray(b["R_allo"])
        res = {}
        for n, R in grids.items():
            emb = jnp.concatenate([encode_rotations(params, mcfg, R[s : s + 65536], o)
                                   for s in range(0, R.shape[0], 65536)])
            m, ms = timed(lambda q, e: match(q, e, k=1, tau=tau), q, emb)
            res[n] = (R[m.index[:, 0]], m.score[:, 0], ms)
            del emb
        R0 = res[a.small][0]
        embed = lambda R, obj: encode_rotations(params, mcfg, R, obj)
        (R_ref, cos_ref), ms_ref = timed(
            jax.jit(lambda q, R0: refine_rotations(embed, q, R0, jnp.full((a.crops,), o, jnp.int32))), q, R0)
        deg = lambda A, B: np.degrees(np.asarray(geodesic_angle(A, B)))
        row = dict(
            obj=oid,
            cos_small=float(np.median(res[a.small][1])), cos_ref=float(np.median(cos_ref)),
            cos_big=float(np.median(res[a.big][1])),
            ref_ge_big=float(np.mean(np.asarray(cos_ref) >= np.asarray(res[a.big][1]) - 1e-4)),
            ref_vs_big_deg=float(np.median(deg(R_ref, res[a.big][0]))),
            small_vs_big_deg=float(np.median(deg(R0, res[a.big][0]))),
            gt_small=float(np.median(deg(R0, R_gt))), gt_ref=float(np.median(deg(R_ref, R_gt))),
            gt_big=float(np.median(deg(res[a.big][0], R_gt))),
            ms_small=res[a.small][2] / a.crops, ms_ref=(res[a.small][2] + ms_ref) / a.crops,
            ms_big=res[a.big][2] / a.crops,
        )
        rows.append(row)
        print(f"obj {oid:2d}: cosine {row['cos_small']:.4f} (small) {row['cos_ref']:.4f} (small+refine) "
              f"{row['cos_big']:.4f} (big); refine >= big in {100 * row['ref_ge_big']:.0f} %; "
              f"angle to big's pick {row['small_vs_big_deg']:.2f} -> {row['ref_vs_big_deg']:.2f} deg; "
              f"to GT {row['gt_small']:.1f} / {row['gt_ref']:.1f} / {row['gt_big']:.1f} deg; "
              f"ms/crop {row['ms_small']:.2f} / {row['ms_ref']:.2f} / {row['ms_big']:.2f}", flush=True)
    med = {k: float(np.median([r[k] for r in rows])) for k in rows[0] if k != "obj"}
    print(f"\nmedian over objects: cosine {med['cos_small']:.4f} / {med['cos_ref']:.4f} / {med['cos_big']:.4f} "
          f"(small / small+refine / big); small+refine reaches the big library's cosine in "
          f"{100 * med['ref_ge_big']:.0f} % of crops; angle to the big library's pick "
          f"{med['small_vs_big_deg']:.2f} -> {med['ref_vs_big_deg']:.2f} deg; ms per crop "
          f"{med['ms_small']:.2f} / {med['ms_ref']:.2f} / {med['ms_big']:.2f}")
    tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
