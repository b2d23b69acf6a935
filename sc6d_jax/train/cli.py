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

Any config field can be set with ``--set KEY=VALUE`` (repeatable; applied last), the key dotted
as in ``config.json``: ``--set loss.z_mode=regression --set model.use_pe=false --set
optim.lr=1e-3 --set stream.occlusion=none --set steps=200``. Values are parsed with the field's
type (bool: true/false/1/0/yes/no; tuples: comma-separated; ``none`` for optional fields).

A resumed run refuses a changed config, except with ``--amend``: the rest of the run then trains
under the changed stream or losses (e.g. ``--resume --amend --set stream.box_scale=1,1``) from its
newest checkpoint on, with its parameters, optimiser state and schedule; the change and its step
go to ``RUN_DIR/amendments.json`` (and into the run's curve). Later resumes continue bit for bit.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import types
import typing
from pathlib import Path
from typing import Any

__all__ = ["apply_overrides", "main", "parse_override"]

_SECTIONS = ("model", "loss", "stream", "optim")
_TRUE = {"true", "1", "yes", "on"}
_FALSE = {"false", "0", "no", "off"}


def _field_types(cls: type) -> dict[str, Any]:
    hints = typing.get_type_hints(cls)
    return {f.name: hints.get(f.name, Any) for f in dataclasses.fields(cls)}


def _convert(text: str, tp: Any, key: str) -> Any:
    """``text`` parsed as a value of the annotated type ``tp`` (ValueError naming ``key``)."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        if type(None) in args and text.strip().lower() in ("none", "null"):
            return None
        rest = [a for a in args if a is not type(None)]
        errors = []
        for a in rest:
            try:
                return _convert(text, a, key)
            except ValueError as exc:
                errors.append(str(exc))
        raise ValueError(errors[0] if len(errors) == 1 else f"--set {key}={text}: not a valid value ({'; '.join(errors)})")
    if origin is tuple:
        items = [x.strip() for x in text.strip().strip("()[]").split(",") if x.strip()]
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(x, args[0], key) for x in items)
        if len(items) != len(args):
            raise ValueError(f"--set {key}={text}: expected {len(args)} comma-separated values, got {len(items)}")
        return tuple(_convert(x, a, key) for x, a in zip(items, args))
    if tp is bool:
        low = text.strip().lower()
        if low in _TRUE:
            return True
        if low in _FALSE:
            return False
        raise ValueError(f"--set {key}={text}: expected a boolean (true/false)")
    if tp is int:
        try:
            return int(text.strip().replace("_", ""))
        except ValueError:
            raise ValueError(f"--set {key}={text}: expected an integer") from None
    if tp is float:
        try:
            return float(text)
        except ValueError:
            raise ValueError(f"--set {key}={text}: expected a number") from None
    if tp is str:
        return text
    raise ValueError(f"--set {key}: cannot set a field of type {tp!r} from the command line")


def parse_override(item: str) -> tuple[str, str]:
    """``"KEY=VALUE"`` -> ``(KEY, VALUE)`` (ValueError when there is no ``=`` or no key)."""
    key, sep, value = item.partition("=")
    key = key.strip()
    if not sep or not key:
        raise ValueError(f"--set expects KEY=VALUE (e.g. loss.z_mode=regression), got {item!r}")
    return key, value


def apply_overrides(cfg: Any, items: list[str]) -> Any:
    """A copy of the TrainConfig ``cfg`` with ``--set KEY=VALUE`` items applied in order.

    KEY is a top-level field (``steps``, ``seed``, ``z_range``, ...) or ``SECTION.FIELD`` with
    SECTION one of model, loss, stream, optim. Setting ``stream.obj_ids`` also sets
    ``model.n_objects`` unless that is set too. Raises ValueError naming an unknown key, a value
    that does not parse as the field's type, or one the config rejects.
    """
    from sc6d_jax.train.config import TrainConfig

    top = _field_types(TrainConfig)
    sections = {name: getattr(cfg, name) for name in _SECTIONS}
    changes: dict[str, Any] = {}
    sec_changes: dict[str, dict[str, Any]] = {name: {} for name in _SECTIONS}
    for item in items:
        key, text = parse_override(item)
        parts = key.split(".")
        if len(parts) == 1 and parts[0] in top and parts[0] not in _SECTIONS:
            changes[parts[0]] = _convert(text, top[parts[0]], key)
        elif len(parts) == 2 and parts[0] in _SECTIONS:
            types_ = _field_types(type(sections[parts[0]]))
            if parts[1] not in types_:
                raise ValueError(
                    f"--set: unknown config key {key!r}; fields of {parts[0]}: {', '.join(sorted(types_))}"
                )
            sec_changes[parts[0]][parts[1]] = _convert(text, types_[parts[1]], key)
        else:
            known = sorted(n for n in top if n not in _SECTIONS) + [f"{s}.FIELD" for s in _SECTIONS]
            raise ValueError(f"--set: unknown config key {key!r}; known: {', '.join(known)}")
    obj_ids = sec_changes["stream"].get("obj_ids")
    if obj_ids is not None and "n_objects" not in sec_changes["model"]:
        sec_changes["model"]["n_objects"] = len(obj_ids)
    for name, ch in sec_changes.items():
        if ch:
            try:
                changes[name] = dataclasses.replace(sections[name], **ch)
            except ValueError as exc:
                raise ValueError(f"--set {name}: {exc}") from exc
    if not changes:
        return cfg
    try:
        return cfg.replace(**changes)
    except ValueError as exc:
        raise ValueError(f"--set: {exc}") from exc


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
    p.add_argument("--amend", action="store_true",
                   help="with --resume: continue the run under its config changed by --set (the stream or the "
                        "losses only), recorded in RUN_DIR/amendments.json")
    p.add_argument("--workers", type=int, default=None, help="renderer worker processes (does not change the data)")
    p.add_argument("--init-weights", type=Path, default=None, help="local ResNet weights file for the backbone")
    p.add_argument("--init-from", default=None, metavar="RUN",
                   help="start from a trained model (run directory or shipped name, e.g. builtin): every "
                        "parameter not specific to its objects (the same as --set init_from=RUN)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--quiet", action="store_true", help="do not print the config")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="set a config field, e.g. loss.z_mode=regression, model.use_pe=false (repeatable)")
    g = p.add_argument_group("multi-host (jax.distributed)")
    g.add_argument("--coordinator", default=None, help="HOST:PORT of process 0's coordinator service")
    g.add_argument("--num-processes", type=int, default=None, help="number of processes in the run")
    g.add_argument("--process-id", type=int, default=None, help="index of this process (0 = writer)")
    return p


def build_config(args: argparse.Namespace) -> Any:
    """The TrainConfig of ``sc6d train``: the preset (or, resuming without --preset, the run's
    config.json), then --steps/--seed/--batch-size/--obj-ids/..., then every --set."""
    from sc6d_jax.train.config import TrainConfig, preset

    saved = args.out / "config.json"
    if args.resume and args.preset is None and saved.is_file():
        cfg = TrainConfig.from_json(saved.read_text(encoding="utf-8"))
    else:
        cfg = preset(args.preset or "cpu")
    changes: dict = {}
    for name in ("steps", "seed", "checkpoint_every", "log_every", "init_from"):
        if getattr(args, name) is not None:
            changes[name] = getattr(args, name)
    if args.batch_size is not None or args.obj_ids is not None:
        s = cfg.stream
        # every other stream setting (curriculum, distance, ...) is kept
        changes["stream"] = dataclasses.replace(
            s,
            batch_size=args.batch_size if args.batch_size is not None else s.batch_size,
            obj_ids=args.obj_ids if args.obj_ids is not None else s.obj_ids,
        )
        if args.obj_ids is not None:
            changes["model"] = dataclasses.replace(cfg.model, n_objects=len(args.obj_ids))
    if changes:
        cfg = cfg.replace(**changes)
    return apply_overrides(cfg, args.overrides)


def main(argv: list[str]) -> int:
    args = build_parser().parse_args(argv)
    dist = (args.coordinator, args.num_processes, args.process_id)
    if any(x is not None for x in dist):
        if any(x is None for x in dist):
            raise ValueError("--coordinator, --num-processes and --process-id must be given together")
        from sc6d_jax.train.loop import initialize_distributed

        initialize_distributed(args.coordinator, args.num_processes, args.process_id)

    from sc6d_jax.train.loop import NonFiniteLossError, train

    if args.workers is not None and args.workers < 0:
        raise ValueError(f"--workers must be >= 0, got {args.workers}")
    if args.amend and not args.resume:
        raise ValueError("--amend continues a run: it needs --resume")
    cfg = build_config(args)
    try:
        train(
            cfg, args.models, args.out, resume=args.resume, workers=args.workers,
            init_weights=args.init_weights, progress=not args.no_progress, verbose=not args.quiet,
            amend=args.amend,
        )
    except NonFiniteLossError as exc:
        print(f"sc6d train: error: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main(sys.argv[1:]))
