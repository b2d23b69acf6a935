"""Oracle rescoring: estimates with one part of the pose taken from the ground truth.

``with_ground_truth(dataset, estimates, "rotation")`` keeps each estimate's translation and
replaces its rotation by the ground truth's; ``"translation"`` the other way round. Scored
like any results, they say what AR each head reaches alone, i.e. which one holds a model back
(``sc6d eval --oracle``). The ground truth of an estimate is the instance its box was cut from
as ``sc6d predict`` picks it: the most visible instance of the object in the image.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Sequence

import numpy as np

from sc6d_jax.bop import most_visible_instances

#: The parts of a pose an oracle can take from the ground truth.
ORACLE_PARTS = ("rotation", "translation")


def with_ground_truth(dataset: Any, estimates: Sequence[Any], part: str) -> list[Any]:
    """``estimates`` (``sc6d_jax.bop.PoseEstimate``) with ``part`` ("rotation" or "translation")
    replaced by the ground truth of the most visible instance of the object in the image
    (``sc6d_jax.bop.most_visible_instances``, as ``sc6d predict`` picks its boxes). Estimates of
    an object with no visible instance stay as they are.

    Args:
        dataset: a ``sc6d_jax.bop.BopDataset`` (its ``scene_gt`` and ``scene_gt_info``).
    """
    if part not in ORACLE_PARTS:
        raise ValueError(f"oracle part must be one of {ORACLE_PARTS}, got {part!r}")
    cache: dict[int, tuple[dict, dict]] = {}
    out = []
    for e in estimates:
        if e.scene_id not in cache:
            cache[e.scene_id] = (dataset.scene_gt(e.scene_id), dataset.scene_gt_info(e.scene_id))
        gts, infos = cache[e.scene_id][0].get(e.im_id, []), cache[e.scene_id][1].get(e.im_id, [])
        best = most_visible_instances(gts, infos, e.obj_id)
        if not best:
            out.append(e)
            continue
        g = gts[best[0]]
        if part == "rotation":
            out.append(dataclasses.replace(e, R=np.asarray(g.R, np.float64).reshape(3, 3)))
        else:
            out.append(dataclasses.replace(e, t=np.asarray(g.t, np.float64).reshape(3)))
    return out
