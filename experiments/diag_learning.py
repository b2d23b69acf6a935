"""Why does the ``cpu`` preset learn slowly?  A diagnostic: the cpu network trained on a fixed set
of pre-rendered easy batches (plain backgrounds, no occluders, no augmentation), printing the
rotation loss every 50 steps.

    python experiments/diag_learning.py --models runs/objects/models --objects all --batches 1 --steps 300
    python experiments/diag_learning.py --models runs/objects/models --objects 1 --batches 400 --steps 400
    python experiments/diag_learning.py --models runs/objects/models --objects all --batches 400 --steps 400 [--gn-groups 4] [--lr 3e-3]

Measured on 2 cores (the figures in the cpu preset's comment and the README):
- one batch, all 14 objects: the rotation loss 9.0 -> 0.13 in 50 steps (the network can fit);
- 400 fresh batches of one object (L-bracket): 9.2 -> 6.2 in 350 steps (lr 1e-3 and 3e-3 alike);
- 400 fresh batches of all 14 objects: stays at about ln(5001) = 8.52 for 400 steps (GroupNorm
  with 4 or 32 groups alike): learning is per object.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--models", required=True, help="BOP models folder (e.g. sc6d objects --out DIR)")
    ap.add_argument("--objects", default="all", help="'all' or comma-separated object ids")
    ap.add_argument("--batches", type=int, default=400, help="distinct pre-rendered batches of 32 crops")
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--gn-groups", type=int, default=None, help="GroupNorm groups (preset's by default)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override a field of the cpu preset, as in sc6d train --set (e.g. model.per_object_rot_out=true)")
    a = ap.parse_args(argv)

    import jax
    import optax

    from sc6d_jax import model
    from sc6d_jax.data import CropStream, StreamConfig, delta_z_range
    from sc6d_jax.train import preset
    from sc6d_jax.train.cli import apply_overrides

    objs = None if a.objects == "all" else tuple(int(x) for x in a.objects.split(","))
    scfg = StreamConfig(a.models, crop_size=64, batch_size=32, workers=0, curriculum=10**9, occlusion=0.0,
                        obj_ids=objs, augment=False)
    keys = ("rgb", "pe", "mask_visib", "R_allo", "delta_xy", "delta_z", "obj_idx", "K")
    with CropStream(scfg) as s:
        batches = [{k: v for k, v in s.batch(i).items() if k in keys} for i in range(a.batches)]
        n_obj = len(s.obj_ids)
    tc = apply_overrides(preset("cpu"), a.set)
    z_range = delta_z_range(scfg, focal_ref=model.F_REF if tc.loss.z_norm == "focal" else None)
    mc = dataclasses.replace(tc.model, n_objects=n_obj)
    if a.gn_groups is not None:
        mc = dataclasses.replace(mc, gn_groups=a.gn_groups)
    params = model.init(jax.random.PRNGKey(0), mc)
    opt = optax.adamw(a.lr, weight_decay=1e-4)
    state = opt.init(params)

    @jax.jit
    def step(params, state, batch, key):
        (_, aux), g = jax.value_and_grad(model.loss_fn, has_aux=True)(params, mc, tc.loss, batch, key, z_range)
        updates, state = opt.update(g, state, params)
        return optax.apply_updates(params, updates), state, aux

    key, t0 = jax.random.PRNGKey(1), time.perf_counter()
    for i in range(a.steps):
        key, k = jax.random.split(key)
        params, state, aux = step(params, state, batches[i % len(batches)], k)
        if i % 50 == 0 or i == a.steps - 1:
            print(f"step {i:4d}  rotation loss {float(aux['loss_rot']):.2f}  top-1 {float(aux['rot_top1']):.2f}  "
                  f"offset error {float(aux['xy_abs_err']):.3f}  {time.perf_counter() - t0:.0f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
