"""The training program: :func:`train` runs AdamW on crops streamed from the renderer.

Read top to bottom: :func:`train` opens the crop stream at the batch index of the step it
starts from, resolves the data-dependent config fields, checks the run directory, initialises
(or restores) the state, then loops over one jit-compiled :func:`make_train_step` per batch,
logging to ``metrics.jsonl`` and a tqdm bar and writing atomic checkpoints.

Determinism.  Batch ``b`` of the stream depends only on ``(seed, b)``; the PRNG key of step
``b`` is ``fold_in(base_key, b)``.  A run therefore is a pure function of its config, and a run
killed at any moment and resumed from its last checkpoint (``resume=True``) ends with the same
parameters, bit for bit, as an uninterrupted one on the same machine and device count.

Parallelism.  The batch is sharded over a one-axis device mesh (``'data'``) spanning every
device of every process; parameters and optimiser state are replicated; XLA inserts the
gradient all-reduce.  With several processes (:func:`initialize_distributed`, i.e. the
``--coordinator/--num-processes/--process-id`` options of ``sc6d train``), process ``p`` renders
only its ``batch_size / num_processes`` rows, from a stream seeded by ``(seed, p)``; results then
depend on the process count (not on the number of devices per process).  Process 0 writes
config, metrics and checkpoints; the run directory must be on a filesystem all processes see.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import sys
import time
from pathlib import Path
from typing import Any, Callable, Iterator, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import NamedSharding, PartitionSpec

from sc6d_jax._io import atomic_write_text
from sc6d_jax.checkpoint import (
    checkpoint_dirs,
    read_metrics_upto,
    read_checkpoint,
    read_ema,
    read_meta,
    save_checkpoint,
)
from sc6d_jax.train.config import TrainConfig, config_differences

__all__ = [
    "DataFns",
    "ModelFns",
    "NonFiniteLossError",
    "initialize_distributed",
    "make_optimizer",
    "make_train_step",
    "read_amendments",
    "train",
]

_MESH_EXTS = (".ply", ".obj", ".stl", ".off", ".glb")


class NonFiniteLossError(FloatingPointError):
    """The loss or the gradient became NaN or infinite; the run stopped before saving it."""

    def __init__(self, step: int, metrics: dict[str, float], last_checkpoint: Path | None):
        self.step = step
        self.metrics = metrics
        self.last_checkpoint = last_checkpoint
        kept = f"last good checkpoint kept: {last_checkpoint}" if last_checkpoint else "no checkpoint was written"
        terms = ", ".join(f"{k}={v:.4g}" for k, v in metrics.items())
        super().__init__(f"loss or gradient is not finite at step {step} ({terms}); run stopped; {kept}")


class ModelFns(NamedTuple):
    """The model functions the loop calls (defaults: :mod:`sc6d_jax.model`).

    ``init(key, model_cfg) -> params``;
    ``loss_fn(params, model_cfg, loss_cfg, batch, key, z_range) -> (loss, aux dict)``;
    ``load_weights(params, model_cfg, path) -> params`` (for ``init_weights``; may be None).
    """

    init: Callable[[jax.Array, Any], Any]
    loss_fn: Callable[..., tuple[jax.Array, dict[str, jax.Array]]]
    load_weights: Callable[[Any, Any, Path], Any] | None = None


class DataFns(NamedTuple):
    """The crop-stream functions the loop calls (defaults: :mod:`sc6d_jax.data`).

    ``stream_config(models_dir=, crop_size=, batch_size=, seed=, workers=, obj_ids=, augment=)``;
    ``stream(stream_cfg, start_batch)`` -> iterator of dict batches with ``.obj_ids`` and ``.close()``;
    ``z_range(stream_cfg) -> (d_lo, d_hi)``.
    """

    stream_config: Callable[..., Any]
    stream: Callable[[Any, int], Any]
    z_range: Callable[[Any], tuple[float, float]]


def _default_model_fns() -> ModelFns:
    from sc6d_jax import model

    def load_weights(params: Any, model_cfg: Any, path: Path) -> Any:
        del model_cfg
        return model.load_resnet_weights(params, path)

    return ModelFns(model.init, model.loss_fn, load_weights)


def _default_data_fns() -> DataFns:
    from sc6d_jax import data

    def stream_config(**kw: Any) -> Any:
        models_dir = Path(kw["models_dir"])
        meshes = [p for p in models_dir.iterdir() if p.suffix.lower() in _MESH_EXTS]
        if not meshes:
            raise ValueError(f"models folder {models_dir} holds no models ({'/'.join(_MESH_EXTS)} files)")
        if kw.get("workers") is None:
            kw.pop("workers", None)
        kw["models_dir"] = str(models_dir)
        return data.StreamConfig(**kw)

    return DataFns(stream_config, data.CropStream, data.delta_z_range)


# -- building blocks ------------------------------------------------------------------------------
def make_optimizer(cfg: TrainConfig) -> tuple[optax.GradientTransformation, optax.Schedule]:
    """AdamW with cosine decay ``lr -> lr_end`` over ``cfg.steps`` (after optional linear warm-up)."""
    o = cfg.optim
    warmup = cfg.warmup_steps
    if warmup >= cfg.steps:
        raise ValueError(f"optim.warmup_steps ({warmup}) must be smaller than steps ({cfg.steps})")
    if warmup > 0:
        sched = optax.warmup_cosine_decay_schedule(0.0, o.lr, warmup, cfg.steps, o.lr_end)
    else:
        sched = optax.cosine_decay_schedule(o.lr, cfg.steps, alpha=o.lr_end / o.lr)
    tx = optax.adamw(sched, b1=o.b1, b2=o.b2, eps=o.eps, weight_decay=o.weight_decay)
    if o.grad_clip is not None:
        tx = optax.chain(optax.clip_by_global_norm(o.grad_clip), tx)
    return tx, sched


def make_train_step(
    loss_fn: Callable[..., Any],
    cfg: TrainConfig,
    tx: optax.GradientTransformation,
    z_range: tuple[float, float],
    mesh: jax.sharding.Mesh | None = None,
) -> Callable[[Any, Any, dict[str, jax.Array], jax.Array, jax.Array], tuple[Any, Any, dict[str, jax.Array]]]:
    """One jit-compiled optimiser step ``(params, opt_state, batch, step, base_key) -> (params, opt_state, metrics)``.

    The key of the step is ``fold_in(base_key, step)``.  ``params`` and ``opt_state`` are donated.
    ``metrics`` holds the loss, the scalar entries of the loss's aux dict, the gradient norm and
    ``finite`` (loss and gradient norm finite).  With a mesh the outputs are replicated on it.
    """
    mcfg, lcfg = cfg.model, cfg.loss
    view_steps = int(round(getattr(lcfg, "view_until", 1.0) * cfg.steps))

    def step_fn(params: Any, opt_state: Any, batch: dict[str, jax.Array], step: jax.Array, base_key: jax.Array):
        key = jax.random.fold_in(base_key, step)
        if getattr(lcfg, "w_view", 0) > 0 and view_steps < cfg.steps:  # the view loss for the first steps only
            batch = {**batch, "view_weight": jnp.where(step < view_steps, 1.0, 0.0)}
        (loss, aux), grads = jax.value_and_grad(
            lambda p: loss_fn(p, mcfg, lcfg, batch, key, z_range), has_aux=True
        )(params)
        gnorm = optax.tree.norm(grads)
        updates, opt_state = tx.update(grads, opt_state, params)
        params = optax.apply_updates(params, updates)
        metrics = {"loss": loss.astype(jnp.float32), "grad_norm": gnorm.astype(jnp.float32)}
        for k, v in (aux or {}).items():
            if k not in metrics and hasattr(v, "shape") and jnp.ndim(v) == 0:
                metrics[k] = jnp.asarray(v, jnp.float32)
        metrics["finite"] = jnp.isfinite(loss) & jnp.isfinite(gnorm)
        return params, opt_state, metrics

    kw: dict[str, Any] = {"donate_argnums": (0, 1)}
    if mesh is not None:
        rep = NamedSharding(mesh, PartitionSpec())
        kw["out_shardings"] = (rep, rep, rep)
    return jax.jit(step_fn, **kw)


@functools.lru_cache(maxsize=8)
def _cached_train_step(loss_fn: Callable[..., Any], cfg: TrainConfig, z_range: tuple[float, float], mesh: Any):
    """make_train_step memoised on its (hashable) inputs, so that several runs of one config in
    one process (tests, benchmarks) compile once.  The run-only fields do not matter."""
    tx, _ = make_optimizer(cfg)
    return make_train_step(loss_fn, cfg, tx, z_range, mesh)


def initialize_distributed(coordinator_address: str, num_processes: int, process_id: int) -> None:
    """Join a multi-process (multi-host) run through ``jax.distributed.initialize``.

    Must be called before any other JAX call in the process.  Every process runs the same
    ``train`` call; the batch is split over all processes' devices.
    """
    if not coordinator_address or ":" not in coordinator_address:
        raise ValueError(f"coordinator address must be HOST:PORT, got {coordinator_address!r}")
    if not isinstance(num_processes, int) or num_processes < 1:
        raise ValueError(f"num_processes must be a positive integer, got {num_processes!r}")
    if not isinstance(process_id, int) or not 0 <= process_id < num_processes:
        raise ValueError(f"process_id must be in [0, {num_processes}), got {process_id!r}")
    jax.distributed.initialize(coordinator_address, num_processes=num_processes, process_id=process_id)


def _process_seed(seed: int, index: int, count: int) -> int:
    from sc6d_jax.data import derive_seed

    return seed if count == 1 else derive_seed(seed, index)


def _replicate(tree: Any, sharding: NamedSharding) -> Any:
    def put(x: Any) -> jax.Array:
        x = np.asarray(x)
        return jax.make_array_from_callback(x.shape, sharding, lambda idx: x[idx])

    return jax.tree.map(put, tree)


def _host_tree(tree: Any) -> Any:
    def get(x: Any) -> np.ndarray:
        if isinstance(x, jax.Array) and not x.is_fully_addressable:
            x = x.addressable_data(0)
        return np.asarray(jax.device_get(x))

    return jax.tree.map(get, tree)


def _global_batch(batch: dict[str, Any], sharding: NamedSharding, local_bs: int, global_bs: int) -> dict[str, jax.Array]:
    out = {}
    for k, v in batch.items():
        if not isinstance(v, np.ndarray | jax.Array) or v.ndim == 0 or v.shape[0] != local_bs:
            continue
        v = np.asarray(v)
        out[k] = jax.make_array_from_process_local_data(sharding, v, (global_bs, *v.shape[1:]))
    return out


# -- the program ----------------------------------------------------------------------------------
def stream_fields(cfg: TrainConfig, models_dir: str | os.PathLike, workers: int | None) -> dict[str, Any]:
    """The crop stream's fields of a training config, all but the batch size and the seed (what
    :func:`train` passes to ``DataFns.stream_config``; tools that render a config's batches
    outside a run use the same)."""
    from sc6d_jax.data._stream import PASSED_WHEN_SET

    common: dict[str, Any] = dict(
        models_dir=Path(models_dir), crop_size=cfg.model.crop_size, workers=workers,
        obj_ids=cfg.stream.obj_ids, augment=cfg.stream.augment,
    )
    common.update(cfg.crop_fields())  # None = the stream's default
    if cfg.stream.colour_p is not None:
        common["colour_p"] = cfg.stream.colour_p
    if cfg.curriculum_steps:
        common["curriculum"] = cfg.curriculum_steps
    if getattr(cfg.loss, "w_dense", 0) > 0 or getattr(cfg.loss, "w_dense_xyz", 0) > 0:
        common["dense"] = True
    if getattr(cfg.model, "dense_xyz", False) and common.get("dense"):
        common["dense_xyz"] = True
    if getattr(cfg.loss, "w_view", 0) > 0:
        common["view"] = cfg.model.view_head
    if getattr(cfg.model, "pe_turns", False):
        common["pe_turns"] = True
    for name in PASSED_WHEN_SET:  # stream options, when on
        if getattr(cfg.stream, name):
            common[name] = getattr(cfg.stream, name)
    return common


def resolve_z_range(cfg: TrainConfig, stream_cfg: Any, z_range_fn: Callable[..., Any]) -> tuple[float, float]:
    """The depth-code range of ``cfg``'s stream ``stream_cfg`` by ``z_range_fn`` (e.g.
    ``sc6d_jax.data.delta_z_range``), normalised by the reference focal length where the loss
    normalises the code so (``loss.z_norm="focal"``)."""
    if getattr(cfg.loss, "z_norm", "none") == "focal":
        from sc6d_jax.model import F_REF

        return tuple(float(x) for x in z_range_fn(stream_cfg, focal_ref=F_REF))
    return tuple(float(x) for x in z_range_fn(stream_cfg))


def train(
    cfg: TrainConfig,
    models_dir: str | os.PathLike,
    run_dir: str | os.PathLike,
    resume: bool = False,
    *,
    workers: int | None = None,
    init_weights: str | os.PathLike | None = None,
    progress: bool = True,
    verbose: bool = True,
    model_fns: ModelFns | None = None,
    data_fns: DataFns | None = None,
    amend: bool = False,
) -> Any:
    """Train a model on crops streamed from the renderer; return the final parameters (numpy).

    Args:
        cfg: the training config (e.g. ``preset("cpu")``); data-dependent fields are resolved.
        models_dir: folder of object models (BOP ``models/``) the crop stream renders.
        run_dir: the run directory: ``config.json``, ``metrics.jsonl``, ``checkpoints/``.
        resume: continue from the newest checkpoint of ``run_dir`` (start afresh when it has
            none).  Without it, a run directory holding checkpoints is refused.
        workers: renderer worker processes of the stream (does not change the data).
        init_weights: local ResNet weights file for the backbone (fresh runs only).
        progress: show a tqdm bar on stderr.
        verbose: print the config and checkpoint notes to stdout.
        model_fns, data_fns: replacements of :mod:`sc6d_jax.model` / :mod:`sc6d_jax.data`.
        amend: with ``resume``, continue the run from its newest checkpoint under ``cfg`` even
            where ``cfg`` differs from the run's config in the crop stream or the losses (what
            the rest of the run trains on; the parameters, optimiser state, schedule and step
            carry on). The change and its step are recorded in ``RUN_DIR/amendments.json``
            and the run's config becomes ``cfg``. Changes of the model, the optimiser, the
            step count, the seed or the objects are refused: they would not continue the run.

    Raises:
        ValueError: bad input (empty models folder, run directory of another config, corrupt or
            incompatible checkpoint) -- nothing on disk is changed.
        NonFiniteLossError: the loss became NaN/inf; the last good checkpoint is kept.
    """
    model_fns = model_fns or _default_model_fns()
    data_fns = data_fns or _default_data_fns()
    models_dir, run_dir = Path(models_dir), Path(run_dir)
    if not models_dir.is_dir():
        raise FileNotFoundError(f"models folder {models_dir} does not exist")
    if run_dir.exists() and not run_dir.is_dir():
        raise ValueError(f"run directory {run_dir} is not a directory")
    if init_weights is not None:
        init_weights = Path(init_weights)
        if not init_weights.is_file():
            raise FileNotFoundError(f"initial weights file {init_weights} does not exist")
        if model_fns.load_weights is None:
            raise ValueError("this model has no weight loader; init_weights is not supported")

    # -- where do we start? -----------------------------------------------------------------
    ckpts = checkpoint_dirs(run_dir)
    if ckpts and not resume:
        raise ValueError(
            f"run directory {run_dir} already holds checkpoints (newest: step {ckpts[-1][0]}); "
            "resume it (--resume) or choose another directory"
        )
    if cfg.init_from is not None and not (resume and ckpts):
        from sc6d_jax import pretrained

        pretrained.check_run(cfg.init_from)  # FileNotFoundError naming it, before anything is written
    latest: Path | None = None
    start = 0
    if resume and ckpts:
        step_in_name, latest = ckpts[-1]
        meta = read_meta(latest)
        if meta["step"] != step_in_name:
            raise ValueError(f"checkpoint {latest} is corrupt: its metadata says step {meta['step']}")
        start = int(meta["step"])

    # -- devices, stream, resolved config --------------------------------------------------
    pidx, pcount = jax.process_index(), jax.process_count()
    ndev = jax.device_count()
    gbs = cfg.stream.batch_size
    if gbs % ndev:
        raise ValueError(f"batch size {gbs} is not divisible by the number of devices ({ndev})")
    local_bs = gbs // pcount
    common = stream_fields(cfg, models_dir, workers)
    scfg = data_fns.stream_config(batch_size=local_bs, seed=_process_seed(cfg.seed, pidx, pcount), **common)
    stream = data_fns.stream(scfg, start)
    try:
        obj_ids = tuple(int(i) for i in stream.obj_ids)
        if cfg.z_range is None:
            zcfg = scfg if pcount == 1 else data_fns.stream_config(batch_size=gbs, seed=cfg.seed, **common)
            z_range = resolve_z_range(cfg, zcfg, data_fns.z_range)
        else:
            z_range = cfg.z_range
        cfg = cfg.replace(
            model=dataclasses.replace(cfg.model, n_objects=len(obj_ids)),
            stream=dataclasses.replace(cfg.stream, obj_ids=obj_ids),
            z_range=z_range,
        )
        cfg_dict = cfg.to_dict()
        cfg_path = run_dir / "config.json"
        amendments = read_amendments(run_dir)
        if amend:
            if latest is None:
                raise ValueError(f"amend: run directory {run_dir} has no checkpoint to continue from")
            change = config_differences(read_meta(latest)["config"], cfg_dict)
            bad = [d for d in change if not d.startswith(AMENDABLE) or d.startswith(("stream.obj_ids ", "stream.batch_size "))]
            if bad:
                raise ValueError(f"amend: only the stream (not its objects or batch size) and the losses can change "
                                 f"in the middle of a run; refused: {'; '.join(bad)}")
            amendments = [a for a in amendments if a["step"] != start]
            if change:
                amendments.append({"step": start, "changes": change})
            if verbose and pidx == 0:
                print(f"sc6d train: amending {run_dir} from step {start}: {'; '.join(change) or 'no change'}", flush=True)
        elif cfg_path.is_file():
            try:
                saved = json.loads(cfg_path.read_text(encoding="utf-8"))
            except (json.JSONDecodeError, UnicodeDecodeError) as exc:
                raise ValueError(f"{cfg_path} is not valid JSON ({exc}); refusing to overwrite it") from exc
            diff = config_differences(saved, cfg_dict)
            if diff:
                raise ValueError(
                    f"run directory {run_dir} belongs to another config; differing fields: {'; '.join(diff)}"
                )
        if latest is not None and not amend and not any(a["step"] == start for a in amendments):
            diff = config_differences(read_meta(latest)["config"], cfg_dict)
            if diff:
                raise ValueError(f"checkpoint {latest} was written for another config; differing: {'; '.join(diff)}")

        # -- state ------------------------------------------------------------------------
        tx, sched = make_optimizer(cfg)
        init_key, base_key = jax.random.split(jax.random.PRNGKey(cfg.seed))
        # init is called eagerly (the model may draw its parameters with numpy, which cannot be
        # traced); on resume its output is only the template of the checkpoint's structure.
        params = model_fns.init(init_key, cfg.model)
        init_source = None  # the checkpoint init_from read (kept in every checkpoint's meta.json)
        if latest is not None:
            init_source = read_meta(latest).get("init_from")
            p_t = jax.eval_shape(lambda p: p, params)
            o_t = jax.eval_shape(tx.init, p_t)
            params, opt_state, key_data, _ = read_checkpoint(latest, p_t, o_t)
            base_key = np.asarray(key_data)
            ema = read_ema(latest, p_t) if cfg.ema else None
            if verbose and pidx == 0:
                print(f"sc6d train: resuming {run_dir} from step {start} ({latest.name})", flush=True)
        else:
            if init_weights is not None:
                params = model_fns.load_weights(params, cfg.model, init_weights)
            if cfg.init_from is not None:
                from sc6d_jax.train.transfer import transfer_params

                moved = transfer_params(params, cfg.model, cfg.init_from, model_fns.init, obj_ids=cfg.stream.obj_ids)
                params = moved.params
                init_source = moved.source
                if verbose and pidx == 0:
                    print(f"sc6d train: init_from: {moved.summary()}", flush=True)
            params = _host_tree(params)
            opt_state = _host_tree(tx.init(params))
            ema = None
        if cfg.ema and ema is None:  # the average starts here (a fresh run, or switched on at a resume)
            ema = (jax.tree.map(np.array, _host_tree(params)), start)
        if verbose and pidx == 0:
            print(f"sc6d train: config\n{cfg.to_json()}", end="", flush=True)

        devices = np.asarray(jax.devices())
        mesh = jax.sharding.Mesh(devices, ("data",))
        rep = NamedSharding(mesh, PartitionSpec())
        data_sh = NamedSharding(mesh, PartitionSpec("data"))
        params = _replicate(params, rep)
        opt_state = _replicate(opt_state, rep)
        if ema is not None:
            ema = (_replicate(ema[0], rep), ema[1])
        base_key = _replicate(np.asarray(base_key), rep)
        step_fn = _cached_train_step(model_fns.loss_fn, cfg.replace(checkpoint_every=1, keep_checkpoints=1, log_every=1), z_range, mesh)

        metrics_path = run_dir / "metrics.jsonl"
        extra_meta = {
            "models_dir": str(models_dir),
            "init_weights": str(init_weights) if init_weights else None,
            "init_from": init_source,
            "process_count": pcount,
            "device_count": ndev,
            "jax_version": jax.__version__,
        }
        if pidx == 0:
            run_dir.mkdir(parents=True, exist_ok=True)
            atomic_write_text(cfg_path, cfg.to_json())
            kept_amends = [a for a in amendments if a["step"] <= start]  # later ones went with their checkpoints
            if kept_amends or (run_dir / AMENDMENTS_FILE).is_file():
                atomic_write_text(run_dir / AMENDMENTS_FILE, json.dumps(kept_amends, indent=2) + "\n")
            kept = read_metrics_upto(metrics_path, start)
            atomic_write_text(metrics_path, "".join(line + "\n" for line in kept))
            time_offset = _time_offset(kept)
        else:
            time_offset = (0.0, 0.0)

        if start >= cfg.steps:
            if verbose and pidx == 0:
                print(f"sc6d train: {run_dir} is already complete ({start} steps)", flush=True)
            return _host_tree(ema[0] if ema is not None else params)
        validator = None
        if cfg.val_crops and pidx == 0 and data_fns.stream is _default_data_fns().stream:
            from sc6d_jax.train.validate import Validator

            validator = Validator(cfg, models_dir, n=cfg.val_crops)
        run = _Run(
            cfg=cfg, stream=stream, step_fn=step_fn, sched=sched, run_dir=run_dir, metrics_path=metrics_path,
            data_sh=data_sh, rep=rep, local_bs=local_bs, extra_meta=extra_meta,
            show_bar=progress and pidx == 0, writer=pidx == 0, validator=validator, time_offset=time_offset,
        )
        return _loop(run, TrainState(params, opt_state, base_key, ema), start, latest)
    finally:
        close = getattr(stream, "close", None)
        if close is not None:
            close()


AMENDMENTS_FILE = "amendments.json"
#: config fields (dotted prefixes) that ``train(..., amend=True)`` may change in the middle of a run
AMENDABLE = ("stream.", "loss.")


def read_amendments(run_dir: str | os.PathLike) -> list[dict[str, Any]]:
    """The run's recorded amendments (``[{"step": N, "changes": [...]}]``, oldest first; [] without)."""
    path = Path(run_dir) / AMENDMENTS_FILE
    if not path.is_file():
        return []
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path} is not valid JSON ({exc})") from exc
    if not isinstance(data, list) or not all(isinstance(a, dict) and isinstance(a.get("step"), int) for a in data):
        raise ValueError(f"{path} is not a list of {{step, changes}} records")
    return sorted(data, key=lambda a: a["step"])


