"""Load ImageNet ResNet convolution weights (torchvision names, .npz) into the backbone params.

Mapping (torchvision -> params['backbone']):
  conv1.weight                     -> stem.conv.w      (OIHW -> HWIO; the file's 3 RGB input
                                                        channels fill input channels 0..2, the
                                                        PE channels 3..4 keep their init)
  layer{s}.{i}.conv{1,2}.weight    -> layer{s}[i].conv{1,2}.conv.w
  layer{s}.{i}.downsample.0.weight -> layer{s}[i].down.conv.w
BatchNorm entries (bn*, downsample.1.*) and the classifier fc.* are ignored: the model uses
GroupNorm (statistics per sample, not per data set), so only the convolutions carry over and
the GroupNorm scale/bias keep their init, except the scale after each block's second conv,
which is set from 0 (fresh init: residual branch off) to 1. The U-Net decoder, pose decoder and rotation head
are always trained from scratch.
"""

from __future__ import annotations

import re
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

_CONV = re.compile(r"^(conv1|layer(\d)\.(\d+)\.(conv1|conv2|downsample\.0))\.weight$")


def _target(params: dict, name: str) -> tuple[list, str] | None:
    """Path (list of keys) in params['backbone'] for a torchvision conv name, or None."""
    m = _CONV.match(name)
    if not m:
        return None
    if m.group(1) == "conv1":
        return ["stem", "conv"], "w"
    stage, idx, part = m.group(2), int(m.group(3)), m.group(4)
    part = {"conv1": "conv1", "conv2": "conv2", "downsample.0": "down"}[part]
    return [f"layer{stage}", idx, part, "conv"], "w"


def _backbone_convs(bb: dict) -> list[str]:
    names = ["conv1.weight"]
    for s in range(1, 5):
        for i, blk in enumerate(bb.get(f"layer{s}", [])):
            names += [f"layer{s}.{i}.conv1.weight", f"layer{s}.{i}.conv2.weight"]
            if "down" in blk:
                names.append(f"layer{s}.{i}.downsample.0.weight")
    return names


def load_resnet_weights(params: dict, path: str | Path, strict: bool = True) -> dict:
    """New params whose backbone convolutions are taken from a torchvision-style .npz file.

    ``path``: .npz with arrays named like torchvision's ResNet state dict (conv weights OIHW).
    Every backbone conv of ``params`` must be in the file with a matching shape (ValueError
    otherwise). With ``strict`` (default), conv weights in the file that the backbone does not
    have (e.g. a ResNet34 file for a ResNet18 model) are an error too; with ``strict=False``
    they are ignored (e.g. to seed a "resnet10" from the first block of each ResNet18 stage).
    Raises FileNotFoundError when the file does not exist. ``params`` is not modified.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"weights file not found: {path}")
    if "backbone" not in params:
        raise ValueError("params has no 'backbone' entry (pass the params of sc6d_jax.model.init)")
    with np.load(path) as f:
        arrays = {k: np.asarray(f[k]) for k in f.files}
    bb = jax.tree.map(lambda x: x, params["backbone"])  # structural copy
    wanted = _backbone_convs(bb)
    missing = [n for n in wanted if n not in arrays]
    if missing:
        raise ValueError(f"{path.name}: missing conv weights {missing[:5]}{' ...' if len(missing) > 5 else ''}")
    extra = [k for k in arrays if _target(bb, k) is not None and k not in wanted]
    if extra and strict:
        raise ValueError(
            f"{path.name}: conv weights {extra[:5]} have no place in this backbone (architecture mismatch; "
            "pass strict=False to ignore them)"
        )
    for name in wanted:
        keys, leaf = _target(bb, name)
        node = bb
        for k in keys:
            node = node[k]
        cur = node[leaf]
        w = arrays[name]
        if w.ndim != 4:
            raise ValueError(f"{name}: expected a 4-D OIHW array, got shape {w.shape}")
        w = np.transpose(w, (2, 3, 1, 0)).astype(np.float32)  # OIHW -> HWIO
        if name == "conv1.weight" and w.shape[2] != cur.shape[2]:
            if w.shape[2] > cur.shape[2] or w.shape[:2] != cur.shape[:2] or w.shape[3] != cur.shape[3]:
                raise ValueError(f"{name}: file shape (HWIO) {w.shape} does not fit the stem {cur.shape}")
            w = jnp.asarray(cur).at[:, :, : w.shape[2], :].set(w)
        elif w.shape != cur.shape:
            raise ValueError(f"{name}: file shape (HWIO) {w.shape} != model shape {cur.shape}")
        node[leaf] = jnp.asarray(w, dtype=cur.dtype)
    # Fresh blocks start with a zero GroupNorm scale on their last conv (residual branch off);
    # with pretrained convolutions the branches are switched on (scale 1) instead.
    for s in range(1, 5):
        for blk in bb.get(f"layer{s}", []):
            blk["conv2"]["gn"]["scale"] = jnp.ones_like(blk["conv2"]["gn"]["scale"])
    out = dict(params)
    out["backbone"] = bb
    return out
