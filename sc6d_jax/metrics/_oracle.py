"""Oracle rescoring: estimates with parts of the pose taken from the ground truth.

``with_ground_truth(dataset, estimates, "rotation")`` keeps each estimate's translation and
replaces its rotation by the ground truth's; ``"translation"`` the other way round. Scored
like any results, they say what AR each head reaches alone, i.e. which one holds a model back
(``sc6d eval --oracle``). The translation splits as the network predicts it, into the
projected centre and the distance along its ray: ``"depth"`` keeps the estimate's ray and
moves the estimate along it to the ground truth's depth (z), ``"centre"`` keeps the estimate's
depth and puts it on the ground truth's ray; both together are ``"translation"``. Several parts
combine (``("rotation", "depth")``: only the projected centre left to the estimate). The
ground truth of an estimate is the instance its box was cut from as ``sc6d predict`` picks it:
the most visible instance of the object in the image.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Sequence

import numpy as np

from sc6d_jax.bop import most_visible_instances

#: The parts of a pose an oracle can take from the ground truth.
ORACLE_PARTS = ("rotation", "translation", "depth", "centre")


def oracle_parts(parts: str | Sequence[str]) -> tuple[str, ...]:
    """``parts`` ("depth", "rotation,depth" or a sequence of names) checked against
    ``ORACLE_PARTS`` and returned as a tuple in their order, each once."""
    names = [p.strip() for p in parts.split(",")] if isinstance(parts, str) else [str(p) for p in parts]
    bad = [p for p in names if p not in ORACLE_PARTS]
    if bad or not names:
        raise ValueError(f"oracle part must be one of {ORACLE_PARTS} (or several joined by commas), got {parts!r}")
    return tuple(p for p in ORACLE_PARTS if p in names)


#: What a pose is made of for an oracle: "translation" stands for its depth and its centre.
POSE_PIECES = ("rotation", "depth", "centre")


def oracle_pieces(parts: str | Sequence[str]) -> frozenset[str]:
    """The pieces of ``POSE_PIECES`` that the oracle ``parts`` take from the ground truth."""
    names = set(oracle_parts(parts))
    if "translation" in names:
        names |= {"depth", "centre"}
    return frozenset(names & set(POSE_PIECES))


def _translation(t_est: np.ndarray, t_gt: np.ndarray, pieces: frozenset[str]) -> np.ndarray:
    """The estimate's translation with ``pieces`` of it from the ground truth (mm)."""
    if {"depth", "centre"} <= pieces:
        return t_gt
    if "depth" in pieces:  # the estimate's ray, the ground truth's depth
        return t_est * (t_gt[2] / t_est[2])
    if "centre" in pieces:  # the ground truth's ray, the estimate's depth
        return t_gt * (t_est[2] / t_gt[2])
    return t_est


def with_ground_truth(dataset: Any, estimates: Sequence[Any], part: str | Sequence[str]) -> list[Any]:
    """``estimates`` (``sc6d_jax.bop.PoseEstimate``) with ``part`` replaced by the ground truth
    of the most visible instance of the object in the image (``sc6d_jax.bop.most_visible_instances``,
    as ``sc6d predict`` picks its boxes). ``part`` is one of ``ORACLE_PARTS`` or several
    (a sequence, or names joined by commas): "rotation", "translation", "depth" (the estimate
    moved along its own ray to the ground truth's z) or "centre" (moved onto the ground truth's
    ray at its own z). Estimates of an object with no visible instance stay as they are.

    Args:
        dataset: a ``sc6d_jax.bop.BopDataset`` (its ``scene_gt`` and ``scene_gt_info``).
    """
    pieces = oracle_pieces(part)
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
        R = np.asarray(g.R, np.float64).reshape(3, 3) if "rotation" in pieces else e.R
        t = _translation(np.asarray(e.t, np.float64).reshape(3), np.asarray(g.t, np.float64).reshape(3), pieces)
        out.append(dataclasses.replace(e, R=R, t=t))
    return out
