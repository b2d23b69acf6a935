"""Shipped pretrained models, addressed by name wherever a run directory is accepted.

    Estimator.load("builtin")              # the model of the built-in objects
    sc6d predict --run builtin --dataset DIR --out results.csv

A shipped model is a parameters-only checkpoint (``meta.json`` + ``state.npz``, the format of
:mod:`sc6d_jax.checkpoint`) in ``sc6d_jax/assets/pretrained/NAME/``.  Its rotation
library cannot be cached inside the package (which may be read-only), so it goes to the user
cache: ``$SC6D_CACHE`` or ``$XDG_CACHE_HOME/sc6d-jax`` or ``~/.cache/sc6d-jax``, in a folder
named after the model's name and the hash of its weights.

:func:`ship` writes such a checkpoint from a training run (``experiments/ship_model.py``).
"""

from __future__ import annotations

import hashlib
import io
import json
import os
from pathlib import Path

import numpy as np

from sc6d_jax._io import atomic_directory

PRETRAINED_DIR = Path(__file__).parent / "assets" / "pretrained"
# name -> what it is (names listed here may be absent from a checkout: see available())
KNOWN = {
    "builtin": "the 14 built-in objects (sc6d objects), cpu preset",
    "lmo": "the 8 LM-O objects, trained on MuJoCo renders of their models",
}


def available() -> list[str]:
    """Names of the shipped models present in this installation."""
    if not PRETRAINED_DIR.is_dir():
        return []
    return sorted(p.name for p in PRETRAINED_DIR.iterdir() if (p / "meta.json").is_file())


def is_name(run: str | os.PathLike) -> bool:
    """True when ``run`` is a bare model name (no path separator) that is not an existing path."""
    s = os.fspath(run)
    return not Path(s).exists() and os.sep not in s and "/" not in s and s in KNOWN


def cache_root() -> Path:
    env = os.environ.get("SC6D_CACHE")
    if env:
        return Path(env)
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "sc6d-jax"


def resolve(run: str | os.PathLike) -> tuple[Path, Path]:
    """``(checkpoint or run directory, library cache directory)`` of a run path or a shipped name.

    A path is returned as it is, with ``RUN/library`` as its cache.  A name (``builtin``,
    ``lmo``) resolves to the shipped checkpoint; FileNotFoundError names what is shipped when
    the model is not.
    """
    if not is_name(run):
        p = Path(run)
        return p, p / "library"
    name = os.fspath(run)
    ckpt = PRETRAINED_DIR / name
    if not (ckpt / "meta.json").is_file():
        have = ", ".join(available()) or "none"
        raise FileNotFoundError(
            f"no shipped model {name!r} in this installation (shipped: {have}); "
            f"train one with 'sc6d train' and pass its run directory instead"
        )
    digest = json.loads((ckpt / "meta.json").read_text(encoding="utf-8"))["state_sha256"][:12]
    return ckpt, cache_root() / f"{name}-{digest}" / "library"


def check_run(run: str | os.PathLike) -> Path:
    """The checkpoint or run directory of ``run`` (a path or a shipped name); FileNotFoundError
    naming the problem when it is neither a training run nor a shipped model."""
    path, _ = resolve(run)
    if not ((path / "config.json").is_file() or (path / "meta.json").is_file()):
        raise FileNotFoundError(f"{path / 'config.json'}: not a training run directory "
                                f"(nor a shipped model: {', '.join(available()) or 'none shipped'})")
    return path


def ship(run_dir: str | os.PathLike, out_dir: str | os.PathLike, step: int | None = None,
         note: str = "") -> Path:
    """Write the parameters of a run's newest (or ``step``) checkpoint as a shipped model.

    Only the parameters (their moving average when the run keeps one: what validation scored),
    the config and a note are kept (no optimiser state): a few MB.
    Written atomically; an existing ``out_dir`` is replaced.
    """
    from sc6d_jax.checkpoint import (
        CHECKPOINT_FORMAT,
        find_checkpoint,
        flatten_with_paths,
        load_checkpoint,
        read_ema,
        read_meta,
    )

    run_dir, out_dir = Path(run_dir), Path(out_dir)
    ckpt = find_checkpoint(run_dir, step)
    params, _ = load_checkpoint(ckpt)
    src_meta = read_meta(ckpt)
    arrays = flatten_with_paths(params, "params")
    arrays = {k: np.asarray(v, np.float32) if np.asarray(v).dtype == np.float64 else np.asarray(v)
              for k, v in arrays.items()}
    arrays["rng_key"] = np.zeros(2, np.uint32)
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    data = buf.getvalue()
    meta = {
        "format": CHECKPOINT_FORMAT,
        "step": int(src_meta["step"]),
        "state_sha256": hashlib.sha256(data).hexdigest(),
        "config": src_meta["config"],
        "shipped": {"note": note, "params_only": True, "moving_average": read_ema(ckpt, params) is not None},
    }
    with atomic_directory(out_dir, overwrite=True) as tmp:
        (tmp / "state.npz").write_bytes(data)
        (tmp / "meta.json").write_text(json.dumps(meta, indent=2) + "\n", encoding="utf-8")
    return out_dir
