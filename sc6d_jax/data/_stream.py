"""The training crop stream: batches rendered on the fly by MuJoCo in worker processes.

Batch ``b`` is a pure function of ``(seed, b)``: each sample draws from
``numpy.random.default_rng([seed, b, j])``, whatever the number of workers, so a resumed run
sees the same data as an uninterrupted one. Each worker process holds one renderer (one GL
context) at crop resolution and renders whole batches; the parent keeps ``2 x workers``
batches in flight so the training loop does not wait. The image-sized arrays (rgb, pe,
mask_visib: 6 MB per batch of 32 at 128x128) come back through a ring of shared-memory slots,
not through the result pipe: pickling them through the pipe cost a third of one worker's
throughput.
"""

from __future__ import annotations

import concurrent.futures as cf
import dataclasses
import multiprocessing as mp
import os
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from multiprocessing import shared_memory
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from sc6d_jax.data._augment import camera_effects, colour_augment, random_background
from sc6d_jax.data._clutter import DISTRACTOR_SHAPES, TABLE_PRIMITIVES, tabletop_around, textured_table
from sc6d_jax.data._scene import IMAGE_H, IMAGE_W, hull_vertices, random_rotation, sample_pose

#: Resample a crop whose visible mask is below either bound (authors' code).
MIN_VISIBLE_PX = 50
MIN_VISIBLE_FRACTION = 0.05
#: the smallest visible box of a target relative to its amodal box that ``delta_z_range`` allows for
VISIBLE_BOX_MIN = 0.3
#: Procedural backgrounds pre-drawn per worker.
BACKGROUND_BANK = 256
#: Rendered clutter scenes per worker (``StreamConfig.scene_backgrounds``).
SCENE_BANK = 128
#: Shadow map side in texels, and the half width it covers about the target in target diameters
#: (``StreamConfig.shadows``): distractors lie up to ~3 diameters behind the target and a light
#: from the side spreads them sideways in its map; 1024 texels over 7 diameters are ~2 texels
#: per pixel of a 64-pixel crop (~1.5 diameters wide).
SHADOW_SIZE = 1024
SHADOW_REACH = 3.5
#: the largest angle between the shadow-casting light's direction and the optical axis (degrees)
SHADOW_LIGHT_ANGLE = 80.0
#: Scheduling priority the worker processes lower themselves by (os.nice).
WORKER_NICENESS = 10
#: times in a row the stream restarts its render workers after one died (CropStream)
MAX_WORKER_RESTARTS = 3


