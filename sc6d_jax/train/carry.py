"""``sc6d carry``: copy a run's resumable state to a small folder for the next training leg.

Examples::

    sc6d carry --run runs/cpu1 --out state/cpu1              # after (or during) a leg
    git add state/cpu1 && git commit -m "cpu1: step 6000"     # carry it between machines
    sc6d train --models M --out state/cpu1 --resume           # next leg: train in the folder

A long training on a small machine runs in legs (a few hours each, maybe on different
machines).  What a resume needs is the config, the newest checkpoint (parameters, optimiser
state, step, base PRNG key and config; the crop stream is rebuilt from the seed and the step)
and, for the curve to continue, the metrics.  ``STATE_DIR`` receives exactly that:

- ``config.json``: the run's resolved config;
- ``checkpoints/ckpt_XXXXXXXX/``: the newest checkpoint only (its SHA-256 is checked first);
- ``metrics.jsonl``: the lines up to that checkpoint's step (later ones, from a leg killed
  between checkpoints, would be dropped by the resume anyway);
- ``val_shares.jsonl``: each validation crop's share of ``val_ar`` up to that step, if the run
  validates (paired comparisons on the same crops, ``experiments/learning_curve.py``);
- ``amendments.json``: the run's changes of config in mid-run (``sc6d train --amend``), if any;
- ``carry.json``: what was carried from where (informative; it also marks the folder as a carry).

It is a run directory as it is: ``sc6d train --models M --out STATE_DIR --resume`` continues it
bit for bit like an uninterrupted run (the models folder may live elsewhere on the next
machine; only ``config.json`` must match).  For the ``cpu`` preset it holds ~7 MB (parameters
and the two AdamW moments, float32).

``STATE_DIR`` is written atomically (a hidden temporary folder beside it, renamed when
complete).  An existing ``STATE_DIR`` is replaced only when it is an earlier carry of the same
run (``carry.json`` present, same config, a checkpoint no newer than the one carried; this
includes carrying a folder onto itself after training in it, which keeps only its newest
checkpoint) or an empty folder; anything else is refused with one error line (exit status 2),
as is a run directory without a checkpoint.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Any, NamedTuple

from sc6d_jax._io import atomic_directory
from sc6d_jax.checkpoint import checkpoint_dirs, read_metrics_upto, verify_state

__all__ = ["CARRY_FORMAT", "Carried", "carry", "main"]

CARRY_FORMAT = "sc6d-jax-carry/1"
_MARKER = "carry.json"


class Carried(NamedTuple):
    """What :func:`carry` wrote: the folder, the step of its checkpoint and its size in bytes."""

    out: Path
    step: int
    size_bytes: int


def _read_json(path: Path, what: str) -> Any:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise FileNotFoundError(f"{path} does not exist: {what}") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path} is not valid JSON ({exc})") from None


def _portable(path: str | None) -> str | None:
    """``path`` when it is relative, else None (an absolute path names one machine's folders)."""
    return path if path and not os.path.isabs(path) else None


def _write(path: Path, data: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _check_out(out: Path, run_dir: Path, config: dict[str, Any], step: int) -> None:
    """Refuse an ``out`` that exists and is not an earlier carry of this run (ValueError)."""
    from sc6d_jax.train.config import config_differences

    if run_dir.resolve() in out.resolve().parents:
        raise ValueError(f"--out {out} holds the run directory {run_dir}; choose another folder")
    if not out.exists():
        return
    if not out.is_dir():
        raise ValueError(f"--out {out} exists and is not a directory")
    if not any(out.iterdir()):
        return
    marker = out / _MARKER
    if not marker.is_file():
        raise ValueError(f"--out {out} exists and is not a carried state ({_MARKER} missing); "
                         "choose another folder or remove it")
    info = _read_json(marker, "")  # exists
    if not isinstance(info, dict) or info.get("format") != CARRY_FORMAT:
        raise ValueError(f"--out {out}: {marker} is not a {CARRY_FORMAT} marker; refusing to replace it")
    saved = _read_json(out / "config.json", "the carried state has no config")
    diff = config_differences(saved, config)
    if diff:
        raise ValueError(f"--out {out} holds the state of another run; differing: {'; '.join(diff)}")
    held = [s for s, _ in checkpoint_dirs(out)]
    if held and max(held) > step:
        raise ValueError(f"--out {out} holds step {max(held)}, newer than step {step} of {run_dir}; "
                         "refusing to go back (remove it first to carry an older state)")


def carry(run_dir: str | os.PathLike, out: str | os.PathLike) -> Carried:
    """Copy what a resume of ``run_dir`` needs into ``out`` (see the module docstring).

    Raises:
        FileNotFoundError: ``run_dir`` or its ``config.json`` does not exist, or it has no
            checkpoint.
        ValueError: the newest checkpoint is corrupt or of another config, or ``out`` exists
            and is not an earlier carry of the same run.  Nothing is changed then.
    """
    from sc6d_jax.train.config import config_differences

    run_dir, out = Path(run_dir), Path(out)
    if not run_dir.is_dir():
        raise FileNotFoundError(f"run directory {run_dir} does not exist")
    ckpts = checkpoint_dirs(run_dir)
    if not ckpts:
        raise FileNotFoundError(f"run directory {run_dir} has no checkpoint; nothing to carry")
    step, ckpt = ckpts[-1]
    meta, state = verify_state(ckpt)
    meta_bytes = (ckpt / "meta.json").read_bytes()
    cfg_path = run_dir / "config.json"
    config = _read_json(cfg_path, "not a training run directory")
    cfg_bytes = cfg_path.read_bytes()
    from sc6d_jax.train.loop import AMENDMENTS_FILE, VAL_SHARES, read_amendments

    amendments = [a for a in read_amendments(run_dir) if a["step"] <= step]
    diff = config_differences(config, meta["config"])
    if diff and not any(a["step"] == step for a in amendments):  # amended at this checkpoint: config.json is the new one
        raise ValueError(f"checkpoint {ckpt} was written for another config than {cfg_path}; "
                         f"differing: {'; '.join(diff)}")
    _check_out(out, run_dir, config, step)
    metrics = "".join(line + "\n" for line in read_metrics_upto(run_dir / "metrics.jsonl", step))
    shares = "".join(line + "\n" for line in read_metrics_upto(run_dir / VAL_SHARES, step))
    # The state is meant to be committed and moved between machines: no absolute path of this
    # machine goes with it (the models folder is informative; the next leg names its own).
    models_dir = _portable(meta.get("models_dir"))
    if models_dir != meta.get("models_dir"):
        meta_bytes = (json.dumps({**meta, "models_dir": models_dir}, indent=2) + "\n").encode("utf-8")
    info = {
        "format": CARRY_FORMAT,
        "step": step,
        "checkpoint": ckpt.name,
        "state_sha256": meta["state_sha256"],
        "source": _portable(str(run_dir)) or run_dir.name,
        "models_dir": models_dir,  # informative, as in the checkpoint (None when it was absolute)
    }
    with atomic_directory(out, overwrite=True) as tmp:
        os.chmod(tmp, 0o777 & ~_umask())  # mkdtemp makes it 0700; make it an ordinary folder
        _write(tmp / "config.json", cfg_bytes)
        _write(tmp / "checkpoints" / ckpt.name / "state.npz", state)
        _write(tmp / "checkpoints" / ckpt.name / "meta.json", meta_bytes)
        _write(tmp / "metrics.jsonl", metrics.encode("utf-8"))
        if shares:
            _write(tmp / VAL_SHARES, shares.encode("utf-8"))
        if amendments:
            _write(tmp / AMENDMENTS_FILE, (json.dumps(amendments, indent=2) + "\n").encode("utf-8"))
        _write(tmp / _MARKER, (json.dumps(info, indent=2) + "\n").encode("utf-8"))
    size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    return Carried(out, step, size)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="sc6d carry", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run", required=True, type=Path, help="training run directory (config, checkpoints)")
    p.add_argument("--out", required=True, type=Path,
                   help="state folder to write (replaced when it is an earlier carry of the same run)")
    return p


def main(argv: list[str]) -> int:
    args = build_parser().parse_args(argv)
    res = carry(args.run, args.out)
    print(f"sc6d carry: {args.run} step {res.step} -> {res.out} ({res.size_bytes / 1e6:.2f} MB)")
    models = _read_json(res.out / _MARKER, "").get("models_dir") or "MODELS"
    print(f"next leg: sc6d train --models {models} --out {res.out} --resume")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main(sys.argv[1:]))