@dataclasses.dataclass(frozen=True)
class _Run:
    """What the step loop needs besides the training state: the resolved config, the stream and
    the compiled step, where to write, the shardings, and who shows and writes what."""

    cfg: TrainConfig
    stream: Iterator[dict[str, Any]]
    step_fn: Callable[..., Any]
    sched: optax.Schedule
    run_dir: Path
    metrics_path: Path
    data_sh: NamedSharding
    rep: NamedSharding
    local_bs: int
    extra_meta: dict[str, Any]
    show_bar: bool
    writer: bool
    validator: Callable[[Any], dict[str, float]] | None = None
    #: (elapsed_s, train_s) of the legs before this one, so that a resumed run's clock goes on
    time_offset: tuple[float, float] = (0.0, 0.0)


def _time_offset(lines: list[str]) -> tuple[float, float]:
    """(elapsed_s, train_s) of the last record of the kept metrics lines that has them."""
    for line in reversed(lines):
        rec = json.loads(line)
        if "train_s" in rec:
            return float(rec.get("elapsed_s", rec["train_s"])), float(rec["train_s"])
    return 0.0, 0.0


@dataclasses.dataclass
class TrainState:
    """The state a run carries from step to step: parameters, optimiser state, the run's base
    key, and the moving average of the parameters with the step where it began (or None)."""

    params: Any
    opt_state: Any
    base_key: jax.Array
    ema: tuple[Any, int] | None = None


