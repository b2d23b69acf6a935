"""Ship a trained run as a named pretrained model inside the package.

    python experiments/ship_model.py RUN_DIR NAME [--step N] [--note TEXT]

writes the parameters (no optimiser state) and the config of the run's newest checkpoint to
``sc6d_jax/assets/pretrained/NAME/``, so that ``Estimator.load(NAME)`` and
``sc6d predict --run NAME`` find it (see ``sc6d_jax.pretrained``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from sc6d_jax import pretrained


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path, help="training run directory")
    ap.add_argument("name", choices=sorted(pretrained.KNOWN), help="name of the shipped model")
    ap.add_argument("--step", type=int, default=None, help="checkpoint step (newest by default)")
    ap.add_argument("--note", default="", help="how the model was trained (stored in meta.json)")
    a = ap.parse_args(argv)
    out = pretrained.ship(a.run, pretrained.PRETRAINED_DIR / a.name, step=a.step, note=a.note)
    size = sum(p.stat().st_size for p in out.iterdir())
    print(f"{out}: {size / 1e6:.1f} MB")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