@dataclass(frozen=True)
class StreamConfig:
    """Settings of :class:`CropStream`.

    Attributes:
        models_dir: BOP models folder (PLY in mm + models_info.json).
        crop_size: S, the crop side in pixels.
        batch_size: crops per batch.
        seed: the stream's seed; batch b depends on (seed, b) only.
        workers: worker processes (0 = render in this process).
        obj_ids: objects to sample (None = every model in the folder); the index of an id in
            this list is the sample's ``obj_idx``.
        obj_weights: how often each object of ``obj_ids`` is drawn, relative to the others (one
            positive weight per id, in their order); None = all equally often (the streams of
            earlier runs are unchanged). The z range (``delta_z_range``) draws uniformly either
            way, so a weighted run decodes depth as the unweighted one does.
        augment: colour augmentation (with probability ``colour_p``) and random in-plane
            90-degree rotations.
        colour_p: the probability that a crop gets the colour augmentation (``colour_augment``:
            blur, per-channel gain and offset, contrast, noise, pixel dropout, inversion), the
            authors' 0.8; 0 keeps the rendered colours (the quarter turns stay with ``augment``).
        pe_turns: the PE map turns with the crop in that augmentation (``sc6d_jax.geometry.turn_pe``;
            False = the authors': it stays unturned).
        occlusion: probability that other objects / primitives occlude the target.
        pad: crop padding factor (s_B = pad * max(w, h)).
        box_shift, box_scale: the box jitter that the crop is cut from, the authors' dynamic
            zoom-in: the centre moves by up to +-box_shift of the box's width and height, the
            side is scaled by a factor drawn from box_scale. It stands for the detector's box
            error; a crop whose box was scaled by s shows the object s times smaller, so the
            depth head must measure the object's size in pixels to within its depth error.
            (0, (1, 1)) = the amodal box itself. Every setting draws the same random numbers.
        box_source: the box the crop is cut from (before the jitter): "amodal", the projection
            of the whole model, or "visible", the extent of the target's visible pixels, as the
            estimator takes a ground truth's ``bbox_visib`` (``sc6d_jax.bop.bbox_extent``) or a
            detector's box: an occluded target
            then fills the crop as it does at inference. The visible box is measured in a first
            render of the crop's scene (target and occluders, masks only) through the amodal
            box, so occluded crops cost two renders; unoccluded ones are cut from the amodal box
            (their visible box). The jitter is applied to the visible box with the same draws.
        distance: camera distance range in object diameters.
        placement: (low, high): the target's centre projects to (u, v) drawn uniformly in this
            range of fractions of the image's width and height; the default (0.15, 0.85) keeps
            it within about 20 degrees of the optical axis (25 in the corners), (0.05, 0.95)
            within about 25 (30-35 in the corners).
        background: "textured" (procedural patterns) or "plain" (one random colour per crop):
            plain backgrounds and no occlusion make a much easier task for tiny smoke runs.
        dense: also render depth and return dense geometric targets of the target's visible
            surface at S/4 (``dense_targets``): its normals in the allocentric frame of the
            rotation label and its depth relative to the object centre in diameters. They
            need no symmetry labels (they describe what the crop shows).
        dense_xyz: with ``dense``, three more channels: the visible surface's points in the
            object's own frame (``dense_targets(xyz=True)``); ambiguous for a symmetric
            object, as any object-frame target is.
        view: side V of a clean view of the target returned as ``view`` uint8 (B,V,V,3)
            (0 = none): the rendered crop before the colour augmentation, black wherever the
            target is not visible (background, occluders), averaged over (S/V)^2 blocks and
            turned with the crop (``clean_view``). What an augmented crop shows of the object
            itself, as the Augmented Autoencoder's reconstruction target; no symmetry labels (two
            poses that look alike give one view). V must divide S.
        curriculum: number of batches over which the task grows from easy to the full setting
            (0 = full from the start). At batch b the difficulty is d = min(1, b / curriculum):
            a crop gets a textured background with probability d (else a plain one) and
            occluders with probability ``occlusion * d``. Small networks trained from scratch
            learn nothing in the first thousands of steps on the full setting, and quickly on
            plain backgrounds; the ramp is a pure function of b, so determinism is kept.
        materials: draw each rendered object's specular intensity (0-0.8) and shininess (0-1)
            per crop (else MuJoCo's 0.3 and 0.3 for every object).
        resample: a crop whose box is smaller in its image than S pixels is reduced to the box's
            image size and enlarged back, as a real crop cut from a camera image is
            (``camera_effects``); rendered directly at S x S it would be sharper than any real one.
        sensor: camera effects at image resolution: motion blur, gamma, sensor noise, JPEG
            (``camera_effects``), before the colour augmentation.
        distractors: up to this many other objects placed behind the target (they never cover
            it), in a crop with probability equal to the curriculum's difficulty: object clutter
            in the background, as in real scenes, next to the procedural patterns.
        object_gain: (low, high): every drawn object's and occluder's pixels multiplied by one
            factor per crop, log-uniform in [low, high], before the camera effects and the colour
            augmentation; the background keeps its brightness. A model's colours are known only
            up to the exposure of its scan and of the test camera; without it the rendered objects
            sit at one brightness relative to their surroundings. None = off.
        object_contrast: (low, high): each drawn object's and occluder's pixels spread about
            their own mean colour by a factor log-uniform in [low, high], drawn per object and
            crop, after ``object_gain``. A scan's vertex colours carry the light of its capture,
            and a photograph adds the test scene's: how strongly an object is shaded relative to
            its rendering is not known. None = off.
        object_colour: (low, high): each drawn object's and occluder's pixels multiplied per
            colour channel by factors log-uniform in [low, high], drawn per channel, object and
            crop, after ``object_gain`` and before ``object_contrast``: a scan's vertex colours
            carry the white balance of its capture, a photograph that of the test camera, and
            the colour augmentation shifts the object and its surroundings together. None = off.
        scene_backgrounds: the probability that a crop's textured background is a window of a
            rendered tabletop clutter scene (``sc6d_jax.data._clutter``: a table with the models
            and primitive shapes on it, under random lights) instead of a procedural pattern;
            a bank of SCENE_BANK scenes is rendered once per worker (at twice the crop size).
            0 = off.
        shadows: the probability that a crop's first directional light casts shadows of the
            rendered geometry (the target on itself, occluders and distractors on the target and
            on each other; not on the 2D background): a photograph's key light leaves dark,
            sharp-edged regions on an object that unshadowed rendering never shows. That light
            comes from any side (its direction uniform within SHADOW_LIGHT_ANGLE of the optical
            axis; the other lights come mostly from behind the camera, where the shadows fall
            out of sight). The shadow map covers SHADOW_REACH target diameters about the target.
            0 = off (and the renderer makes no shadow map).
        tabletop: the probability that a crop's target stands on a rendered table with 1-4 other
            models and 0-2 primitive shapes standing around it (``sc6d_jax.data._clutter.tabletop_around``),
            all in the target's own render: one set of lights (and shadows, with ``shadows``), the
            contact of the target with its surface, neighbours that may occlude it; the table
            fills the crop below its horizon, the 2D background the rest. A pasted target
            (the default) is lit apart from its surroundings and never touches them; in a
            photograph it shares their light. Such a crop has no floating ``distractors``.
            Scaled by the curriculum's difficulty, as the distractors are. 0 = off.
        tabletop_spacing: (low, high) in target diameters: the table's neighbours stand that far
            from the target (uniform), measured between their extents along the direction
            from the target to each (they touch at 0 and never intersect), instead of outside
            the target's bounding sphere (None, the default: apart by its largest radius or
            more). With ``box_source="visible"`` such a crop is cut from the target's visible
            box, as an occluded one is. Only with ``tabletop``.
        These eleven default to off (the streams of earlier runs are unchanged); they are the
        stream's realism options for real test images (LM-O).
        image_border: the crop's pixels that lie outside the 640x480 image its pose was drawn in
            are black (after the colour augmentation) and not part of the visible mask, as in a
            crop cut from a real image (``sc6d_jax.geometry.warp_crop`` pads with zeros); False =
            the whole crop is rendered, beyond the image's edges too.
        supersample: each crop pixel is the mean of ``supersample x supersample`` samples over its
            area: the crop is rendered at ``supersample * crop_size`` pixels through
            ``sc6d_jax.geometry.supersample_transform`` and averaged in blocks
            (``area_downsample``; the visible mask is each block's majority). A crop rendered
            with one sample per pixel (1, the default) has hard, stair-stepped edges, so the
            object's outline, and with it its size in the crop, is known to a pixel only; the
            averaged edges carry where the outline falls within the pixel, as a camera's pixels
            (and the estimator's crops cut with the model's ``crop_supersample``) do. Not with
            ``dense``.
        max_faces: render meshes with more faces than this simplified to about this many
            (``sc6d_jax.render.simplify_mesh``; 0 = the full meshes). 5,000 faces render the
            LM-O models 3.5x faster at 64x64 with silhouettes 99 % the same (IoU); the labels
            (boxes, poses) still come from the full meshes.
    """

    models_dir: str
    crop_size: int = 64
    batch_size: int = 32
    seed: int = 0
    workers: int = 2
    obj_ids: tuple[int, ...] | None = None
    obj_weights: tuple[float, ...] | None = None
    augment: bool = True
    pe_turns: bool = False
    occlusion: float = 0.5
    pad: float = 1.5
    box_shift: float = 0.25
    box_scale: tuple[float, float] = (0.75, 1.25)
    box_source: str = "amodal"
    distance: tuple[float, float] = (2.5, 9.0)
    placement: tuple[float, float] = (0.15, 0.85)
    background: str = "textured"
    curriculum: int = 0
    dense: bool = False
    dense_xyz: bool = False
    view: int = 0
    materials: bool = False
    resample: bool = False
    sensor: bool = False
    distractors: int = 0
    max_faces: int = 0
    object_gain: tuple[float, float] | None = None
    object_contrast: tuple[float, float] | None = None
    object_colour: tuple[float, float] | None = None
    scene_backgrounds: float = 0.0
    shadows: float = 0.0
    tabletop: float = 0.0
    tabletop_spacing: tuple[float, float] | None = None
    image_border: bool = False
    colour_p: float = 0.8
    supersample: int = 1

    def __post_init__(self) -> None:
        check_options(self)
        if not isinstance(self.supersample, int) or isinstance(self.supersample, bool) or not 1 <= self.supersample <= 8:
            raise ValueError(f"supersample must be an integer in [1, 8], got {self.supersample!r}")
        if self.supersample > 1 and self.dense:
            raise ValueError("supersample > 1 is not available with dense targets (dense=True)")
        object.__setattr__(self, "placement", unit_range(self.placement, "placement"))
        if self.dense_xyz and not self.dense:
            raise ValueError("dense_xyz adds channels to the dense targets: it needs dense=True")
        if not isinstance(self.view, int) or self.view < 0 or (self.view and self.crop_size % self.view):
            raise ValueError(f"view must be 0 (off) or a positive int dividing crop_size {self.crop_size}, got {self.view!r}")
        if self.background not in ("textured", "plain"):
            raise ValueError(f"background must be 'textured' or 'plain', got {self.background!r}")
        if self.box_source not in ("amodal", "visible"):
            raise ValueError(f"box_source must be 'amodal' or 'visible', got {self.box_source!r}")
        if not 0.0 <= self.box_shift < 1.0:
            raise ValueError(f"box_shift must be in [0, 1), got {self.box_shift!r}")
        if len(self.box_scale) != 2 or not 0.0 < self.box_scale[0] <= self.box_scale[1]:
            raise ValueError(f"box_scale must be (low, high) with 0 < low <= high, got {self.box_scale!r}")
        if not 0.0 <= self.colour_p <= 1.0:
            raise ValueError(f"colour_p must be a probability in [0, 1], got {self.colour_p!r}")
        if self.curriculum < 0:
            raise ValueError(f"curriculum must be >= 0 batches, got {self.curriculum}")
        if not 0.0 <= self.occlusion <= 1.0:
            raise ValueError(f"occlusion must be a probability in [0, 1], got {self.occlusion}")
        if self.crop_size < 8 or self.crop_size % 4:
            raise ValueError(f"crop_size must be a multiple of 4 and >= 8, got {self.crop_size}")
        if self.batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {self.batch_size}")
        if self.workers < 0:
            raise ValueError(f"workers must be >= 0, got {self.workers}")
        if self.obj_weights is not None:
            object.__setattr__(self, "obj_weights", object_weights(self.obj_weights, self.obj_ids))


