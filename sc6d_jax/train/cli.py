"""``sc6d train``: train a model on crops streamed from the renderer.

Examples::

    sc6d train --models objects/models --out runs/cpu1 --preset cpu
    sc6d train --models objects/models --out runs/cpu1 --resume          # continue after a kill
    sc6d train --models M --out R --preset paper --init-weights resnet34.npz

Multi-host (every process runs the same command with its own --process-id; the run directory
must be on a filesystem all processes see; process 0 writes it)::

    sc6d train --models M --out R --preset paper \\
        --coordinator host0:1234 --num-processes 2 --process-id 0     # on host 0
    sc6d train ... --coordinator host0:1234 --num-processes 2 --process-id 1   # on host 1

With ``--resume`` and no ``--preset``, the config is read from ``RUN_DIR/config.json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

__all__ = ["main"]


def _obj_ids(text: str) -> tuple[int, ...]:
    try:
        ids = tuple(int(x) for x in text.split(",") if x.strip())
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"--obj-ids must be comma-separated integers, got {text!r}") from exc
    if not ids:
        raise argparse.ArgumentTypeError("--obj-ids is empty")
    return ids


def build_parser() -> argparse.ArgumentParser:
    from sc6d_jax.train.config import PRESETS

    p = argparse.ArgumentParser(prog="sc6d train", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--models", required=True, type=Path, help="folder of object models (BOP models/)")
    p.add_argument("--out", required=True, type=Path, help="run directory (config, metrics, checkpoints)")
    p.add_argument("--preset", default=None, help=f"config preset: {', '.join(PRESETS)} (default cpu)")
    p.add_argument("--steps", type=int, default=None, help="number of optimiser steps (preset's by default)")
    p.add_argument("--seed", type=int, default=None, help="seed of parameters, keys and data (default 0)")
    p.add_argument("--batch-size", type=int, default=None, help="global batch size (preset's by default)")
    p.add_argument("--obj-ids", type=_obj_ids, default=None, help="comma-separated BOP object ids (default all)")
    p.add_argument("--checkpoint-every", type=int, default=None, help="checkpoint interval in steps")
    p.add_argument("--log-every", type=int, default=None, help="metrics interval in steps")
    p.add_argument("--resume", action="store_true", help="continue from the newest checkpoint of --out")
    p.add_argument("--workers", type=int, default=None, help="renderer worker processes (does not change the data)")
    p.add_argument("--init-weights", type=Path, default=None, help="local ResNet weights file for the backbone")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--quiet", action="store_true", help="do not print the config")
    g = p.add_argument_group("multi-host (jax.distributed)")
    g.add_argument("--coordinator", default=None, help="HOST:PORT of process 0's coordinator service")
    g.add_argument("--num-processes", type=int, default=None, help="number of processes in the run")
    g.add_argument("--process-id", type=int, default=None, help="index of this process (0 = writer)")
    return p


def main(argv: list[str]) -> int:
    args = build_parser().parse_args(argv)
    dist = (args.coordinator, args.num_processes, args.process_id)
    if any(x is not None for x in dist):
        if any(x is None for x in dist):
            raise ValueError("--coordinator, --num-processes and --process-id must be given together")
        from sc6d_jax.train.loop import initialize_distributed

        initialize_distributed(args.coordinator, args.num_processes, args.process_id)

    from sc6d_jax.train.config import StreamSettings, TrainConfig, preset
    from sc6d_jax.train.loop import NonFiniteLossError, train

    if args.workers is not None and args.workers < 0:
        raise ValueError(f"--workers must be >= 0, got {args.workers}")
    saved = args.out / "config.json"
    if args.resume and args.preset is None and saved.is_file():
        cfg = TrainConfig.from_json(saved.read_text(encoding="utf-8"))
    else:
        cfg = preset(args.preset or "cpu")
    changes: dict = {}
    for name in ("steps", "seed", "checkpoint_every", "log_every"):
        if getattr(args, name) is not None:
            changes[name] = getattr(args, name)
    if args.batch_size is not None or args.obj_ids is not None:
        s = cfg.stream
        changes["stream"] = StreamSettings(
            batch_size=args.batch_size if args.batch_size is not None else s.batch_size,
            obj_ids=args.obj_ids if args.obj_ids is not None else s.obj_ids,
            augment=s.augment,
            occlusion=s.occlusion,
        )
        if args.obj_ids is not None:
            changes["model"] = dataclasses.replace(cfg.model, n_objects=len(args.obj_ids))
    if changes:
        cfg = cfg.replace(**changes)
    try:
        train(
            cfg, args.models, args.out, resume=args.resume, workers=args.workers,
            init_weights=args.init_weights, progress=not args.no_progress, verbose=not args.quiet,
        )
    except NonFiniteLossError as exc:
        print(f"sc6d train: error: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main(sys.argv[1:]))