@functools.partial(jax.jit, donate_argnums=0)
def _ema_update(ema: Any, params: Any, decay: jax.Array) -> Any:
    return jax.tree.map(lambda e, p: decay * e + (1.0 - decay) * p, ema, params)


def _ema_decay(cfg: TrainConfig, updates_done: int, start: int = 0) -> np.float32:
    """The average's decay after ``updates_done`` updates: ``min(cfg.ema, (1 + n) / (10 + n))``
    (TensorFlow's ramp, which forgets the random initial parameters) for an average begun at step
    0; ``cfg.ema`` throughout for one switched on later (it begins from trained parameters)."""
    if start > 0:
        return np.float32(cfg.ema)
    return np.float32(min(cfg.ema, (1.0 + updates_done) / (10.0 + updates_done)))


def _loop(run: _Run, state: TrainState, start: int, last_ckpt: Path | None) -> Any:
    """Steps ``start .. cfg.steps`` of a run from the given state; returns the final parameters
    (their moving average when the run keeps one)."""
    params, opt_state, base_key, ema = state.params, state.opt_state, state.base_key, state.ema
    cfg, stream, step_fn, sched = run.cfg, run.stream, run.step_fn, run.sched
    run_dir, metrics_path, data_sh, rep = run.run_dir, run.metrics_path, run.data_sh, run.rep
    local_bs, extra_meta, show_bar, writer, validator = run.local_bs, run.extra_meta, run.show_bar, run.writer, run.validator
    from tqdm.auto import tqdm

    gbs = cfg.stream.batch_size
    cfg_dict = cfg.to_dict()
    bar = tqdm(total=cfg.steps, initial=start, desc="train", unit="step", file=sys.stderr,
               disable=not show_bar, dynamic_ncols=True, smoothing=0.1)
    pending: list[tuple[int, dict[str, jax.Array]]] = []
    window: list[dict[str, float]] = []
    t0 = t_win = time.perf_counter()
    n_win = 0
    val_s = 0.0  # time spent validating, left out of train_s
    off_elapsed, off_train = run.time_offset  # earlier legs of a resumed run
    it = iter(stream)
    mfile = open(metrics_path, "a", encoding="utf-8") if writer else None

    held: list[dict[str, Any]] = []  # the record of a checkpoint step, written with its validation

    def write(rec: dict[str, Any]) -> None:
        if mfile is not None:
            mfile.write(json.dumps(rec) + "\n")
            mfile.flush()

    def drain(hold: int | None = None) -> None:
        """Log the pending steps' metrics; the record of step ``hold`` is kept in ``held``."""
        nonlocal t_win, n_win
        while pending:
            done, m = pending.pop(0)
            host = {k: float(np.asarray(_host_tree(v))) for k, v in m.items()}
            finite = bool(host.pop("finite"))
            window.append(host)
            n_win += 1
            if not finite:
                raise NonFiniteLossError(done, host, last_ckpt)
            if done % cfg.log_every == 0 or done == cfg.steps or done == hold:
                # a checkpoint step that is validated is always logged: its record carries both
                now = time.perf_counter()
                rec: dict[str, Any] = {"step": done}
                for k in window[0]:
                    rec[k] = float(np.mean([w[k] for w in window]))
                rec["lr"] = float(sched(done - 1))
                rec["crops_per_s"] = n_win * gbs / max(now - t_win, 1e-9)
                rec["elapsed_s"] = off_elapsed + now - t0
                rec["train_s"] = off_train + now - t0 - val_s
                window.clear()
                t_win, n_win = now, 0
                if done == hold:
                    held.append(rec)
                else:
                    write(rec)
                post = {k: f"{v:.4g}" for k, v in rec.items() if k not in ("step", "lr", "elapsed_s", "crops_per_s")}
                post["crops/s"] = f"{rec['crops_per_s']:.0f}"
                bar.set_postfix(post, refresh=False)

    try:
        for s in range(start, cfg.steps):
            batch = _global_batch(next(it), data_sh, local_bs, gbs)
            step_arr = jax.make_array_from_callback((), rep, lambda idx, s=s: np.asarray(s, np.int32))
            params, opt_state, m = step_fn(params, opt_state, batch, step_arr, base_key)
            if ema is not None:
                ema = (_ema_update(ema[0], params, _ema_decay(cfg, s - ema[1], ema[1])), ema[1])
            drain()  # metrics of the previous step, while this one runs
            done = s + 1
            pending.append((done, m))
            bar.update(1)
            if done % cfg.checkpoint_every == 0 or done == cfg.steps:
                validating = validator is not None and writer
                drain(hold=done if validating else None)
                if writer:
                    last_ckpt = save_checkpoint(
                        run_dir, done, params, opt_state, base_key, cfg_dict,
                        keep=cfg.keep_checkpoints, extra_meta=extra_meta, ema=ema,
                    )
                else:
                    jax.block_until_ready(params)
                if validating:
                    # the step's record gets the validation fields (one line per logged step)
                    tv = time.perf_counter()
                    vrec = held.pop()
                    vrec.update(validator(ema[0] if ema is not None else params))
                    shares = getattr(validator, "last_shares", None)
                    if shares is not None:  # each crop's part of val_ar: paired A/Bs on the same crops
                        with open(run_dir / VAL_SHARES, "a", encoding="utf-8") as f:
                            f.write(json.dumps({"step": done, "crops": getattr(validator, "fingerprint", None),
                                            "shares": [round(float(x), 4) for x in shares]}) + "\n")
                    if ema is not None:  # what inference will use, and the raw parameters beside it
                        raw = validator(params)
                        vrec.update({name: raw[k] for name, k in zip(RAW_LOGGED, RAW_KEYS)})
                    val_s += time.perf_counter() - tv
                    vrec["val_s"] = time.perf_counter() - tv
                    write(vrec)
                    bar.set_postfix({"val_rot": f"{vrec['val_rot_median_deg']:.1f}",
                                     "val_dz": f"{100 * vrec['val_depth_rel_median']:.1f}%",
                                     "val_ar": f"{vrec['val_ar']:.3f}"}, refresh=False)
        drain()
    finally:
        bar.close()
        if mfile is not None:
            mfile.close()
    return _host_tree(ema[0] if ema is not None else params)


#: Per validation, each crop's share of ``val_ar`` (``{"step", "crops", "shares"}`` per line, ``crops``
#: the validator's fingerprint; the last line of a step counts after a resume): runs that validate
#: on the same crops compare per crop (``experiments/learning_curve.py``).
VAL_SHARES = "val_shares.jsonl"

#: The validation fields also logged for the raw parameters of a run that keeps a moving average,
#: under ``val_raw_*`` (:data:`RAW_LOGGED`).
RAW_KEYS = ("val_ar", "val_rot_median_deg", "val_depth_rel_median")
RAW_LOGGED = tuple(f"val_raw_{k[4:]}" for k in RAW_KEYS)

