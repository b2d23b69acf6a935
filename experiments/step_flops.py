"""The work of one training step, per configuration: XLA's count of floating-point operations and
bytes accessed for the gradient of the loss on one batch (network, SO(3) encoder, negatives,
losses; not the renderer, not the optimiser). A count, not a timing: it is the same on every
machine and can be taken while a training runs beside it; timings belong to benchmarks.

    python experiments/step_flops.py [--preset cpu] [--n-objects 14] \\
        --config base: --config fast:loss.n_negatives=1000,loss.n_local_negatives=64

Each ``--config NAME:KEY=VALUE,...`` is a list of ``--set`` overrides of ``--preset`` (as in
``experiments/learning_curve.py``). Prints GFLOP and GB per step and each configuration's ratio
to the first; ``--out FILE.csv`` also writes them.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "experiments"))


def step_cost(cfg, n_objects: int, seed: int = 0) -> dict[str, float]:
    """{"gflop", "gbytes"} of one gradient of the loss of ``cfg`` on a synthetic batch of its size."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from sc6d_jax import model as M
    from sc6d_jax.data._scene import random_rotation

    mcfg = dataclasses.replace(cfg.model, n_objects=n_objects)
    B, S = cfg.stream.batch_size, mcfg.crop_size
    rng = np.random.default_rng(seed)
    K = np.array([[600.0, 0, 320], [0, 600.0, 240], [0, 0, 1]], np.float32)
    batch = {
        "rgb": jnp.asarray(rng.integers(0, 256, (B, S, S, 3)), jnp.uint8),
        "pe": jnp.zeros((B, S, S, 2), jnp.float32),
        "mask_visib": jnp.asarray(rng.integers(0, 2, (B, S, S)), jnp.uint8),
        "R_allo": jnp.asarray(np.stack([random_rotation(rng) for _ in range(B)]), jnp.float32),
        "delta_xy": jnp.zeros((B, 2), jnp.float32),
        "delta_z": jnp.full((B,), 1000.0, jnp.float32),
        "obj_idx": jnp.asarray(rng.integers(0, n_objects, B), jnp.int32),
        "K": jnp.asarray(np.broadcast_to(K, (B, 3, 3))),
        "difficulty": jnp.ones((B,), jnp.float32),
    }
    params = M.init(jax.random.PRNGKey(seed), mcfg)
    z_range = (500.0, 3000.0)
    grad = jax.jit(jax.grad(lambda p: M.loss_fn(p, mcfg, cfg.loss, batch, jax.random.PRNGKey(1), z_range)[0]))
    c = grad.lower(params).compile().cost_analysis()
    c = c[0] if isinstance(c, (list, tuple)) else c
    return {"gflop": float(c["flops"]) / 1e9, "gbytes": float(c.get("bytes accessed", 0.0)) / 1e9}


def main(argv: list[str] | None = None) -> int:
    from learning_curve import parse_config

    from sc6d_jax.train import preset
    from sc6d_jax.train.cli import apply_overrides

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--preset", default="cpu")
    p.add_argument("--n-objects", type=int, default=1, help="objects the model holds (1 = one-object runs)")
    p.add_argument("--config", action="append", help="NAME:KEY=VALUE,... (repeatable; default: the preset)")
    p.add_argument("--out", type=Path, default=None, help="also write the figures to this CSV")
    a = p.parse_args(argv)
    if a.n_objects < 1:
        print("step_flops: error: --n-objects must be >= 1", file=sys.stderr)
        return 2
    try:
        configs = [parse_config(c) for c in (a.config or ["preset:"])]
        cfgs = [(name, apply_overrides(preset(a.preset), sets)) for name, sets in configs]
    except (ValueError, KeyError, TypeError) as exc:
        print(f"step_flops: error: {exc}", file=sys.stderr)
        return 2
    rows = []
    for name, cfg in cfgs:
        c = step_cost(cfg, a.n_objects)
        rows.append({"config": name, "n_objects": a.n_objects, **c, "ratio": c["gflop"] / (rows[0]["gflop"] if rows else c["gflop"])})
        r = rows[-1]
        print(f"{name:>16}: {r['gflop']:6.2f} GFLOP, {r['gbytes']:5.2f} GB per step ({r['ratio']:.2f}x the first)", flush=True)
    if a.out is not None:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        with open(a.out, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
        print(f"step_flops: wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
