"""Start a run from another trained model: the parameters that do not belong to its objects.

The paper starts its backbone from ImageNet weights; without downloads, this project's
substitute is a model trained on other rendered objects (``TrainConfig.init_from``: a run
directory, a checkpoint directory or a shipped model's name such as ``builtin``). Every
parameter array of the new model whose shape does not depend on the number of objects (the
backbone, the shared decoder, the pose decoder and its heads, the SO(3) encoder's shared
layers) starts from the source's array of the same name and shape; the arrays that belong to
objects (their decoder embeddings, the SO(3) encoder's output layers, any per-object decoder
or head) start as a fresh run's, since the new run's objects are others. A source trained on
the very objects of the new run (the same object ids in the same order, e.g. ``builtin`` for a run
on the built-in objects) gives its per-object arrays too: the run fine-tunes it. The copied and
the fresh arrays are listed, so that what carried over is on record.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import jax
import numpy as np

from sc6d_jax.checkpoint import flatten_with_paths

#: Prefix of the arrays' names (as in checkpoints: ``params/backbone/stem/conv/w``).
PREFIX = "params"


@dataclass(frozen=True)
class Transfer:
    """What :func:`transfer_params` did: the new parameters and the names of the arrays.

    Attributes:
        params: the new model's parameters (numpy pytree).
        copied: names of the arrays taken from the source (checkpoint names, ``params/backbone/...``).
        per_object: names of the arrays that belong to objects and were kept fresh (none when
            ``same_objects``: they are then among ``copied``).
        unmatched: names of the object-independent arrays the source has not in that shape (kept fresh).
        source: the checkpoint directory the parameters came from.
        same_objects: the source was trained on the run's objects (ids and order), so its
            per-object arrays were copied as well.
    """

    params: Any
    copied: tuple[str, ...]
    per_object: tuple[str, ...]
    unmatched: tuple[str, ...]
    source: str
    same_objects: bool = False

    def summary(self) -> str:
        """One line: how many arrays and scalars came from the source, and what stayed fresh."""
        sizes = {k: int(np.size(a)) for k, a in flatten_with_paths(self.params, PREFIX).items()}
        n_copied = sum(sizes[k] for k in self.copied)
        fresh = ("none (the source's objects are the run's: per-object arrays copied too)" if self.same_objects
                 else f"{len(self.per_object)} per-object")
        return (f"{len(self.copied)} of {len(sizes)} parameter arrays ({n_copied:,} of {sum(sizes.values()):,} scalars) "
                f"from {self.source}; fresh: {fresh}"
                + (f", {len(self.unmatched)} without a match ({', '.join(self.unmatched[:4])}"
                   f"{', ...' if len(self.unmatched) > 4 else ''})" if self.unmatched else ""))


def per_object_names(flat: dict[str, np.ndarray], init_fn: Any, model_cfg: Any) -> set[str]:
    """Names of the arrays in ``flat`` (a model drawn with ``model_cfg``, flattened by
    :func:`flatten_with_paths` with :data:`PREFIX`) whose shape depends on ``model_cfg.n_objects``,
    found by drawing the model with one object more."""
    more = flatten_with_paths(init_fn(jax.random.PRNGKey(0), dataclasses.replace(model_cfg, n_objects=model_cfg.n_objects + 1)),
                              PREFIX)
    if set(flat) != set(more):  # pragma: no cover - a model whose structure depends on the object count
        raise ValueError("the model's parameter structure depends on n_objects; cannot tell the per-object arrays")
    return {k for k in flat if flat[k].shape != more[k].shape}


def transfer_params(params: Any, model_cfg: Any, source: str | os.PathLike, init_fn: Any | None = None,
                    obj_ids: Sequence[int] | None = None) -> Transfer:
    """``params`` (a fresh run's) with every object-independent array taken from ``source``.

    ``source``: a run directory, a checkpoint directory or a shipped model's name; its newest
    checkpoint is read (its moving average when it keeps one, as inference does). ``obj_ids``:
    the run's objects, in the model's order; when the source's checkpoint names the same ids in
    the same order, its per-object arrays are copied too (fine-tuning). Raises
    FileNotFoundError when the source is none of these, ValueError when not one array of the
    backbone fits (a source of another architecture: crop size, width or backbone).
    """
    from sc6d_jax import pretrained
    from sc6d_jax.checkpoint import find_checkpoint, load_checkpoint, unflatten_like

    if init_fn is None:
        from sc6d_jax.model import init as init_fn
    ckpt = find_checkpoint(pretrained.check_run(source))
    src_params, src_cfg = load_checkpoint(ckpt)
    src_flat = flatten_with_paths(src_params, PREFIX)
    own = flatten_with_paths(params, PREFIX)
    per_obj = per_object_names(own, init_fn, model_cfg)
    src_ids = src_cfg.stream.obj_ids
    same = obj_ids is not None and src_ids is not None and tuple(src_ids) == tuple(int(i) for i in obj_ids)
    out, copied, fresh_obj, unmatched = {}, [], [], []
    for name, leaf in own.items():
        if name in per_obj and not same:
            fresh_obj.append(name)
            out[name] = leaf
        elif name in src_flat and src_flat[name].shape == leaf.shape:
            copied.append(name)
            out[name] = src_flat[name].astype(leaf.dtype)
        else:
            unmatched.append(name)
            out[name] = leaf
    if not any(n.startswith(f"{PREFIX}/backbone/") for n in copied):
        raise ValueError(f"init_from {source}: no backbone array of {ckpt} fits this model "
                         f"(another crop size, width or backbone?); unmatched: {', '.join(unmatched[:4])}")
    return Transfer(unflatten_like(params, out, PREFIX, str(ckpt)), tuple(copied), tuple(fresh_obj), tuple(unmatched),
                    str(ckpt), same)

