"""What a checkpoint of a long run would score if the run ended now: a short cool-down probe.

    python experiments/anneal_probe.py --run runs/long --models runs/objects/models --out runs/probe-30k \\
        [--step 30000] [--steps 2000] [--workers 1] [--set loss.turn_negatives=true ...]

A long cosine run spends most of its steps at a high learning rate, where the validation curve
is noisy and flat-looking while the model still improves underneath: most of the gain comes in
the final decay. The probe starts from a checkpoint's parameters (fresh optimiser moments, a
warm-up of 1 %), decays the learning rate from the run's current value to its ``lr_end`` over
``--steps`` steps on the full stream (no curriculum), and validates on the run's own validation
crops (same seed) at the end. Probes of successive checkpoints, each with the same ``--steps``,
say whether the run is still learning. The run itself is left untouched.

Writes ``OUT/`` (a training run: config, checkpoints, metrics.jsonl) and prints the run's
validation record at ``--step`` next to the probe's.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

def _fmt(rec: dict | None) -> str:
    if not rec:
        return "no validation record"
    return (f"AR {rec['val_ar']:.3f}, rotation {rec['val_rot_median_deg']:.1f} deg, "
            f"depth {100 * rec['val_depth_rel_median']:.2f} %, under 10 deg {rec['val_rot_under_10']:.2f}")


def run_record(run: Path, step: int) -> dict | None:
    """The run's validation record at ``step`` (None without one)."""
    path = run / "metrics.jsonl"
    if not path.is_file():
        return None
    for line in path.read_text().splitlines():
        rec = json.loads(line)
        if rec.get("step") == step and "val_ar" in rec:
            return rec
    return None


def setup(run: Path, step: int | None, steps: int, val_crops: int | None = None,
          sets: list[str] | None = None) -> tuple[int, object, object]:
    """(step, parameters of the checkpoint, the probe's TrainConfig) for ``run`` at ``step``;
    ``sets``: ``sc6d train --set`` overrides of the probe's loss, stream or optimiser (a same-start
    A/B of a recipe change); ValueError for one that would change the model."""
    from sc6d_jax.checkpoint import find_checkpoint, load_checkpoint, read_meta
    from sc6d_jax.train.loop import make_optimizer

    step = int(read_meta(find_checkpoint(run, step))["step"])
    params, cfg = load_checkpoint(run, step, raw=True)  # the run's own trajectory, not its average
    lr_now = float(make_optimizer(cfg)[1](step))
    optim = dataclasses.replace(cfg.optim, lr=max(lr_now, cfg.optim.lr_end), warmup_steps=0, warmup_fraction=0.01)
    stream = dataclasses.replace(cfg.stream, curriculum=0, curriculum_fraction=0.0)
    pcfg = cfg.replace(optim=optim, stream=stream, steps=steps, checkpoint_every=steps, keep_checkpoints=1,
                       preset=f"anneal-probe:{cfg.preset}@{step}", ema=0.0,
                       val_crops=cfg.val_crops if val_crops is None else val_crops)
    if sets:
        from sc6d_jax.train.cli import apply_overrides

        changed = apply_overrides(pcfg, list(sets))
        if changed.model != pcfg.model:
            raise ValueError(f"--set {' '.join(sets)}: a probe cannot change the model (the checkpoint's parameters fix it)")
        pcfg = changed
    return step, params, pcfg


def probe(run: Path, models: Path, out: Path, step: int | None, steps: int, workers: int = 1,
          val_crops: int | None = None, sets: list[str] | None = None) -> tuple[int, dict]:
    """Train the cool-down from ``run``'s checkpoint at ``step`` into ``out``; (step, final record)."""
    from sc6d_jax.train import train
    from sc6d_jax.train.loop import ModelFns, _default_model_fns

    step, params, pcfg = setup(run, step, steps, val_crops, sets)
    fns = ModelFns(lambda key, mcfg: params, _default_model_fns().loss_fn, None)
    train(pcfg, models, out, resume=(out / "checkpoints").is_dir(), workers=workers, model_fns=fns,
          progress=sys.stderr.isatty())
    return step, run_record(out, steps) or {}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run", required=True, type=Path, help="the long run's directory")
    p.add_argument("--models", required=True, type=Path, help="its BOP models folder")
    p.add_argument("--out", required=True, type=Path, help="output run directory of the probe")
    p.add_argument("--step", type=int, default=None, help="checkpoint step (newest by default)")
    p.add_argument("--steps", type=int, default=2000, help="cool-down steps (default 2000)")
    p.add_argument("--workers", type=int, default=1)
    p.add_argument("--val-crops", type=int, default=None, help="validation crops (the run's by default)")
    p.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE",
                   help="override the probe's loss / stream / optim settings (as sc6d train --set; repeatable): "
                        "probes with and without a change, from the same checkpoint, are a same-start A/B")
    a = p.parse_args(argv)
    os.environ.setdefault("MUJOCO_GL", "egl")
    if not (a.run / "checkpoints").is_dir():
        print(f"anneal_probe: error: {a.run} has no checkpoints/ (not a training run)", file=sys.stderr)
        return 2
    if a.steps < 10:
        print("anneal_probe: error: --steps must be >= 10", file=sys.stderr)
        return 2
    try:
        step, rec = probe(a.run, a.models, a.out, a.step, a.steps, a.workers, a.val_crops, a.sets)
    except (FileNotFoundError, ValueError) as exc:
        print(f"anneal_probe: error: {exc}", file=sys.stderr)
        return 2
    print(f"run at step {step}: {_fmt(run_record(a.run, step))}")
    print(f"after a {a.steps}-step cool-down: {_fmt(rec)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
