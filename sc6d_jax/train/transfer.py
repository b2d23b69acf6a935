"""Start a run from another trained model: the parameters that do not belong to its objects.

The paper starts its backbone from ImageNet weights; without downloads, this project's
substitute is a model trained on other rendered objects (``TrainConfig.init_from``: a run
directory, a checkpoint directory or a shipped model's name such as ``builtin``). Every
parameter array of the new model whose shape does not depend on the number of objects (the
backbone, the shared decoder, the pose decoder and its heads, the SO(3) encoder's shared
layers) starts from the source's array of the same name and shape; the arrays that belong to
objects (their decoder embeddings, the SO(3) encoder's output layers, any per-object decoder
or head) start as a fresh run's, since the new run's objects are others. The copied and the
fresh arrays are listed, so that what carried over is on record.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from typing import Any

import jax
import numpy as np


@dataclass(frozen=True)
class Transfer:
    """What :func:`transfer_params` did: the new parameters and the names of the arrays.

    Attributes:
        params: the new model's parameters (numpy pytree).
        copied: names of the arrays taken from the source.
        per_object: names of the arrays that belong to objects (kept fresh).
        unmatched: names of the object-independent arrays the source has not in that shape (kept fresh).
        source: the checkpoint directory the parameters came from.
    """

    params: Any
    copied: tuple[str, ...]
    per_object: tuple[str, ...]
    unmatched: tuple[str, ...]
    source: str

    def summary(self, params_sizes: dict[str, int]) -> str:
        n_copied = sum(params_sizes[k] for k in self.copied)
        n_all = sum(params_sizes.values())
        return (f"{len(self.copied)} of {len(params_sizes)} parameter arrays ({n_copied:,} of {n_all:,} scalars) "
                f"from {self.source}; fresh: {len(self.per_object)} per-object"
                + (f", {len(self.unmatched)} without a match ({', '.join(self.unmatched[:4])}"
                   f"{', ...' if len(self.unmatched) > 4 else ''})" if self.unmatched else ""))


def _flat(tree: Any) -> dict[str, Any]:
    return {jax.tree_util.keystr(p): leaf for p, leaf in jax.tree_util.tree_leaves_with_path(tree)}


def per_object_names(init_fn: Any, model_cfg: Any) -> set[str]:
    """Names of the parameter arrays whose shape depends on ``model_cfg.n_objects`` (found by
    drawing the model with one object more)."""
    key = jax.random.PRNGKey(0)
    a = _flat(init_fn(key, model_cfg))
    b = _flat(init_fn(key, dataclasses.replace(model_cfg, n_objects=model_cfg.n_objects + 1)))
    if set(a) != set(b):  # pragma: no cover - a model whose structure depends on the object count
        raise ValueError("the model's parameter structure depends on n_objects; cannot tell the per-object arrays")
    return {k for k in a if np.shape(a[k]) != np.shape(b[k])}


def transfer_params(params: Any, model_cfg: Any, source: str | os.PathLike, init_fn: Any | None = None) -> Transfer:
    """``params`` (a fresh run's) with every object-independent array taken from ``source``.

    ``source``: a run directory, a checkpoint directory or a shipped model's name; its newest
    checkpoint is read (its moving average when it keeps one, as inference does). Raises
    FileNotFoundError when the source is none of these, ValueError when not one array of the
    backbone fits (a source of another architecture: crop size, width or backbone).
    """
    from sc6d_jax import pretrained
    from sc6d_jax.checkpoint import find_checkpoint, load_checkpoint

    if init_fn is None:
        from sc6d_jax.model import init as init_fn
    path = pretrained.check_run(source)
    ckpt = find_checkpoint(path)
    src, _ = load_checkpoint(ckpt)
    src_flat = _flat(src)
    per_obj = per_object_names(init_fn, model_cfg)
    flat_with_path, treedef = jax.tree_util.tree_flatten_with_path(params)
    leaves, copied, fresh_obj, unmatched = [], [], [], []
    for p, leaf in flat_with_path:
        name = jax.tree_util.keystr(p)
        if name in per_obj:
            fresh_obj.append(name)
            leaves.append(np.asarray(leaf))
        elif name in src_flat and np.shape(src_flat[name]) == np.shape(leaf):
            copied.append(name)
            leaves.append(np.array(src_flat[name], dtype=np.asarray(leaf).dtype))
        else:
            unmatched.append(name)
            leaves.append(np.asarray(leaf))
    if not any(n.startswith("['backbone']") for n in copied):
        raise ValueError(f"init_from {source}: no backbone array of {ckpt} fits this model "
                         f"(another crop size, width or backbone?); unmatched: {', '.join(unmatched[:4])}")
    return Transfer(jax.tree_util.tree_unflatten(treedef, leaves), tuple(copied), tuple(fresh_obj), tuple(unmatched),
                    str(ckpt))
