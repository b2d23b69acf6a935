"""Checkpoint files, readable without the training package.

A checkpoint is a directory ``RUN_DIR/checkpoints/ckpt_00001000/{state.npz, meta.json}``.
``state.npz`` holds the flattened training state with path keys (``params/...``,
``opt_state/...``, ``rng_key``; with a moving average of the parameters also ``ema/...`` and
``ema_start``, the step where the average began); ``meta.json`` holds the step, the config, a SHA-256 of the
npz and informative fields.  Each checkpoint directory is written under a hidden temporary name
and renamed when complete (``sc6d_jax._io.atomic_directory``), so a process killed at any moment
leaves either the complete checkpoint or none; old checkpoints are renamed to a hidden name
before they are removed.  Loading checks the hash, the keys, the shapes and the dtypes against
a template and raises ``ValueError`` naming the file on any mismatch, touching nothing.

This module is pure IO (numpy, jax pytrees, json); the training loop
(:mod:`sc6d_jax.train`), inference (:mod:`sc6d_jax.inference`), shipped models
(:mod:`sc6d_jax.pretrained`) and ``sc6d carry`` use it.  Only :func:`load_checkpoint`, which
rebuilds the config and the model's parameter structure, imports ``sc6d_jax.model`` and the
config class (lazily).
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import re
import shutil
import zipfile
from pathlib import Path
from typing import Any

import jax
import numpy as np

from sc6d_jax._io import atomic_directory

__all__ = [
    "CHECKPOINT_FORMAT",
    "checkpoint_dirs",
    "find_checkpoint",
    "flatten_with_paths",
    "load_checkpoint",
    "read_checkpoint",
    "read_ema",
    "read_meta",
    "read_metrics_upto",
    "save_checkpoint",
    "unflatten_like",
    "verify_state",
]

CHECKPOINT_FORMAT = "sc6d-jax-checkpoint/1"
_NAME = re.compile(r"^ckpt_(\d{8,})$")
_STATE = "state.npz"
_META = "meta.json"


def _key_str(k: Any) -> str:
    for attr in ("key", "name", "idx"):
        if hasattr(k, attr):
            return str(getattr(k, attr))
    return str(k)


def flatten_with_paths(tree: Any, prefix: str) -> dict[str, np.ndarray]:
    """Flatten a pytree to ``{"prefix/a/b/0": host array}`` (dict keys, attribute names, indices)."""
    out: dict[str, np.ndarray] = {}
    leaves, _ = jax.tree_util.tree_flatten_with_path(tree)
    for path, leaf in leaves:
        name = "/".join([prefix, *(_key_str(k) for k in path)])
        if name in out:
            raise ValueError(f"two leaves share the checkpoint key {name!r}")
        out[name] = _host(leaf)
    return out


def _host(x: Any) -> np.ndarray:
    """A host copy of an array (for multi-process replicated arrays: the local copy)."""
    if isinstance(x, jax.Array) and not x.is_fully_addressable:
        x = x.addressable_data(0)
    return np.asarray(jax.device_get(x))


def unflatten_like(template: Any, arrays: dict[str, np.ndarray], prefix: str, source: str) -> Any:
    """Rebuild ``template``'s structure from ``arrays`` (as written by :func:`flatten_with_paths`).

    Raises ValueError naming ``source`` when a key is missing or a shape or dtype differs.
    """
    leaves, treedef = jax.tree_util.tree_flatten_with_path(template)
    new = []
    for path, leaf in leaves:
        name = "/".join([prefix, *(_key_str(k) for k in path)])
        if name not in arrays:
            raise ValueError(f"checkpoint {source} is incompatible: it has no entry {name!r}")
        a = arrays[name]
        shape = tuple(leaf.shape) if hasattr(leaf, "shape") else np.shape(leaf)
        dtype = np.dtype(leaf.dtype) if hasattr(leaf, "dtype") else np.asarray(leaf).dtype
        if a.shape != shape or a.dtype != dtype:
            raise ValueError(
                f"checkpoint {source} is incompatible: {name!r} is {a.dtype}{list(a.shape)}, "
                f"the model expects {dtype}{list(shape)}"
            )
        new.append(a)
    expected = {"/".join([prefix, *(_key_str(k) for k in p)]) for p, _ in leaves}
    extra = sorted(k for k in arrays if k.startswith(prefix + "/") and k not in expected)
    if extra:
        raise ValueError(f"checkpoint {source} is incompatible: unexpected entries {extra[:5]}")
    return jax.tree_util.tree_unflatten(treedef, new)


def checkpoint_dirs(run_dir: str | os.PathLike) -> list[tuple[int, Path]]:
    """Complete checkpoints of a run, oldest first, as ``(step, directory)``."""
    root = Path(run_dir) / "checkpoints"
    if not root.is_dir():
        return []
    found = []
    for p in root.iterdir():
        m = _NAME.match(p.name)
        if m and p.is_dir():
            found.append((int(m.group(1)), p))
    return sorted(found)


def _remove_stale(root: Path) -> None:
    """Remove hidden leftovers (``.ckpt_*``) of writes or deletions interrupted by a kill."""
    if root.is_dir():
        for p in root.iterdir():
            if p.name.startswith(".ckpt_") and p.is_dir():
                shutil.rmtree(p, ignore_errors=True)


def save_checkpoint(
    run_dir: str | os.PathLike,
    step: int,
    params: Any,
    opt_state: Any,
    rng_key: Any,
    config: dict[str, Any],
    keep: int = 3,
    extra_meta: dict[str, Any] | None = None,
    ema: tuple[Any, int] | None = None,
) -> Path:
    """Write checkpoint ``step`` atomically and keep only the ``keep`` newest ones.

    Args:
        run_dir: the run directory (checkpoints go to ``run_dir/checkpoints``).
        step: number of completed optimiser steps.
        params, opt_state: pytrees of arrays (device or host).
        rng_key: the run's base PRNG key (raw uint32 key data).
        config: ``TrainConfig.to_dict()``.
        keep: number of newest checkpoints to keep (>= 1).
        extra_meta: informative JSON-able fields stored in meta.json.
        ema: ``(average parameters, step where the average began)``, or None.

    Returns:
        The checkpoint directory.
    """
    if keep < 1:
        raise ValueError(f"keep must be >= 1, got {keep}")
    root = Path(run_dir) / "checkpoints"
    root.mkdir(parents=True, exist_ok=True)
    _remove_stale(root)
    arrays = {**flatten_with_paths(params, "params"), **flatten_with_paths(opt_state, "opt_state")}
    arrays["rng_key"] = _host(rng_key)
    if ema is not None:
        arrays.update(flatten_with_paths(ema[0], "ema"))
        arrays["ema_start"] = np.asarray(int(ema[1]), np.int64)
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    data = buf.getvalue()
    meta = {
        "format": CHECKPOINT_FORMAT,
        "step": int(step),
        "state_sha256": hashlib.sha256(data).hexdigest(),
        "config": config,
        **(extra_meta or {}),
    }
    final = root / f"ckpt_{int(step):08d}"
    with atomic_directory(final, overwrite=True) as tmp:
        with open(tmp / _STATE, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        with open(tmp / _META, "w", encoding="utf-8") as f:
            f.write(json.dumps(meta, indent=2) + "\n")
            f.flush()
            os.fsync(f.fileno())
    for _, old in checkpoint_dirs(run_dir)[:-keep]:
        hidden = old.with_name(f".{old.name}.old")
        os.replace(old, hidden)
        shutil.rmtree(hidden, ignore_errors=True)
    return final


def read_meta(ckpt_dir: str | os.PathLike) -> dict[str, Any]:
    """The ``meta.json`` of a checkpoint directory (ValueError naming it when unreadable)."""
    path = Path(ckpt_dir) / _META
    try:
        meta = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError as exc:
        raise ValueError(f"checkpoint {ckpt_dir} is corrupt: {_META} is missing") from exc
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"checkpoint {path} is corrupt: {exc}") from exc
    if not isinstance(meta, dict) or meta.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"checkpoint {path} is not a {CHECKPOINT_FORMAT} checkpoint")
    for k in ("step", "state_sha256", "config"):
        if k not in meta:
            raise ValueError(f"checkpoint {path} is corrupt: no {k!r} in the metadata")
    return meta


def verify_state(ckpt_dir: str | os.PathLike) -> tuple[dict[str, Any], bytes]:
    """``(meta, state.npz bytes)`` of a checkpoint whose metadata is readable, whose step matches
    its directory name (when it is named ``ckpt_XXXXXXXX``) and whose ``state.npz`` matches the
    SHA-256 in ``meta.json``; ValueError naming the file otherwise."""
    ckpt_dir = Path(ckpt_dir)
    meta = read_meta(ckpt_dir)
    m = _NAME.match(ckpt_dir.name)
    if m and int(m.group(1)) != meta["step"]:
        raise ValueError(f"checkpoint {ckpt_dir} is corrupt: its metadata says step {meta['step']}")
    state = ckpt_dir / _STATE
    try:
        data = state.read_bytes()
    except FileNotFoundError as exc:
        raise ValueError(f"checkpoint {ckpt_dir} is corrupt: {_STATE} is missing") from exc
    if hashlib.sha256(data).hexdigest() != meta["state_sha256"]:
        raise ValueError(f"checkpoint {state} is corrupt: its SHA-256 does not match {_META}")
    return meta, data


def read_checkpoint(
    ckpt_dir: str | os.PathLike, params_template: Any, opt_state_template: Any | None
) -> tuple[Any, Any, np.ndarray, dict[str, Any]]:
    """Load ``(params, opt_state, rng_key, meta)`` as host arrays shaped like the templates.

    ``opt_state_template=None`` skips the optimiser state (returns None for it).  The templates
    may hold ``jax.ShapeDtypeStruct`` leaves (from ``jax.eval_shape``).
    """
    ckpt_dir = Path(ckpt_dir)
    meta, arrays = _arrays(ckpt_dir)
    state = ckpt_dir / _STATE
    params = unflatten_like(params_template, arrays, "params", str(state))
    opt_state = None
    if opt_state_template is not None:
        opt_state = unflatten_like(opt_state_template, arrays, "opt_state", str(state))
    if "rng_key" not in arrays:
        raise ValueError(f"checkpoint {state} is incompatible: it has no 'rng_key'")
    return params, opt_state, arrays["rng_key"], meta


def _arrays(ckpt_dir: Path) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """``(meta, the arrays of state.npz)`` of a verified checkpoint (ValueError naming it)."""
    meta, data = verify_state(ckpt_dir)
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            return meta, {k: z[k] for k in z.files}
    except (zipfile.BadZipFile, ValueError, OSError) as exc:
        raise ValueError(f"checkpoint {ckpt_dir / _STATE} is corrupt: {exc}") from exc


def _ema_from(arrays: dict[str, np.ndarray], params_template: Any, source: str) -> tuple[Any, int] | None:
    if "ema_start" not in arrays:
        return None
    return unflatten_like(params_template, arrays, "ema", source), int(arrays["ema_start"])


def read_ema(ckpt_dir: str | os.PathLike, params_template: Any) -> tuple[Any, int] | None:
    """``(average parameters, step where the average began)`` of a checkpoint that holds a moving
    average of its parameters (``TrainConfig.ema``), else None."""
    ckpt_dir = Path(ckpt_dir)
    return _ema_from(_arrays(ckpt_dir)[1], params_template, str(ckpt_dir / _STATE))


def find_checkpoint(run_dir: str | os.PathLike, step: int | None = None) -> Path:
    """The checkpoint directory of a run's newest (or ``step``) checkpoint.

    ``run_dir`` may also be a checkpoint directory itself (one holding ``meta.json``, e.g. a
    shipped model); it is returned as it is (``step`` is then ignored).  FileNotFoundError when
    the run directory does not exist or has no checkpoints, ValueError when it has no
    checkpoint of ``step``.
    """
    run_dir = Path(run_dir)
    if (run_dir / _META).is_file():
        return run_dir
    if not run_dir.is_dir():
        raise FileNotFoundError(f"run directory {run_dir} does not exist")
    found = dict(checkpoint_dirs(run_dir))
    if not found:
        raise FileNotFoundError(f"run directory {run_dir} has no checkpoints")
    if step is None:
        step = max(found)
    if step not in found:
        raise ValueError(f"run directory {run_dir} has no checkpoint of step {step}; it has {sorted(found)}")
    return found[step]


def load_checkpoint(run_dir: str | os.PathLike, step: int | None = None, raw: bool = False) -> tuple[Any, Any]:
    """Parameters and :class:`~sc6d_jax.train.TrainConfig` of a run's newest (or given) checkpoint.

    Args:
        run_dir: a run directory written by :func:`sc6d_jax.train.train`, or a checkpoint
            directory ``.../checkpoints/ckpt_XXXXXXXX`` itself.
        step: load this step instead of the newest.
        raw: the optimiser's parameters even when the checkpoint holds their moving average
            (``TrainConfig.ema``), which is returned by default: it is what validation scored.

    Returns:
        ``(params, config)``: params as a pytree of numpy arrays.
    """
    # lazy: the config class and the network are needed only to rebuild the parameter structure
    from sc6d_jax.model import init
    from sc6d_jax.train.config import TrainConfig

    ckpt = find_checkpoint(run_dir, step)
    meta = read_meta(ckpt)
    cfg = TrainConfig.from_dict(meta["config"])
    template = jax.eval_shape(lambda p: p, init(jax.random.PRNGKey(0), cfg.model))  # eager: init may use numpy
    if not raw:
        ema = read_ema(ckpt, template)
        if ema is not None:
            return ema[0], cfg
    params, _, _, _ = read_checkpoint(ckpt, template, None)
    return params, cfg


def read_metrics_upto(path: Path, upto: int) -> list[str]:
    """Lines of a run's ``metrics.jsonl`` with an integer step <= ``upto``, without newlines
    (what a resume from the checkpoint of step ``upto`` keeps; a torn line from a kill is dropped)."""
    path = Path(path)
    if not path.is_file():
        return []
    keep = []
    for line in path.read_text(encoding="utf-8").splitlines():
        try:
            rec = json.loads(line)
        except json.JSONDecodeError:
            continue
        if isinstance(rec, dict) and isinstance(rec.get("step"), int) and rec["step"] <= upto:
            keep.append(line)
    return keep