def object_weights(weights, obj_ids, prefix: str = "") -> tuple[float, ...]:
    """``weights`` as a tuple of floats, checked: one positive finite weight per id of ``obj_ids``
    (ValueError naming ``prefix + "obj_weights"`` otherwise)."""
    w = _float_pair(weights)
    if not w or not all(np.isfinite(x) and x > 0 for x in w):
        raise ValueError(f"{prefix}obj_weights must be positive numbers, one per object, got {weights!r}")
    if obj_ids is None:
        raise ValueError(f"{prefix}obj_weights weighs the objects of obj_ids in their order: set {prefix}obj_ids too")
    if len(w) != len(obj_ids):
        raise ValueError(f"{prefix}obj_weights has {len(w)} weights for {len(obj_ids)} objects "
                         f"(obj_ids {tuple(obj_ids)}): give one per object, in their order")
    return w


#: The stream's realism options for real test images (StreamConfig fields, all off by default),
#: and the other options a training config passes on to the stream only when set: the one list
#: that the training settings (``sc6d_jax.train.config.StreamSettings``) and loop follow.
REALISM_OPTIONS = ("materials", "resample", "sensor", "distractors", "object_gain", "object_contrast",
                   "object_colour", "scene_backgrounds", "shadows", "tabletop", "tabletop_spacing")
PASSED_WHEN_SET = (*REALISM_OPTIONS, "max_faces", "image_border", "obj_weights")


def check_options(cfg, prefix: str = "") -> None:
    """Check (and normalise in place: ranges become float pairs) the :data:`PASSED_WHEN_SET`
    fields of ``cfg``, a StreamConfig or a training config's stream settings; the errors name each
    field as ``prefix + name``."""
    for name in ("scene_backgrounds", "shadows", "tabletop"):
        v = getattr(cfg, name)
        if not 0.0 <= v <= 1.0:
            raise ValueError(f"{prefix}{name} must be a probability in [0, 1], got {v!r}")
    for name in ("object_gain", "object_contrast", "object_colour"):
        if getattr(cfg, name) is not None:
            object.__setattr__(cfg, name, positive_range(getattr(cfg, name), prefix + name))
    if cfg.tabletop_spacing is not None:
        g = _float_pair(cfg.tabletop_spacing)
        if len(g) != 2 or not 0.0 <= g[0] <= g[1]:
            raise ValueError(f"{prefix}tabletop_spacing must be (low, high) with 0 <= low <= high target diameters, "
                             f"got {cfg.tabletop_spacing!r}")
        object.__setattr__(cfg, "tabletop_spacing", g)
        if not cfg.tabletop:
            raise ValueError(f"{prefix}tabletop_spacing places the table's neighbours: it needs {prefix}tabletop > 0")
    if not isinstance(cfg.distractors, int) or cfg.distractors < 0:
        raise ValueError(f"{prefix}distractors must be a non-negative integer, got {cfg.distractors!r}")
    if not isinstance(cfg.max_faces, int) or cfg.max_faces < 0 or 0 < cfg.max_faces < 4:
        raise ValueError(f"{prefix}max_faces must be 0 (full meshes) or an integer >= 4, got {cfg.max_faces!r}")


def _float_pair(value) -> tuple[float, ...]:
    """``value`` as a tuple of floats; () when it is not a sequence of numbers."""
    try:
        return tuple(float(x) for x in value)
    except (TypeError, ValueError):
        return ()


def _each_instance(rgb: np.ndarray, instance: np.ndarray, change) -> np.ndarray:
    """``rgb`` with each instance's pixels (``instance == k``, k >= 0, in the order of the ids)
    replaced by ``change(pixels)`` (float32 (n, 3)), rounded and clipped back to uint8."""
    x = rgb.astype(np.float32)
    for k in np.unique(instance[instance >= 0]):
        m = instance == k
        x[m] = change(x[m])
    return np.clip(x + 0.5, 0, 255).astype(np.uint8)


def object_contrast(rng: np.random.Generator, rgb: np.ndarray, instance: np.ndarray,
                    span: tuple[float, float]) -> np.ndarray:
    """``rgb`` with each instance's pixels spread about their mean colour by its own factor,
    log-uniform in ``span`` (drawn in the order of the instance ids)."""
    lo, hi = np.log(span[0]), np.log(span[1])

    def spread(px: np.ndarray) -> np.ndarray:
        mu = px.mean(axis=0)
        return (px - mu) * float(np.exp(rng.uniform(lo, hi))) + mu

    return _each_instance(rgb, instance, spread)


def object_colour(rng: np.random.Generator, rgb: np.ndarray, instance: np.ndarray,
                  span: tuple[float, float]) -> np.ndarray:
    """``rgb`` with each instance's pixels multiplied per channel by three factors of its own,
    log-uniform in ``span`` (drawn in the order of the instance ids)."""
    lo, hi = np.log(span[0]), np.log(span[1])
    return _each_instance(rgb, instance, lambda px: px * np.exp(rng.uniform(lo, hi, 3)).astype(np.float32))


def positive_range(value, name: str) -> tuple[float, float]:
    """``value`` as a ``(low, high)`` float pair with 0 < low <= high (ValueError naming ``name``)."""
    g = _float_pair(value)
    if len(g) != 2 or not 0.0 < g[0] <= g[1]:
        raise ValueError(f"{name} must be (low, high) with 0 < low <= high, got {value!r}")
    return g


def unit_range(value, name: str) -> tuple[float, float]:
    """``value`` as a ``(low, high)`` float pair with 0 <= low <= high <= 1 (ValueError naming ``name``)."""
    g = _float_pair(value)
    if len(g) != 2 or not 0.0 <= g[0] <= g[1] <= 1.0:
        raise ValueError(f"{name} must be (low, high) with 0 <= low <= high <= 1, got {value!r}")
    return g


def inside_image(T: np.ndarray, S: int, width: int = IMAGE_W, height: int = IMAGE_H) -> np.ndarray:
    """(..., S, S) bool: which pixels of crops with transforms ``T`` (..., 3, 3) (image -> crop,
    affine) come from inside a ``width`` x ``height`` image: their centres map to within half a
    pixel of its pixel centres, where a bilinear warp with a zero border still reads the image."""
    Ti = np.linalg.inv(np.asarray(T, np.float64))
    s = np.arange(S, dtype=np.float64)
    u, v = np.meshgrid(s, s)  # u: column, v: row
    x = Ti[..., 0, 0, None, None] * u + Ti[..., 0, 1, None, None] * v + Ti[..., 0, 2, None, None]
    y = Ti[..., 1, 0, None, None] * u + Ti[..., 1, 1, None, None] * v + Ti[..., 1, 2, None, None]
    return (x >= -0.5) & (x <= width - 0.5) & (y >= -0.5) & (y <= height - 0.5)


