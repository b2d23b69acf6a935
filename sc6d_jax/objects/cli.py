"""``sc6d objects --out DIR``: write the built-in object set as a BOP models/ folder."""

from __future__ import annotations

import argparse
from pathlib import Path


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(prog="sc6d objects", description=__doc__)
    p.add_argument("--out", type=Path, required=True, help="models folder to write (must not exist unless --overwrite)")
    p.add_argument("--seed", type=int, default=0, help="seed of the sizes and colours (default 0)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing folder")
    a = p.parse_args(argv)
    from sc6d_jax.objects import builtin_objects, model_info, write_models

    write_models(a.out, seed=a.seed, overwrite=a.overwrite)
    print(f"wrote {a.out}:")
    print(f"{'id':>3}  {'name':<12} {'diameter mm':>11}  symmetry")
    for o in builtin_objects(a.seed):
        info = model_info(o)
        sym = "continuous" if o.symmetries_continuous else (f"{len(o.symmetries_discrete) + 1}-fold discrete" if o.symmetries_discrete else "none")
        print(f"{o.obj_id:>3}  {o.name:<12} {info.diameter:>11.1f}  {sym}")
    return 0
