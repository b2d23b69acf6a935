"""Serialise the jitted predictor with ``jax.export`` and run it without the training code.

The file (``.npz``) holds the serialised StableHLO module and its
array arguments: the model parameters as a flat list and the packed rotation library. The
exported function maps a batch of crops (uint8 ``(B,S,S,3)``, K ``(B,3,3)``, crop centre
``(B,2)``, side ``(B,)`` (``meta["crop_pad"]`` times the box's longer side, as the model was
trained; cut with ``meta["crop_supersample"]`` samples per pixel along each axis, the ``supersample``
of ``sc6d_jax.geometry.warp_crop``), object index ``(B,)``) to the pose dict of
:func:`sc6d_jax.inference.predict_crops`.

The batch dimension is symbolic where the network allows it. Per-object decoders (per-sample
convolution kernels) lower to convolutions whose group count is the batch size, which StableHLO
cannot keep symbolic; such models are exported for a fixed batch of ``FIXED_BATCH`` crops and
the loader pads and chunks any batch to it.
"""

from __future__ import annotations

import io
import json
import os
from pathlib import Path
from typing import Any, Callable

import numpy as np

from sc6d_jax._io import atomic_write_bytes

EXPORT_FORMAT = "sc6d-jax-exported-predictor/1"
FIXED_BATCH = 16


def export_predictor(est: Any, path: str | os.PathLike, tta: bool = False, top_k: int = 1,
                     tta_mode: str = "fuse") -> Path:
    """Write ``est``'s predictor (options fixed: tta, tta_mode, top_k; no refinement) to ``path`` (.npz)."""
    import jax
    import jax.numpy as jnp
    from jax import export

    from sc6d_jax.inference._predictor import predict_crops

    leaves, treedef = jax.tree_util.tree_flatten(est.params)
    kw, blocks = est.crops_fn(64, tta=tta, top_k=top_k, refine=False, tta_mode=tta_mode)
    S = est.mcfg.crop_size

    def fn(leaves, blocks, lib_R, rgb, K, center, side, obj_idx):
        params = jax.tree_util.tree_unflatten(treedef, leaves)
        return predict_crops(params, blocks, lib_R, rgb, K, center, side, obj_idx, **kw)

    sds = jax.ShapeDtypeStruct

    def args_for(b):
        return (
            [sds(x.shape, x.dtype) for x in leaves],
            sds(blocks.shape, blocks.dtype),
            sds(est._lib_R.shape, est._lib_R.dtype),
            sds((b, S, S, 3), jnp.uint8),
            sds((b, 3, 3), jnp.float32),
            sds((b, 2), jnp.float32),
            sds((b,), jnp.float32),
            sds((b,), jnp.int32),
        )

    try:
        exp = export.export(jax.jit(fn))(*args_for(export.symbolic_shape("b")[0]))
        fixed = None
    except NotImplementedError:  # per-sample kernels: the batch becomes a conv group count
        exp = export.export(jax.jit(fn))(*args_for(FIXED_BATCH))
        fixed = FIXED_BATCH
    meta = {"format": EXPORT_FORMAT, "crop_size": S, "crop_pad": est.mcfg.crop_pad,
            "crop_supersample": getattr(est.mcfg, "crop_supersample", 1), "obj_ids": est.obj_ids, "tta": tta, "tta_mode": tta_mode, "top_k": top_k,
            "n_params": len(leaves), "library_key": est.library.key, "fixed_batch": fixed}
    arrays = {f"p{i:05d}": np.asarray(x) for i, x in enumerate(leaves)}
    arrays.update(blocks=np.asarray(blocks), lib_R=np.asarray(est._lib_R),
                  exported=np.frombuffer(bytes(exp.serialize()), np.uint8), meta=np.asarray(json.dumps(meta)))
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return atomic_write_bytes(path, buf.getvalue())


def load_exported(path: str | os.PathLike) -> Callable[..., dict]:
    """Load a predictor written by :meth:`Estimator.export`.

    Returns ``f(rgb, K, center, side, obj_idx) -> dict`` of numpy arrays (``f.meta`` holds the
    crop size, object ids and options). Needs only jax and numpy.
    """
    import jax.numpy as jnp
    from jax import export

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"exported predictor {path} does not exist")
    try:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            if meta.get("format") != EXPORT_FORMAT:
                raise ValueError(f"{path} is not a {EXPORT_FORMAT} file")
            leaves = [jnp.asarray(z[f"p{i:05d}"]) for i in range(meta["n_params"])]
            blocks, lib_R = jnp.asarray(z["blocks"]), jnp.asarray(z["lib_R"])
            exp = export.deserialize(bytearray(z["exported"].tobytes()))
    except (KeyError, OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path} is not a readable exported predictor: {exc}") from exc

    def run(rgb, K, center, side, obj_idx) -> dict[str, np.ndarray]:
        rgb = np.asarray(rgb)
        if rgb.dtype != np.uint8 or rgb.ndim != 4 or rgb.shape[1:] != (meta["crop_size"],) * 2 + (3,):
            raise ValueError(f"crops must be uint8 (B, {meta['crop_size']}, {meta['crop_size']}, 3), got {rgb.dtype}{rgb.shape}")
        ins = [rgb, np.asarray(K, np.float32), np.asarray(center, np.float32), np.asarray(side, np.float32),
               np.asarray(obj_idx, np.int32)]
        fixed, n = meta.get("fixed_batch"), len(rgb)
        if not fixed:
            out = exp.call(leaves, blocks, lib_R, *(jnp.asarray(a) for a in ins))
            return {k: np.asarray(v) for k, v in out.items()}
        chunks = []
        for i in range(0, max(n, 1), fixed):  # pad the last chunk by repeating its first row
            part = [a[i:i + fixed] for a in ins]
            m = len(part[0])
            part = [np.concatenate([p, np.repeat(p[:1], fixed - m, axis=0)]) if m < fixed else p for p in part]
            out = exp.call(leaves, blocks, lib_R, *(jnp.asarray(a) for a in part))
            chunks.append({k: np.asarray(v)[:m] for k, v in out.items()})
        return {k: np.concatenate([c[k] for c in chunks]) for k in chunks[0]}

    run.meta = meta  # type: ignore[attr-defined]
    return run