def derive_seed(seed: int, tag: int) -> int:
    """A stream seed derived from a run's ``seed`` and a ``tag`` (a process index, a purpose):
    independent streams that are still pure functions of the run's seed."""
    return int(np.random.SeedSequence([seed, tag]).generate_state(1)[0] & 0x7FFFFFFF)


def dense_targets(
    depth: np.ndarray, mask: np.ndarray, K_B: np.ndarray, R: np.ndarray, R_allo: np.ndarray, t: np.ndarray,
    diameter: np.ndarray, factor: int = 4, xyz: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """Dense targets of the target's visible surface, averaged over ``factor`` x ``factor`` blocks.

    depth (B,S,S) mm along the optical axis of the crop camera K_B (B,3,3); mask (B,S,S) the
    target's visible pixels; R, R_allo (B,3,3) its egocentric and allocentric rotations, t (B,3)
    mm, diameter (B,) mm. Returns ``dense`` float32 (B,S/f,S/f,4): the unit surface normal (from
    the back-projected depth's central differences, turned into the allocentric frame of the
    rotation label, facing the camera) and (depth - t_z) / diameter; and ``weight`` float32
    (B,S/f,S/f): the fraction of each block's pixels where the target and its four neighbours are
    visible (0 = no target there; the normal is then 0). With ``xyz``, three more channels: the
    surface's points in the object's own frame, R^T (P - t) / diameter (block means): what
    tells a nearly symmetric object's turned copies apart, unlike the view-frame normals.
    """
    depth = np.asarray(depth, np.float32)
    B, S, _ = depth.shape
    f = factor
    ramp = np.arange(S, dtype=np.float32)
    fx, fy = K_B[:, 0, 0].astype(np.float32), K_B[:, 1, 1].astype(np.float32)
    xs = (ramp[None] - K_B[:, 0, 2, None].astype(np.float32)) / fx[:, None]  # (B,S): X / Z along u
    ys = (ramp[None] - K_B[:, 1, 2, None].astype(np.float32)) / fy[:, None]
    X = depth * xs[:, None, :]
    Y = depth * ys[:, :, None]
    vis = (np.asarray(mask) > 0) & (depth > 0)
    ok = np.zeros_like(vis)
    ok[:, 1:-1, 1:-1] = vis[:, 1:-1, 1:-1] & vis[:, :-2, 1:-1] & vis[:, 2:, 1:-1] & vis[:, 1:-1, :-2] & vis[:, 1:-1, 2:]
    c = (slice(None), slice(1, -1), slice(1, -1))
    # central differences along u (a) and v (b) of the back-projected points, inner pixels only
    ax, ay, az = (M[:, 1:-1, 2:] - M[:, 1:-1, :-2] for M in (X, Y, depth))
    bx, by, bz = (M[:, 2:, 1:-1] - M[:, :-2, 1:-1] for M in (X, Y, depth))
    nx, ny, nz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
    inv = 1.0 / (np.sqrt(nx * nx + ny * ny + nz * nz) + 1e-12)
    facing = np.where(nx * X[c] + ny * Y[c] + nz * depth[c] > 0, -inv, inv)  # n . P < 0: towards the camera
    w = ok.astype(np.float32)
    n = np.zeros((B, S, S, 3), np.float32)
    n[:, 1:-1, 1:-1, 0] = nx * facing * w[c]
    n[:, 1:-1, 1:-1, 1] = ny * facing * w[c]
    n[:, 1:-1, 1:-1, 2] = nz * facing * w[c]
    rel = (depth - t[:, 2, None, None].astype(np.float32)) / np.asarray(diameter, np.float32)[:, None, None]

    def blocks(a: np.ndarray) -> np.ndarray:
        return a.reshape(B, S // f, f, S // f, f, *a.shape[3:]).sum(axis=(2, 4))

    wsum = blocks(w)
    n_avg = blocks(n)
    n_avg /= np.linalg.norm(n_avg, axis=-1, keepdims=True) + 1e-12
    # camera frame -> allocentric frame of the label (R_allo R^T), after averaging (it is linear)
    to_allo = np.einsum("bij,bkj->bik", R_allo, R).astype(np.float32)
    n_avg = np.einsum("bij,bhwj->bhwi", to_allo, n_avg)
    rel_avg = blocks(rel * w) / np.maximum(wsum, 1e-12)
    parts = [n_avg, rel_avg[..., None]]
    if xyz:  # camera frame -> the object's frame, about its origin, in diameters
        P = np.stack([X, Y, depth], axis=-1) - t[:, None, None, :].astype(np.float32)
        P = np.einsum("bji,bhwj->bhwi", np.asarray(R, np.float32), P)
        P /= np.asarray(diameter, np.float32)[:, None, None, None]
        parts.append(blocks(P * w[..., None]) / np.maximum(wsum, 1e-12)[..., None])
    dense = np.concatenate(parts, axis=-1)
    dense[wsum == 0] = 0.0
    return dense.astype(np.float32), (wsum / (f * f)).astype(np.float32)


def clean_view(rgb: np.ndarray, mask: np.ndarray, side: int) -> np.ndarray:
    """The target alone as the crop shows it: uint8 (B,side,side,3) of ``rgb`` (B,S,S,3) where
    ``mask`` (B,S,S) is set and black elsewhere, averaged over (S/side)^2 blocks (rounded)."""
    B, S = rgb.shape[:2]
    if S % side:
        raise ValueError(f"clean_view: side {side} must divide the crop size {S}")
    f = S // side
    x = rgb.astype(np.float32) * (np.asarray(mask) > 0)[..., None]
    x = x.reshape(B, side, f, side, f, 3).mean(axis=(2, 4))
    return np.clip(np.rint(x), 0, 255).astype(np.uint8)


def resolve_obj_ids(cfg: StreamConfig) -> list[int]:
    from sc6d_jax.bop import load_models_info

    models = Path(cfg.models_dir)
    if not models.is_dir():
        raise FileNotFoundError(f"{models}: models folder not found")
    plys = sorted(models.glob("obj_*.ply"))
    if not plys:
        raise ValueError(f"{models}: no models (obj_XXXXXX.ply) in the folder")
    if not (models / "models_info.json").is_file():
        raise FileNotFoundError(f"{models / 'models_info.json'}: required BOP file missing")
    available = sorted(load_models_info(models))
    if cfg.obj_ids is None:
        return available
    missing = [i for i in cfg.obj_ids if i not in available]
    if missing:
        raise ValueError(f"objects {missing} are not in {models} (available: {available})")
    return list(cfg.obj_ids)


def _roll2(img: np.ndarray, dy: int, dx: int) -> np.ndarray:
    """``np.roll(img, (dy, dx), axis=(0, 1))`` as four block copies (np.roll: ~7x slower)."""
    h, w = img.shape[:2]
    out = np.empty_like(img)
    out[dy:, dx:] = img[: h - dy, : w - dx]
    out[:dy, dx:] = img[h - dy :, : w - dx]
    out[dy:, :dx] = img[: h - dy, w - dx :]
    out[:dy, :dx] = img[h - dy :, w - dx :]
    return out


class _Worker:
    """One renderer and the models it needs; renders whole batches."""

    def __init__(self, cfg: StreamConfig) -> None:
        from sc6d_jax.bop import load_models_info, model_path
        from sc6d_jax.render import Renderer, load_mesh

        self.cfg = cfg
        self.obj_ids = resolve_obj_ids(cfg)
        #: each object's probability in the order of obj_ids (None = uniform)
        self.obj_p = None if cfg.obj_weights is None else np.asarray(cfg.obj_weights) / np.sum(cfg.obj_weights)
        infos = load_models_info(cfg.models_dir)
        all_ids = sorted(infos)
        meshes = {i: load_mesh(model_path(cfg.models_dir, i)) for i in all_ids}
        self.vertices = {i: hull_vertices(m.vertices) for i, m in meshes.items()}  # for the boxes
        self.diameters = {i: infos[i].diameter for i in all_ids}
        self.all_ids = all_ids
        S = cfg.crop_size
        if cfg.max_faces:
            from sc6d_jax.render import simplify_mesh

            meshes = {i: simplify_mesh(m, cfg.max_faces) for i, m in meshes.items()}
        self.radii = {i: float(np.linalg.norm(v, axis=1).max()) for i, v in self.vertices.items()}
        n_prims = 2 + (1 + TABLE_PRIMITIVES[1] if cfg.tabletop > 0 else 0)  # occluders (+ table and shapes)
        #: the render's side: supersample samples per crop pixel along each axis
        self.render_size = S * cfg.supersample
        self.renderer = Renderer(meshes, self.render_size, self.render_size, max_instances=2, n_primitives=n_prims, n_lights=2,
                                 shadow_size=SHADOW_SIZE if cfg.shadows > 0 else 0)
        # A bank of procedural backgrounds (a function of the seed), varied per sample by
        # flips, a roll and a colour shift: 4x cheaper than drawing a new one per crop.
        bank_rng = np.random.default_rng([cfg.seed, 2**31 - 2])
        self.backgrounds = np.stack([random_background(bank_rng, S) for _ in range(BACKGROUND_BANK)])
        self.scenes = None
        if cfg.scene_backgrounds > 0:  # rendered tabletop clutter, windows of S x S cut per crop
            from sc6d_jax.data._clutter import clutter_scenes

            self.scenes = clutter_scenes(meshes, self.diameters, SCENE_BANK, 2 * S,
                                         np.random.default_rng([cfg.seed, 2**31 - 3]))

    def difficulty(self, b: int) -> float:
        return 1.0 if self.cfg.curriculum == 0 else min(1.0, b / self.cfg.curriculum)

    def background(self, rng: np.random.Generator, difficulty: float = 1.0) -> np.ndarray:
        if self.cfg.background == "plain" or (difficulty < 1.0 and rng.random() >= difficulty):
            S = self.cfg.crop_size
            return np.broadcast_to(rng.integers(0, 256, 3).astype(np.uint8), (S, S, 3)).copy()
        if self.scenes is not None and rng.random() < self.cfg.scene_backgrounds:
            scene = self.scenes[rng.integers(len(self.scenes))]
            S = self.cfg.crop_size
            y0, x0 = (int(v) for v in rng.integers(0, scene.shape[0] - S + 1, 2))
            bg = scene[y0:y0 + S, x0:x0 + S]
            if rng.random() < 0.5:
                bg = bg[:, ::-1]
            return np.ascontiguousarray(bg)
        bg = self.backgrounds[rng.integers(len(self.backgrounds))]
        if rng.random() < 0.5:
            bg = bg[:, ::-1]
        if rng.random() < 0.5:
            bg = bg[::-1]
        bg = _roll2(bg, *(int(v) for v in rng.integers(0, bg.shape[0], 2)))
        shift = rng.integers(-30, 31, 3)
        # saturating uint8 arithmetic (cv2) instead of an int16 round trip
        up = np.maximum(shift, 0).astype(np.float64).tolist() + [0.0]
        down = np.maximum(-shift, 0).astype(np.float64).tolist() + [0.0]
        return cv2.subtract(cv2.add(np.ascontiguousarray(bg), tuple(up)), tuple(down))

    def _poses(self, rngs: list[np.random.Generator]):
        """Poses for a list of samples, with their crop transforms computed in one batched call."""
        from sc6d_jax import geometry as G

        cfg = self.cfg
        poses = [sample_pose(r, self.obj_ids, self.vertices, self.diameters, cfg.distance, box_shift=cfg.box_shift,
                             box_scale=cfg.box_scale, placement=cfg.placement, obj_p=self.obj_p) for r in rngs]
        centers = np.array([[p.box[0] + p.box[2] / 2, p.box[1] + p.box[3] / 2] for p in poses])
        sides = np.array([cfg.pad * max(p.box[2], p.box[3]) for p in poses])
        T = np.asarray(G.crop_transform(centers, sides, cfg.crop_size), np.float64)
        return poses, centers, sides, T

    def _visible_crop(self, p, objects, prims) -> tuple[np.ndarray, float, np.ndarray] | None:
        """(center, side, T) of the crop cut from the target's visible box, jittered as ``p.box``
        jitters ``p.box_obj``; None when too little of the target is visible. The visible box is
        measured on the masks of a render through the (unjittered) amodal box's crop."""
        from sc6d_jax import geometry as G
        from sc6d_jax.bop import bbox_extent

        cfg, S = self.cfg, self.cfg.crop_size
        xo, yo, wo, ho = (float(v) for v in p.box_obj)
        c0 = np.array([xo + wo / 2, yo + ho / 2])
        T0 = np.asarray(G.crop_transform(c0, cfg.pad * max(wo, ho), self.render_size), np.float64)
        mask = self.renderer.render(objects, T0 @ p.K, primitives=prims, depth=False, shadows=False).mask_visib[0]
        ys, xs = np.nonzero(mask)
        if len(xs) < MIN_VISIBLE_PX * cfg.supersample**2:
            return None
        r, tx, ty = T0[0, 0], T0[0, 2], T0[1, 2]
        # the extent of the visible pixels, as the estimator takes a ground-truth bbox_visib
        x, y, w, h = bbox_extent((xs.min(), ys.min(), xs.max() - xs.min(), ys.max() - ys.min()))
        u0, u1 = (x - tx) / r, (x + w - tx) / r
        v0, v1 = (y - ty) / r, (y + h - ty) / r
        wv, hv = max(u1 - u0, 1.0), max(v1 - v0, 1.0)
        # the jitter that took box_obj to box, applied to the visible box (the same draws)
        xj, yj, wj, hj = (float(v) for v in p.box)
        scale = wj / wo
        dx = (xj + wj / 2 - c0[0]) / wo
        dy = (yj + hj / 2 - c0[1]) / ho
        center = np.array([(u0 + u1) / 2 + dx * wv, (v0 + v1) / 2 + dy * hv])
        side = cfg.pad * scale * max(wv, hv)
        return center, side, np.asarray(G.crop_transform(center, side, S), np.float64)

    def _render(self, rng: np.random.Generator, p, side: float, T: np.ndarray, difficulty: float = 1.0):
        """Render one crop through K_B = T K with occluders, lights and a background.

        Returns (rgb, visible mask, depth or None, center, side, T) -- the crop box changes
        only with ``box_source="visible"`` and occluders -- or None when too little of the
        target is visible."""
        from sc6d_jax.render import Light, Primitive

        from sc6d_jax.geometry import area_downsample, supersample_transform

        cfg, S, ss = self.cfg, self.cfg.crop_size, self.cfg.supersample
        K_B = T @ p.K
        center = None
        objects = [(p.obj_id, p.R, p.t)]
        prims = []
        table_slot = None  # the table's index in prims (tabletop)
        occluded = False
        if rng.random() < cfg.occlusion * difficulty:  # occluders between the camera and the target
            occluded = True
            for _ in range(rng.integers(1, 3)):
                depth = p.t[2] * rng.uniform(0.55, 0.9)
                off = rng.uniform(-0.45, 0.45, 2) * side / p.K[0, 0] * depth
                c = p.t * depth / p.t[2] + np.array([off[0], off[1], 0.0])
                if rng.random() < 0.5:
                    oid = int(self.all_ids[rng.integers(len(self.all_ids))])
                    if sum(o[0] == oid for o in objects) < 2:
                        objects.append((oid, random_rotation(rng), c))
                else:
                    size = rng.uniform(0.08, 0.3, 3) * self.diameters[p.obj_id]
                    prims.append(
                        Primitive(str(rng.choice(DISTRACTOR_SHAPES)), size,
                                  rng.uniform(0, 1, 3), random_rotation(rng), c)
                    )
        if cfg.tabletop > 0 and rng.random() < cfg.tabletop * difficulty:  # no draw when off
            # the target stands on a table among other models and shapes, all in this one render
            table, around, shapes = tabletop_around(rng, p.obj_id, p.R, p.t, self.vertices, self.radii,
                                                    self.diameters, self.all_ids, self.renderer.max_instances,
                                                    self.renderer.near, spacing=cfg.tabletop_spacing)
            # neighbours in contact hide the target as occluders do: cut from its visible box
            occluded = occluded or (cfg.tabletop_spacing is not None and bool(around or shapes))
            for o in around:
                if sum(q[0] == o[0] for q in objects) < self.renderer.max_instances:
                    objects.append(o)
            table_slot = len(prims)
            prims += [table, *shapes]
        elif cfg.distractors and rng.random() < difficulty:  # clutter behind the target
            d_t = self.diameters[p.obj_id]
            for _ in range(rng.integers(1, cfg.distractors + 1)):
                oid = int(self.all_ids[rng.integers(len(self.all_ids))])
                # centres farther apart along z than the two bounding spheres' radii: every
                # point of the distractor lies behind every point of the target
                depth = p.t[2] + 0.5 * (d_t + self.diameters[oid]) * rng.uniform(1.0, 2.5)
                off = rng.uniform(-0.6, 0.6, 2) * side / p.K[0, 0] * depth
                c = p.t * depth / p.t[2] + np.array([off[0], off[1], 0.0])
                R_d = random_rotation(rng)
                if sum(o[0] == oid for o in objects) < self.renderer.max_instances:
                    objects.append((oid, R_d, c))
        if cfg.materials:
            for oid in dict.fromkeys(o[0] for o in objects):
                self.renderer.set_material(oid, specular=rng.uniform(0.0, 0.8), shininess=rng.uniform(0.0, 1.0))
        lights = [
            Light(direction=rng.normal(size=3) + np.array([0, 0, 1.5]), diffuse=rng.uniform(0.2, 0.7),
                  specular=rng.uniform(0.0, 0.4))
            for _ in range(rng.integers(1, 3))
        ]
        region = None
        if cfg.shadows and rng.random() < cfg.shadows:  # no draw when off: earlier streams unchanged
            # a key light from any side (uniform on the cap within SHADOW_LIGHT_ANGLE of the
            # optical axis): one from behind the camera hides the shadows behind the objects
            cos_th = rng.uniform(np.cos(np.radians(SHADOW_LIGHT_ANGLE)), 1.0)
            ph = rng.uniform(0.0, 2 * np.pi)
            sin_th = np.sqrt(1.0 - cos_th**2)
            lights[0] = dataclasses.replace(lights[0], castshadow=True,
                                            direction=(sin_th * np.cos(ph), sin_th * np.sin(ph), cos_th))
            region = (p.t, SHADOW_REACH * self.diameters[p.obj_id])
        self.renderer.set_lights(lights, headlight=(rng.uniform(0.1, 0.4), rng.uniform(0.1, 0.5)),
                                 shadow_region=region)
        background = self.background(rng, difficulty)
        if cfg.box_source == "visible" and occluded:
            got = self._visible_crop(p, objects, prims)
            if got is None:
                return None
            center, side, T = got
            K_B = T @ p.K
        if ss > 1:  # render ss x ss samples per crop pixel; the background's pixels as blocks
            K_B = supersample_transform(T, ss) @ p.K
            background = np.repeat(np.repeat(background, ss, axis=0), ss, axis=1)
        out = self.renderer.render(objects, K_B, primitives=prims, background=background, depth=cfg.dense)
        mask = area_downsample(out.mask_visib[0], ss)
        if cfg.image_border:  # the target is not seen beyond the image's edges
            mask = mask & inside_image(T, S)
        n_vis = int(mask.sum())
        if n_vis < MIN_VISIBLE_PX or n_vis < MIN_VISIBLE_FRACTION * S * S:
            return None
        rgb = out.rgb
        if table_slot is not None:  # the table's shade times a texture (the crop's background)
            rgb = textured_table(rgb, out.instance == len(objects) + table_slot, background)
        if cfg.object_gain is not None:  # the objects' exposure relative to their surroundings
            lo, hi = cfg.object_gain
            gain = float(np.exp(rng.uniform(np.log(lo), np.log(hi))))
            fg = out.instance >= 0
            rgb = rgb.copy()
            rgb[fg] = np.clip(rgb[fg].astype(np.float32) * gain + 0.5, 0, 255).astype(np.uint8)
        if cfg.object_colour is not None:  # each object's white balance against its surroundings
            rgb = object_colour(rng, rgb, out.instance, cfg.object_colour)
        if cfg.object_contrast is not None:  # each object's shading contrast, about its mean colour
            rgb = object_contrast(rng, rgb, out.instance, cfg.object_contrast)
        rgb = area_downsample(rgb, ss)
        if cfg.resample or cfg.sensor:
            rgb = camera_effects(rng, rgb, side, resample=cfg.resample, sensor=cfg.sensor)
        return rgb, mask, out.depth, center, side, T

    def batch(self, b: int) -> dict[str, np.ndarray]:
        """Batch ``b``: sample j draws from default_rng([seed, b, j]) only. Labels (translation
        code, allocentric rotation, PE maps) are computed for the whole batch in batched calls."""
        from sc6d_jax import geometry as G

        cfg, B, S = self.cfg, self.cfg.batch_size, self.cfg.crop_size
        rngs = [np.random.default_rng([cfg.seed, b, j]) for j in range(B)]
        poses, centers, sides, T = self._poses(rngs)
        rgbs, masks, depths = [None] * B, [None] * B, [None] * B
        for j in range(B):
            for attempt in range(50):
                got = self._render(rngs[j], poses[j], sides[j], T[j], self.difficulty(b))
                if got is not None:
                    rgbs[j], masks[j], depths[j], c_j, sides[j], T[j] = got
                    if c_j is not None:  # cut from the visible box
                        centers[j] = c_j
                    break
                p2, c2, s2, T2 = self._poses([rngs[j]])  # resample this one (rare)
                poses[j], centers[j], sides[j], T[j] = p2[0], c2[0], s2[0], T2[0]
            else:
                raise RuntimeError("could not sample a visible crop in 50 attempts (objects too small for the crop?)")
        K = np.stack([p.K for p in poses])
        R = np.stack([p.R for p in poses])
        t = np.stack([p.t for p in poses])
        delta_xy, delta_z = (np.asarray(a, np.float64) for a in G.encode_translation(t, K, centers, sides, S))
        R_allo = np.asarray(G.egocentric_to_allocentric(R, t), np.float64)
        pe = np.array(G.pe_map(K, T, S), np.float32)  # writable: pe_turns turns it per crop
        rgb, mask = np.stack(rgbs), np.stack(masks)
        dense = dense_w = None
        if cfg.dense:
            dense, dense_w = dense_targets(
                np.stack(depths), mask, T @ K, R, R_allo, t, np.array([self.diameters[p.obj_id] for p in poses]),
                xyz=cfg.dense_xyz,
            )
        view = clean_view(rgb, mask, cfg.view) if cfg.view else None  # before the colour augmentation
        outside = ~inside_image(T, S) if cfg.image_border else None
        if outside is not None and not cfg.augment:
            rgb[outside] = 0
        if cfg.augment:
            for j in range(B):
                rgb[j] = colour_augment(rngs[j], rgb[j], p=cfg.colour_p)
                if outside is not None:  # black as a crop cut from an image is, after any colour change
                    rgb[j][outside[j]] = 0
                k = int(rngs[j].integers(4))
                if k:  # turn the crop by k*90 deg clockwise == Rz(+90k) about the optical axis
                    rgb[j] = np.rot90(rgb[j], -k)
                    mask[j] = np.rot90(mask[j], -k)
                    if view is not None:
                        view[j] = np.rot90(view[j], -k)
                    c, s_ = [(1, 0), (0, 1), (-1, 0), (0, -1)][k]
                    Rz = np.array([[c, -s_, 0], [s_, c, 0], [0, 0, 1]], np.float64)
                    R_allo[j] = Rz @ R_allo[j]
                    delta_xy[j] = Rz[:2, :2] @ delta_xy[j]
                    if cfg.pe_turns:
                        pe[j] = G.turn_pe(pe[j], k)
                    if dense is not None:
                        dense[j] = np.rot90(dense[j], -k)
                        dense[j, ..., :3] = dense[j, ..., :3] @ Rz.T.astype(np.float32)
                        dense_w[j] = np.rot90(dense_w[j], -k)
        extra = {} if dense is None else {"dense": dense, "dense_w": dense_w}
        if view is not None:
            extra["view"] = view
        return dict(
            **extra,
            rgb=rgb, pe=pe, mask_visib=mask.astype(np.uint8), R_allo=R_allo.astype(np.float32),
            R=R.astype(np.float32), t=t.astype(np.float32), K=K.astype(np.float32),
            K_B=(T @ K).astype(np.float32), delta_xy=delta_xy.astype(np.float32),
            delta_z=delta_z.astype(np.float32),
            obj_idx=np.array([self.obj_ids.index(p.obj_id) for p in poses], np.int32),
            obj_id=np.array([p.obj_id for p in poses], np.int32),
            center=centers.astype(np.float32), side=sides.astype(np.float32),
            difficulty=np.full((B,), self.difficulty(b), np.float32),
        )


_WORKER: _Worker | None = None
_RING: "_Ring | None" = None


class _Ring:
    """``n`` slots of shared memory, each holding one batch's image-sized arrays."""

    def __init__(self, cfg: StreamConfig, n: int, name: str | None = None) -> None:
        self.layout, self.slot_bytes = self.slot_layout(cfg)
        self.n = n
        if name is None:
            self.shm = shared_memory.SharedMemory(create=True, size=n * self.slot_bytes)
            self.owner = True
        else:
            self.shm = shared_memory.SharedMemory(name=name)
            self.owner = False

    @staticmethod
    def slot_layout(cfg: StreamConfig) -> tuple[list[tuple[str, tuple[int, ...], np.dtype, int]], int]:
        """[(key, shape, dtype, byte offset in a slot)] and the slot's size (64-byte aligned)."""
        B, S = cfg.batch_size, cfg.crop_size
        layout, off = [], 0
        for key, shape, dt in (
            ("rgb", (B, S, S, 3), np.dtype(np.uint8)),
            ("pe", (B, S, S, 2), np.dtype(np.float32)),
            ("mask_visib", (B, S, S), np.dtype(np.uint8)),
        ):
            layout.append((key, shape, dt, off))
            off += -(-int(np.prod(shape)) * dt.itemsize // 64) * 64
        return layout, off

    @classmethod
    def fits(cls, cfg: StreamConfig, n: int) -> bool:
        """Whether n slots fit in half the free shared memory (Docker's /dev/shm is 64 MB by
        default; writing past a full tmpfs would kill the worker with SIGBUS)."""
        try:
            st = os.statvfs("/dev/shm")
        except OSError:  # no /dev/shm (not Linux): let SharedMemory decide
            return True
        return n * cls.slot_layout(cfg)[1] <= st.f_bavail * st.f_frsize // 2

    def views(self, slot: int) -> dict[str, np.ndarray]:
        base = slot * self.slot_bytes
        return {k: np.ndarray(shape, dt, buffer=self.shm.buf, offset=base + o) for k, shape, dt, o in self.layout}

    def close(self) -> None:
        self.shm.close()
        if self.owner:
            self.shm.unlink()


def _exit_with_parent(parent: int, every: float = 1.0) -> None:
    """End this worker once its parent is gone (a SIGKILLed training run would otherwise leave
    its workers, their memory and the shared-memory ring behind)."""
    while True:
        time.sleep(every)
        if os.getppid() != parent:
            os._exit(0)


def _init_worker(cfg: StreamConfig, ring: tuple[str, int] | None = None) -> None:
    global _WORKER, _RING
    threading.Thread(target=_exit_with_parent, args=(os.getppid(),), daemon=True).start()
    os.environ.setdefault("LP_NUM_THREADS", "1")  # one Mesa rasteriser thread per process
    os.environ.setdefault("MUJOCO_GL", "egl")
    os.environ.setdefault("JAX_PLATFORMS", "cpu")
    cv2.setNumThreads(1)  # one core per worker: OpenCV's own thread pool only oversubscribes
    try:  # below the training process: the workers fill the cores' idle time between XLA's ops
        os.nice(WORKER_NICENESS)
    except OSError:  # pragma: no cover - not permitted on some systems
        pass
    _WORKER = _Worker(cfg)
    if ring is not None:
        _RING = _Ring(cfg, ring[1], name=ring[0])


def _render_batch(b: int) -> dict[str, np.ndarray]:
    assert _WORKER is not None
    return _WORKER.batch(b)


def _render_batch_to_slot(b: int, slot: int) -> dict[str, np.ndarray]:
    """Batch ``b`` with its image-sized arrays written to ring slot ``slot`` (and left out)."""
    assert _WORKER is not None and _RING is not None
    out = _WORKER.batch(b)
    for k, view in _RING.views(slot).items():
        view[...] = out.pop(k)
    return out


class CropStream:
    """Iterator over training batches (dicts of numpy arrays); see the module docstring.

    Keys: rgb uint8 (B,S,S,3), pe float32 (B,S,S,2), mask_visib uint8 (B,S,S), R_allo, R (B,3,3),
    t (B,3) mm, K and K_B (B,3,3), delta_xy (B,2), delta_z (B,), obj_idx / obj_id int32 (B,),
    center (B,2) and side (B,) of the crop box in the image, difficulty (B,) the curriculum's
    difficulty of the batch (1 = full); with dense=True also dense (B,S/4,S/4,4), dense_w (B,S/4,S/4);
    with view=V also view uint8 (B,V,V,3).
    """

    def __init__(self, cfg: StreamConfig, start_batch: int = 0) -> None:
        self.cfg = cfg
        self.obj_ids = resolve_obj_ids(cfg)
        self._next = int(start_batch)
        self._pending: deque = deque()
        self._pool: cf.ProcessPoolExecutor | None = None
        self._local: _Worker | None = None
        self._ring: _Ring | None = None
        if cfg.workers == 0:
            self._local = _Worker(cfg)
        else:
            # one slot per batch in flight, plus the one being copied out; through the result
            # pipe when the shared memory is too small for the ring
            n = 2 * cfg.workers + 1
            self._ring = _Ring(cfg, n) if _Ring.fits(cfg, n) else None
            self._restarts = 0  # worker-pool restarts since the last batch that arrived
            self._start_pool()

    def _start_pool(self) -> None:
        ring = None if self._ring is None else (self._ring.shm.name, self._ring.n)
        self._pool = cf.ProcessPoolExecutor(
            self.cfg.workers, mp_context=mp.get_context("spawn"), initializer=_init_worker,
            initargs=(self.cfg, ring),
        )

    def _restart_pool(self, err: BaseException) -> None:
        """A worker died (a crash in the renderer or the GL driver, or a kill): start a fresh pool
        and render the batches in flight again. Batch b is a pure function of (seed, b), so the
        stream goes on exactly as it would have; a worker that dies again before any batch
        arrives, MAX_WORKER_RESTARTS times, ends the stream with the error."""
        self._restarts += 1
        if self._restarts > MAX_WORKER_RESTARTS:
            raise RuntimeError(
                f"crop stream: the render workers died {MAX_WORKER_RESTARTS + 1} times in a row at batch "
                f"{self._next} ({err})") from err
        print(f"crop stream: a render worker died at batch {self._next} ({err}); restarting the workers "
              f"({self._restarts}/{MAX_WORKER_RESTARTS}) and rendering the batches in flight again",
              file=sys.stderr, flush=True)
        assert self._pool is not None
        self._pool.shutdown(wait=False, cancel_futures=True)
        self._pending.clear()
        self._start_pool()

    def batch(self, b: int) -> dict[str, np.ndarray]:
        """Batch ``b`` computed now (in this process or one worker), independent of the iterator."""
        if self._local is not None:
            return self._local.batch(b)
        assert self._pool is not None
        return self._pool.submit(_render_batch, b).result()

    def __iter__(self) -> Iterator[dict[str, np.ndarray]]:
        return self

    def __next__(self) -> dict[str, np.ndarray]:
        if self._local is not None:
            out = self._local.batch(self._next)
            self._next += 1
            return out
        assert self._pool is not None
        ring = self._ring
        try:
            # a worker that died while none of its batches was in flight breaks the pool too:
            # then the submit, not the result, is where the stream hears of it
            while len(self._pending) < 2 * self.cfg.workers:
                b = self._next + len(self._pending)
                if ring is None:
                    self._pending.append(self._pool.submit(_render_batch, b))
                else:
                    self._pending.append(self._pool.submit(_render_batch_to_slot, b, b % ring.n))
            out = self._pending.popleft().result()
        except cf.process.BrokenProcessPool as err:
            self._restart_pool(err)
            return self.__next__()
        self._restarts = 0
        if ring is not None:
            # the in-flight batches are consecutive, so slot next % n is not written again
            # before the next call (n = in flight + 1); the arrays are copied out of it here
            out.update({k: v.copy() for k, v in ring.views(self._next % ring.n).items()})
        self._next += 1
        return out

    def close(self) -> None:
        if self._pool is not None:
            for f in self._pending:
                f.cancel()
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
        if self._ring is not None:
            self._ring.close()
            self._ring = None
        if self._local is not None:
            self._local.renderer.close()
            self._local = None

    def __enter__(self) -> "CropStream":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:  # pragma: no cover
        try:
            self.close()
        except Exception:
            pass


def delta_z_range(
    cfg: StreamConfig, n: int = 4000, margin: float = 0.1, focal_ref: float | None = None
) -> tuple[float, float]:
    """(d_lo, d_hi) of delta_z = t_z * s_B / S over the training pose distribution, widened by
    ``margin`` on each side. Poses only (no rendering), deterministic in ``cfg.seed``.

    focal_ref: the range of the focal-normalised code delta_z * focal_ref / sqrt(fx fy)
    instead (``sc6d_jax.model.LossConfig.z_norm = "focal"``).

    With ``box_source="visible"`` an occluded target's crop is cut from its visible box, which
    can be much smaller than the amodal box the poses give: the low end is lowered to
    ``VISIBLE_BOX_MIN * d_lo`` (a target 10 % visible keeps a visible box of about a third of
    its amodal one)."""
    from sc6d_jax.bop import load_models_info, model_path
    from sc6d_jax.render import load_mesh

    obj_ids = resolve_obj_ids(cfg)
    infos = load_models_info(cfg.models_dir)
    verts = {i: hull_vertices(load_mesh(model_path(cfg.models_dir, i)).vertices) for i in obj_ids}
    diam = {i: infos[i].diameter for i in obj_ids}
    rng = np.random.default_rng([cfg.seed, 2**31 - 1])
    dz = []
    for _ in range(n):
        p = sample_pose(rng, obj_ids, verts, diam, cfg.distance, box_shift=cfg.box_shift, box_scale=cfg.box_scale,
                        placement=cfg.placement)
        side = cfg.pad * max(p.box[2], p.box[3])
        d = p.t[2] * side / cfg.crop_size
        if focal_ref is not None:
            d *= focal_ref / np.sqrt(p.K[0, 0] * p.K[1, 1])
        dz.append(d)
    lo, hi = float(np.min(dz)), float(np.max(dz))
    span = hi - lo
    lo = max(lo - margin * span, 1e-3)
    if cfg.box_source == "visible":
        lo *= VISIBLE_BOX_MIN
    return lo, hi + margin * span
