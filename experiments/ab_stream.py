"""Same-run A/B of the training stream: this checkout against another one, alternating rounds.

    git worktree add /tmp/old REV
    python experiments/ab_stream.py /tmp/old [--rounds 4] [--size 128] [--workers 2] [--crops 1500]

Each round times the full stream (``bench_render.time_stream``: median of 3 repeats) once
with the other checkout's code and once with this one's, each in a fresh process run from a
temporary folder with its checkout first on PYTHONPATH (so neither the working directory nor
the editable install decides which ``sc6d_jax`` is imported). Prints every round, the medians
and their ratio; the machine's load drifts, so only same-run ratios are worth comparing.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parents[1]

_CHILD = """
import sys, tempfile
from pathlib import Path
import sc6d_jax, bench_render
from sc6d_jax.objects import write_models
assert Path(sc6d_jax.__file__).resolve().is_relative_to(Path(sys.argv[1]).resolve()), sc6d_jax.__file__
with tempfile.TemporaryDirectory() as tmp:
    models = write_models(Path(tmp) / "models")
    print(bench_render.time_stream(models, int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]), 3))
"""


def time_checkout(root: Path, size: int, workers: int, crops: int) -> float:
    env = dict(os.environ, PYTHONPATH=f"{root}{os.pathsep}{root / 'experiments'}")
    env.setdefault("MUJOCO_GL", "egl")
    with tempfile.TemporaryDirectory() as cwd:
        out = subprocess.run(
            [sys.executable, "-c", _CHILD, str(root), str(size), str(workers), str(crops)],
            env=env, cwd=cwd, capture_output=True, text=True,
        )
    if out.returncode != 0:
        raise RuntimeError(f"timing {root} failed:\n{out.stderr[-2000:]}")
    return float(out.stdout.strip().splitlines()[-1])


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("other", type=Path, help="the other checkout (e.g. a git worktree of an older commit)")
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--crops", type=int, default=1500)
    a = ap.parse_args(argv)
    if not (a.other / "sc6d_jax" / "data").is_dir():
        ap.error(f"{a.other} is not a checkout of this project (no sc6d_jax/data)")
    res: dict[str, list[float]] = {"other": [], "this": []}
    for r in range(a.rounds):
        for name, root in (("other", a.other.resolve()), ("this", HERE)):
            v = time_checkout(root, a.size, a.workers, a.crops)
            res[name].append(v)
            print(f"round {r + 1}: {name:5s} {v:7.0f} crops/s", flush=True)
    med = {k: statistics.median(v) for k, v in res.items()}
    print(
        f"{a.size}x{a.size}, {a.workers} workers, {a.rounds} rounds: this {med['this']:.0f} vs other "
        f"{med['other']:.0f} crops/s (median), ratio {med['this'] / med['other']:.2f}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
