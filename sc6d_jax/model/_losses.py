"""SC6D training losses: InfoNCE over sampled rotations, z (focal / CE / L1), delta_xy L1, mask BCE.

Every ablation switch of the paper's Table 3 is a LossConfig field: z regression vs
classification (A0/A1), focal loss (A2), expectation decode (A3; decode only, the training loss
is the same as classification), PE map (A4; ModelConfig.use_pe), IPDF head (ModelConfig.rot_head).
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp

from sc6d_jax.geometry import (
    rebase_negatives,
    rot_x,
    rot_y,
    rot_z,
    sample_rotation_deltas,
    z_bin_centers,
    z_bin_label,
)

from ._config import ModelConfig
from ._network import apply, rot_cls_grid, vote_grid, with_rotation_priors
from ._rotation import rotation_logits, rotation_prior_output

Z_MODES = ("regression", "classification", "expectation")
Z_LOSSES = ("focal", "ce", "gauss")
Z_NORMS = ("none", "focal")
Z_BINS = ("linear", "log")
MASK_DOWNSAMPLE = ("area", "nearest")

#: Reference focal length (pixels) of the focal-normalised depth code (``LossConfig.z_norm``).
F_REF = 600.0


@dataclasses.dataclass(frozen=True)
class LossConfig:
    """Loss settings (frozen, hashable; a jit static argument).

    - z_mode: "regression" (L1 on delta_z normalised to [0, 1] over the bin range, read from
      z-head output unit 0), "classification" (argmax decode) or "expectation" (softmax
      expectation decode; paper default). Both classification modes train the same loss.
    - z_loss: "focal" (-alpha (1 - p)^gamma log p, paper), "ce" (plain cross-entropy) or
      "gauss" (cross-entropy against a Gaussian-smoothed label of ``z_label_sigma`` bins around
      the exact, fractional bin position: neighbouring bins are nearly right, so every bin
      near the target gets a gradient instead of one bin in 1000).
    - z_norm: "none" (paper: the depth code is delta_z = t_z s_B / S) or "focal" (the code is
      delta_z * F_REF / f with f = sqrt(fx fy) of the image K). delta_z depends on the focal
      length, which a crop does not show (the PE map gives the crop's angular size s_B / f,
      not f); with the training stream's random focal lengths (520-680 px) that is a
      +-13 % label noise no network can remove. The focal-normalised code is t_z times the
      crop's angular size per pixel, a property of what the crop shows.
    - z_bins: "linear" (paper: bins evenly spaced in the code) or "log" (evenly spaced in
      log(code): a constant relative depth resolution, and the regression mode regresses
      log(code)).
    - z_label_sigma: width in bins of the "gauss" label.
    - w_z_l1: weight of an extra L1 loss on the relative error of the decoded depth
      (|log(decoded / true)|, the expectation of the bins) next to the bin loss (0 = off).
    - focal_alpha 0.5, focal_gamma 2.
    - tau: InfoNCE temperature (0.1). n_negatives: Q sampled rotations (5000).
    - rebase_negatives: True (authors): the Q Fibonacci-viewpoint + random-roll deltas are
      left-multiplied onto each sample's ground truth, so every sample has its own Q
      candidates (the SO(3) encoder runs B*(Q+1) times). False: the Q deltas are used as
      they are, one candidate set for the whole batch (encoder runs Q + B times; much
      cheaper on a CPU), plus each sample's ground truth.
    - n_local_negatives: M extra negatives per sample near its ground truth (R_gt turned by a
      random axis and an angle uniform in [local_min_deg, local_max_deg]): hard negatives
      that teach fine rotation once the coarse shape is learnt (the shared set is ~14 degrees
      apart at Q = 5000). 0 = off (paper).
    - turn_negatives: 9 more negatives per sample, its ground truth turned by a quarter, half
      and three-quarter turn about each of the object's own axes (:func:`axis_turns`): the poses a
      nearly symmetric object is confused with (a mug upside down, a dumbbell turned about its
      bar), which random negatives almost never hit. No symmetry labels: for an exactly
      symmetric object the turned pose looks the same and only costs a constant floor of the
      loss (False = off, paper).
    - n_axis_negatives: M more negatives per sample on the rings of the quarter turns: its
      ground truth turned about one of the object's own axes (drawn per negative) by an angle
      uniform in [axis_min_deg, 360 - axis_min_deg] (:func:`axis_ring_deltas`): the angle about a
      thin object's axis at every value, not only at the quarter turns. 0 = off (paper).
    - w_rot_readout: weight of an L2 loss between the model's rotation readout
      (``ModelConfig.rot_readout``: a linear map of the rotation embedding) and the first two
      columns of the allocentric ground truth. InfoNCE has a fixed point where the SO(3)
      encoder gives a whole ring of turns about an object axis one embedding and the image
      embedding ignores the angle (each side's gradient along the ring vanishes while the other
      is flat): a nearly symmetric object (a dumbbell about its bar) stays there. The readout
      asks the image embedding for the angle directly. No symmetry labels: for an exactly
      symmetric object the target is ambiguous and the readout learns its mean (0 = off, paper).
    - w_rot_cls: weight of the cross-entropy of the model's rotation classifier
      (``ModelConfig.rot_cls``) against the grid rotation nearest to the allocentric ground truth
      (0 = off, paper).
    - z_rot_noise_deg: with ``ModelConfig.z_rot`` (or ``xy_rot``), the rotation the priors are fed in
      training is the ground truth turned about a random axis by an angle uniform in
      [0, z_rot_noise_deg] (0 = the ground truth itself): inference feeds the matched rotation,
      which is off by some degrees.
    - z_rot_separate: with ``ModelConfig.z_rot``, train the prior and the image's z head each
      on its own depth loss (the image head exactly as without the prior) instead of their sum
      of logits; inference still adds the two (a product of the two distributions). Joint
      training lets the image head lean on the ground-truth rotation it never has at inference.
    - per_sample_negatives: draw an independent random roll per sample (vmapped over the
      batch) instead of one set of deltas shared by the batch.
    - w_rot 1, w_xy 10, w_z 1, w_mask 1: loss weights.
    - teacher_gate: with ``ModelConfig.mask_gate``, gate the features of a sample by its
      ground-truth visible mask instead of the predicted one with probability 1 - d, where d is
      the curriculum's difficulty of its batch (``batch['difficulty']``, 1 = full): while the
      mask head is still poor, the pose heads see the object's features without the clutter.
    - w_dense: weight of the dense geometry loss (needs ``ModelConfig.dense_head`` and the
      stream's ``dense`` / ``dense_w`` targets): L1 of the normal and the relative depth over
      the visible blocks, weighted by their visible fraction (0 = off, paper).
    - w_xy_vote: weight of the L1 of each decoder cell's vote (``ModelConfig.xy_vote``: its
      offset to the projected centre, crop-side units) against the ground truth's, averaged over
      the cells weighted by the visible mask's fraction in each (0 = off; the aggregated
      delta_xy keeps its own ``w_xy`` loss).
    - w_dense_xyz: weight of the L1 of the object-frame surface points (``ModelConfig.dense_xyz``
      and the stream's ``dense_xyz`` targets), over the same blocks (0 = off).
    - w_view: weight of the clean-view reconstruction (needs ``ModelConfig.view_head`` and the
      stream's ``view``): squared error per pixel of ``out["view"]`` against ``view / 255``,
      averaged over the ``view_top`` fraction of each crop's pixels with the largest errors
      (the Augmented Autoencoder's bootstrapped L2, factor 4 = 0.25: the object's small parts
      count, not only the black around it). 0 = off.
    - view_until: the fraction of the run's steps during which the view loss counts (1 = all;
      0.5 = the first half, then its weight is 0): the training step passes the weight in the
      batch as ``view_weight``.
    - mask_downsample: "area" (default: the S x S visible mask averaged over 4x4 blocks, a
      soft target in [0, 1]) or "nearest" (every 4th pixel, offset 2: a binary target).
    """

    z_mode: str = "expectation"
    z_loss: str = "focal"
    focal_alpha: float = 0.5
    focal_gamma: float = 2.0
    tau: float = 0.1
    n_negatives: int = 5000
    rebase_negatives: bool = True
    per_sample_negatives: bool = False
    w_rot: float = 1.0
    w_xy: float = 10.0
    w_xy_vote: float = 0.0
    w_z: float = 1.0
    w_mask: float = 1.0
    mask_downsample: str = "area"
    z_norm: str = "none"
    z_bins: str = "linear"
    z_label_sigma: float = 1.0
    w_z_l1: float = 0.0
    n_local_negatives: int = 0
    local_min_deg: float = 2.0
    local_max_deg: float = 30.0
    w_dense: float = 0.0
    w_dense_xyz: float = 0.0
    teacher_gate: bool = False
    turn_negatives: bool = False
    n_axis_negatives: int = 0
    axis_min_deg: float = 30.0
    w_rot_readout: float = 0.0
    w_rot_cls: float = 0.0
    w_view: float = 0.0
    view_top: float = 0.25
    view_until: float = 1.0
    z_rot_noise_deg: float = 0.0
    z_rot_separate: bool = False

    def __post_init__(self) -> None:
        if self.z_mode not in Z_MODES:
            raise ValueError(f"z_mode must be one of {Z_MODES}, got {self.z_mode!r}")
        if self.z_loss not in Z_LOSSES:
            raise ValueError(f"z_loss must be one of {Z_LOSSES}, got {self.z_loss!r}")
        if self.z_norm not in Z_NORMS:
            raise ValueError(f"z_norm must be one of {Z_NORMS}, got {self.z_norm!r}")
        if self.z_bins not in Z_BINS:
            raise ValueError(f"z_bins must be one of {Z_BINS}, got {self.z_bins!r}")
        if not self.z_label_sigma > 0:
            raise ValueError(f"z_label_sigma must be > 0, got {self.z_label_sigma}")
        if not isinstance(self.n_local_negatives, int) or self.n_local_negatives < 0:
            raise ValueError(f"n_local_negatives must be a non-negative int, got {self.n_local_negatives!r}")
        if not 0 <= self.local_min_deg <= self.local_max_deg <= 180:
            raise ValueError(
                f"need 0 <= local_min_deg <= local_max_deg <= 180, got {self.local_min_deg}, {self.local_max_deg}"
            )
        if not isinstance(self.n_axis_negatives, int) or self.n_axis_negatives < 0:
            raise ValueError(f"n_axis_negatives must be a non-negative int, got {self.n_axis_negatives!r}")
        if not 0 < self.axis_min_deg < 180:
            raise ValueError(f"axis_min_deg must be in (0, 180), got {self.axis_min_deg}")
        for name in ("turn_negatives", "z_rot_separate"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name} must be true or false, got {getattr(self, name)!r}")
        if self.mask_downsample not in MASK_DOWNSAMPLE:
            raise ValueError(f"mask_downsample must be one of {MASK_DOWNSAMPLE}, got {self.mask_downsample!r}")
        if not self.tau > 0:
            raise ValueError(f"tau must be > 0, got {self.tau}")
        if not isinstance(self.n_negatives, int) or self.n_negatives < 1:
            raise ValueError(f"n_negatives must be a positive int, got {self.n_negatives!r}")
        if not 0.0 < self.view_until <= 1.0:
            raise ValueError(f"view_until must be a fraction of the run in (0, 1], got {self.view_until!r}")
        if not 0.0 < self.view_top <= 1.0:
            raise ValueError(f"view_top must be a fraction in (0, 1], got {self.view_top!r}")
        for name in ("w_rot", "w_xy", "w_xy_vote", "w_z", "w_mask", "w_z_l1", "w_dense", "w_dense_xyz", "w_rot_readout", "w_rot_cls",
                     "w_view", "focal_alpha", "focal_gamma", "z_rot_noise_deg"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")


# ----------------------------------------------------------------------------- loss terms


def info_nce(logits: jax.Array) -> jax.Array:
    """Mean InfoNCE over the batch with the positive at index 0: logsumexp(l) - l[:, 0]."""
    return jnp.mean(jax.nn.logsumexp(logits, axis=-1) - logits[:, 0])


def focal_loss(logits: jax.Array, labels: jax.Array, alpha: float = 0.5, gamma: float = 2.0) -> jax.Array:
    """Mean over the batch of -alpha (1 - p)^gamma log p, p = softmax(logits)[label]."""
    logp = jnp.take_along_axis(jax.nn.log_softmax(logits, axis=-1), labels[:, None], axis=-1)[:, 0]
    p = jnp.exp(logp)
    return jnp.mean(-alpha * (1.0 - p) ** gamma * logp)


def cross_entropy(logits: jax.Array, labels: jax.Array) -> jax.Array:
    """Mean softmax cross-entropy with integer labels."""
    logp = jnp.take_along_axis(jax.nn.log_softmax(logits, axis=-1), labels[:, None], axis=-1)[:, 0]
    return -jnp.mean(logp)


def vote_loss(votes: jax.Array, delta_xy: jax.Array, mask: jax.Array) -> jax.Array:
    """L1 of the cells' offsets ``votes[..., :2]`` (B,n,n,3) against the ground truth's (the
    projected centre ``delta_xy`` (B,2) minus each cell's centre, ``vote_grid``), averaged over the
    cells weighted by ``mask`` (B,n,n), the visible fraction of each; a crop without visible cells
    counts 0."""
    want = delta_xy[:, None, None, :] - vote_grid(votes.shape[1])[None]
    err = jnp.sum(jnp.abs(votes[..., :2].astype(jnp.float32) - want), axis=-1)
    m = mask.astype(jnp.float32)
    return jnp.mean(jnp.sum(err * m, axis=(1, 2)) / jnp.maximum(jnp.sum(m, axis=(1, 2)), 1e-6))


def bce_with_logits(logits: jax.Array, targets: jax.Array) -> jax.Array:
    """Mean binary cross-entropy on logits with (soft) targets in [0, 1], numerically stable."""
    return jnp.mean(jnp.maximum(logits, 0) - logits * targets + jnp.log1p(jnp.exp(-jnp.abs(logits))))


def downsample_mask(mask: jax.Array, factor: int = 4, mode: str = "area") -> jax.Array:
    """(B,S,S) mask (any dtype; > 0 is foreground) -> float32 (B,S/f,S/f) target.

    "area": fraction of foreground pixels in each f x f block; "nearest": the pixel at offset
    f // 2 inside each block.
    """
    m = (mask > 0).astype(jnp.float32)
    b, h, w = m.shape
    if h % factor or w % factor:
        raise ValueError(f"mask size {h}x{w} not divisible by {factor}")
    if mode == "area":
        return m.reshape(b, h // factor, factor, w // factor, factor).mean(axis=(2, 4))
    if mode == "nearest":
        return m[:, factor // 2 :: factor, factor // 2 :: factor]
    raise ValueError(f"mode must be one of {MASK_DOWNSAMPLE}, got {mode!r}")


def _z_axis(lcfg: LossConfig, z_range: tuple[float, float]) -> tuple[float, float]:
    """The bin axis ends: the code range, or its logarithm for log bins."""
    d_lo, d_hi = z_range
    if lcfg.z_bins == "log":
        return math.log(d_lo), math.log(d_hi)
    return d_lo, d_hi


def _code_scale(K: jax.Array | None, lcfg: LossConfig) -> jax.Array | float:
    """code / delta_z: 1 for z_norm="none", F_REF / sqrt(fx fy) of the image K for "focal"."""
    if lcfg.z_norm == "none":
        return 1.0
    if K is None:
        raise ValueError("z_norm='focal' needs the image intrinsics K")
    K = jnp.asarray(K, jnp.float32)
    return F_REF / jnp.sqrt(K[..., 0, 0] * K[..., 1, 1])


def z_code(delta_z: jax.Array, K: jax.Array | None, lcfg: LossConfig) -> jax.Array:
    """The depth code the z head predicts: delta_z (paper) or delta_z * F_REF / f (z_norm="focal").

    K: (B,3,3) image intrinsics (only read for z_norm="focal")."""
    return delta_z * _code_scale(K, lcfg)


def code_to_delta_z(code: jax.Array, K: jax.Array | None, lcfg: LossConfig) -> jax.Array:
    """Inverse of :func:`z_code`: the paper's delta_z = t_z s_B / S from a decoded code."""
    return code / _code_scale(K, lcfg)


def predict_z(out: dict, lcfg: LossConfig, z_range: tuple[float, float]) -> jax.Array:
    """Decode the depth code (B,) from a forward pass according to lcfg.z_mode and z_bins.

    The code is delta_z for z_norm="none"; use :func:`code_to_delta_z` (or :func:`decode_delta_z`)
    to get delta_z for z_norm="focal"."""
    a_lo, a_hi = _z_axis(lcfg, z_range)
    zl = out["z_logits"]
    if lcfg.z_mode == "regression":
        v = a_lo + (a_hi - a_lo) * zl[..., 0]
    else:
        centers = z_bin_centers(zl.shape[-1], a_lo, a_hi, dtype=zl.dtype)
        if lcfg.z_mode == "classification":
            v = centers[jnp.argmax(zl, axis=-1)]
        else:
            v = jax.nn.softmax(zl, axis=-1) @ centers
    return jnp.exp(v) if lcfg.z_bins == "log" else v


def decode_delta_z(out: dict, lcfg: LossConfig, z_range: tuple[float, float], K: jax.Array | None) -> jax.Array:
    """delta_z = t_z s_B / S (B,) of a forward pass: :func:`predict_z` then :func:`code_to_delta_z`."""
    return code_to_delta_z(predict_z(out, lcfg, z_range), K, lcfg)


def gaussian_bin_targets(pos: jax.Array, n_bins: int, sigma: float) -> jax.Array:
    """(B, n_bins) soft labels: a Gaussian of ``sigma`` bins around the fractional bin ``pos``, normalised."""
    k = jnp.arange(n_bins, dtype=jnp.float32)
    w = jnp.exp(-0.5 * jnp.square((k[None, :] - pos[:, None]) / sigma))
    return w / jnp.sum(w, axis=-1, keepdims=True)


def local_rotation_deltas(key: jax.Array, shape: tuple[int, ...], min_deg: float, max_deg: float) -> jax.Array:
    """Rotations (*shape, 3, 3) about uniform random axes by angles uniform in [min_deg, max_deg]."""
    k1, k2 = jax.random.split(key)
    axis = jax.random.normal(k1, shape + (3,))
    axis = axis / jnp.linalg.norm(axis, axis=-1, keepdims=True)
    ang = jnp.deg2rad(jax.random.uniform(k2, shape, minval=min_deg, maxval=max_deg))
    x, y, z = axis[..., 0], axis[..., 1], axis[..., 2]
    zero = jnp.zeros_like(x)
    Kx = jnp.stack([jnp.stack([zero, -z, y], -1), jnp.stack([z, zero, -x], -1), jnp.stack([-y, x, zero], -1)], -2)
    s, c = jnp.sin(ang)[..., None, None], jnp.cos(ang)[..., None, None]
    return jnp.eye(3) + s * Kx + (1.0 - c) * (Kx @ Kx)


def axis_ring_deltas(key: jax.Array, shape: tuple[int, ...], min_deg: float) -> jax.Array:
    """Rotations (*shape, 3, 3) about the object's x, y or z axis (uniform per rotation) by an
    angle uniform in [min_deg, 360 - min_deg]; ``R_gt @ delta`` turns the ground truth in the
    object's frame (as :func:`axis_turns`, at every angle)."""
    k1, k2 = jax.random.split(key)
    which = jax.random.randint(k1, shape, 0, 3)[..., None, None]
    ang = jnp.deg2rad(jax.random.uniform(k2, shape, minval=min_deg, maxval=360.0 - min_deg))
    return jnp.where(which == 0, rot_x(ang), jnp.where(which == 1, rot_y(ang), rot_z(ang)))


def axis_turns() -> jax.Array:
    """(9, 3, 3): the quarter, half and three-quarter turns about the object's own x, y and z
    axes. R_gt @ turn is the ground truth turned in the object's frame, the pose a nearly
    symmetric object is confused with."""
    quarters = 0.5 * jnp.pi * jnp.arange(1.0, 4.0)
    return jnp.concatenate([rot_x(quarters), rot_y(quarters), rot_z(quarters)])


def candidate_logits(
    params: dict,
    mcfg: ModelConfig,
    lcfg: LossConfig,
    out: dict,
    R_gt: jax.Array,
    obj_idx: jax.Array,
    key: jax.Array,
) -> jax.Array:
    """(B, Q+1[+M][+9][+M_axis]) rotation logits with the ground truth at index 0 (negatives per lcfg)."""
    b = R_gt.shape[0]
    q = lcfg.n_negatives
    if lcfg.per_sample_negatives:
        deltas = jax.vmap(lambda k: sample_rotation_deltas(k, q))(jax.random.split(key, b))  # (B,Q,3,3)
        if lcfg.rebase_negatives:
            cands = jax.vmap(rebase_negatives)(deltas, R_gt)
        else:
            cands = jnp.concatenate([R_gt[:, None], deltas], axis=1)
        parts = [rotation_logits(params, mcfg, out, cands, obj_idx, lcfg.tau)]
    elif lcfg.rebase_negatives:
        cands = rebase_negatives(sample_rotation_deltas(key, q), R_gt)  # (B,Q+1,3,3)
        parts = [rotation_logits(params, mcfg, out, cands, obj_idx, lcfg.tau)]
    else:
        deltas = sample_rotation_deltas(key, q)  # (Q,3,3), shared by the batch
        pos = rotation_logits(params, mcfg, out, R_gt[:, None], obj_idx, lcfg.tau)  # (B,1)
        parts = [pos, rotation_logits(params, mcfg, out, deltas, obj_idx, lcfg.tau)]  # + (B,Q)
        if lcfg.n_local_negatives:
            m = lcfg.n_local_negatives
            loc = local_rotation_deltas(jax.random.fold_in(key, 1), (b, m), lcfg.local_min_deg, lcfg.local_max_deg)
            parts.append(rotation_logits(params, mcfg, out, R_gt[:, None] @ loc, obj_idx, lcfg.tau))  # (B,M)
    if lcfg.turn_negatives:
        turned = R_gt[:, None] @ axis_turns()  # (B,9,3,3)
        parts.append(rotation_logits(params, mcfg, out, turned, obj_idx, lcfg.tau))
    if lcfg.n_axis_negatives:
        ring = axis_ring_deltas(jax.random.fold_in(key, 2), (b, lcfg.n_axis_negatives), lcfg.axis_min_deg)
        parts.append(rotation_logits(params, mcfg, out, R_gt[:, None] @ ring, obj_idx, lcfg.tau))  # (B,M)
    return jnp.concatenate(parts, axis=1) if len(parts) > 1 else parts[0]


def _check_batch(mcfg: ModelConfig, batch: dict) -> None:
    need = ["rgb", "mask_visib", "R_allo", "delta_xy", "delta_z", "obj_idx"] + (["pe"] if mcfg.use_pe else [])
    missing = [k for k in need if k not in batch]
    if missing:
        raise ValueError(f"batch is missing {missing}")
    b = batch["rgb"].shape[0]
    s = mcfg.crop_size
    shapes = {"mask_visib": (b, s, s), "R_allo": (b, 3, 3), "delta_xy": (b, 2), "delta_z": (b,), "obj_idx": (b,)}
    for k, shp in shapes.items():
        if tuple(batch[k].shape) != shp:
            raise ValueError(f"batch[{k!r}] must have shape {shp}, got {tuple(batch[k].shape)}")


def loss_fn(
    params: dict,
    mcfg: ModelConfig,
    lcfg: LossConfig,
    batch: dict,
    key: jax.Array,
    z_range: tuple[float, float],
) -> tuple[jax.Array, dict]:
    """Total loss and its terms for one batch of the crop stream.

    batch: 'rgb' uint8 (B,S,S,3) (converted to float in [0,1] here; float input is taken as
    already in [0,1]), 'pe' (B,S,S,2), 'mask_visib' (B,S,S) (> 0 = visible), 'R_allo' (B,3,3),
    'delta_xy' (B,2), 'delta_z' (B,), 'obj_idx' (B,). key: randomness of the negatives.
    z_range: (d_lo, d_hi) of the z bins (sc6d_jax.data.delta_z_range).

    Returns (loss, aux) with aux = {'loss', 'loss_rot', 'loss_xy', 'loss_z', 'loss_mask',
    'rot_top1' (fraction of samples whose ground truth outscores every negative),
    'z_abs_err' (mean |decoded depth code - true code|; the code is delta_z unless
    z_norm="focal"), 'z_rel_err' (the same relative to the true code), 'xy_abs_err'}.
    With z_norm="focal" the batch must hold 'K' (B,3,3), the image intrinsics.
    """
    _check_batch(mcfg, batch)
    if lcfg.z_norm != "none" and "K" not in batch:
        raise ValueError("z_norm='focal' needs the image intrinsics K (batch['K'])")
    if lcfg.w_dense > 0 or lcfg.w_dense_xyz > 0:
        _check_dense(mcfg, lcfg, batch)
    if lcfg.w_rot_cls > 0 and not mcfg.rot_cls:
        raise ValueError("loss.w_rot_cls > 0 needs a model with model.rot_cls > 0 (its grid size)")
    if lcfg.w_xy_vote > 0 and not mcfg.xy_vote:
        raise ValueError("loss.w_xy_vote > 0 needs a model with model.xy_vote=True")
    if lcfg.w_rot_readout > 0 and not mcfg.rot_readout:
        raise ValueError("loss.w_rot_readout > 0 needs a model with model.rot_readout=True")
    if lcfg.w_view > 0:
        if not mcfg.view_head:
            raise ValueError("loss.w_view > 0 needs a model with model.view_head > 0 (the view's side)")
        v = mcfg.view_head
        if "view" not in batch or tuple(jnp.shape(batch["view"]))[1:] != (v, v, 3):
            raise ValueError(f"loss.w_view > 0 needs a batch with 'view' (B,{v},{v},3) (a stream with view={v}), got "
                             f"{None if 'view' not in batch else tuple(jnp.shape(batch['view']))}")
    d_lo, d_hi = z_range
    obj_idx = jnp.asarray(batch["obj_idx"], jnp.int32)
    target = downsample_mask(jnp.asarray(batch["mask_visib"]), 4, lcfg.mask_downsample)
    teacher = None
    if lcfg.teacher_gate and mcfg.mask_gate:
        if "difficulty" not in batch:
            raise ValueError("loss.teacher_gate needs batch['difficulty'] (the crop stream's curriculum)")
        d = jnp.asarray(batch["difficulty"], jnp.float32)
        teacher = (target, jax.random.uniform(jax.random.fold_in(key, 2), d.shape) >= d)
    out = apply(params, mcfg, batch["rgb"], batch.get("pe") if mcfg.use_pe else None, obj_idx, teacher)
    R_gt = jnp.asarray(batch["R_allo"], jnp.float32)
    logits = candidate_logits(params, mcfg, lcfg, out, R_gt, obj_idx, key)
    loss_rot = info_nce(logits)

    dxy = jnp.asarray(batch["delta_xy"], jnp.float32)

    dz = jnp.asarray(batch["delta_z"], jnp.float32)
    code = z_code(dz, batch.get("K"), lcfg)
    a_lo, a_hi = _z_axis(lcfg, z_range)
    val = jnp.log(code) if lcfg.z_bins == "log" else code

    def depth_loss(o: dict) -> tuple[jax.Array, jax.Array]:
        """(depth loss, decoded code) of z logits ``o["z_logits"]``."""
        if lcfg.z_mode == "regression":
            lz = jnp.mean(jnp.abs(o["z_logits"][:, 0] - (val - a_lo) / (a_hi - a_lo)))
        else:
            labels = z_bin_label(val, mcfg.n_z_bins, a_lo, a_hi)
            if lcfg.z_loss == "focal":
                lz = focal_loss(o["z_logits"], labels, lcfg.focal_alpha, lcfg.focal_gamma)
            elif lcfg.z_loss == "gauss":
                pos = jnp.clip((val - a_lo) / (a_hi - a_lo), 0.0, 1.0) * (mcfg.n_z_bins - 1)
                soft = gaussian_bin_targets(pos, mcfg.n_z_bins, lcfg.z_label_sigma)
                lz = -jnp.mean(jnp.sum(soft * jax.nn.log_softmax(o["z_logits"], axis=-1), axis=-1))
            else:
                lz = cross_entropy(o["z_logits"], labels)
        pred = predict_z(o, lcfg, z_range)
        if lcfg.w_z_l1 > 0:
            lz = lz + lcfg.w_z_l1 * jnp.mean(jnp.abs(jnp.log(jnp.maximum(pred, 1e-6) / code)))
        return lz, pred

    extra = {}
    if mcfg.z_rot or mcfg.xy_rot:
        R_z = R_gt
        if lcfg.z_rot_noise_deg > 0:
            R_z = R_gt @ local_rotation_deltas(jax.random.fold_in(key, 3), (R_gt.shape[0],), 0.0, lcfg.z_rot_noise_deg)
        if mcfg.z_rot and lcfg.z_rot_separate:  # the depth prior on its own, the image head as without it
            extra["loss_z_prior"] = depth_loss({"z_logits": rotation_prior_output(params["z_rot"], R_z, obj_idx)})[0]
            out = with_rotation_priors(params, dataclasses.replace(mcfg, z_rot=False), out, R_z, obj_idx)
        else:
            out = with_rotation_priors(params, mcfg, out, R_z, obj_idx)
    loss_z, code_pred = depth_loss(out)
    loss_xy = jnp.mean(jnp.sum(jnp.abs(out["delta_xy"] - dxy), axis=-1))

    loss_mask = bce_with_logits(out["mask_logit"], target)

    loss = lcfg.w_rot * loss_rot + lcfg.w_xy * loss_xy + lcfg.w_z * loss_z + lcfg.w_mask * loss_mask
    if "loss_z_prior" in extra:
        loss = loss + lcfg.w_z * extra["loss_z_prior"]
    if lcfg.w_dense > 0:
        extra["loss_dense"] = dense_loss(out, batch, slice(0, 4))
        loss = loss + lcfg.w_dense * extra["loss_dense"]
    if lcfg.w_xy_vote > 0:
        # each vote weighs the visible fraction of its cell (area), whatever the mask head's target
        f = mcfg.crop_size // out["xy_votes"].shape[1]
        cells = target if (f, lcfg.mask_downsample) == (4, "area") else \
            downsample_mask(jnp.asarray(batch["mask_visib"]), f, "area")
        extra["loss_xy_vote"] = vote_loss(out["xy_votes"], dxy, cells)
        loss = loss + lcfg.w_xy_vote * extra["loss_xy_vote"]
    if lcfg.w_dense_xyz > 0:
        extra["loss_dense_xyz"] = dense_loss(out, batch, slice(4, 7))
        loss = loss + lcfg.w_dense_xyz * extra["loss_dense_xyz"]
    if lcfg.w_rot_readout > 0:
        want = jnp.swapaxes(R_gt[:, :, :2], 1, 2).reshape(R_gt.shape[0], 6)  # the two columns, one after the other
        extra["loss_rot_readout"] = jnp.mean(jnp.sum(jnp.square(out["rot_6d"] - want), axis=-1))
        loss = loss + lcfg.w_rot_readout * extra["loss_rot_readout"]
    if lcfg.w_view > 0:
        extra["loss_view"] = view_loss(out["view"], batch["view"], lcfg.view_top)
        loss = loss + lcfg.w_view * jnp.asarray(batch.get("view_weight", 1.0), jnp.float32) * extra["loss_view"]
    if lcfg.w_rot_cls > 0:
        G = jnp.asarray(rot_cls_grid(mcfg.rot_cls))
        nearest = jnp.argmax(jnp.einsum("kij,bij->bk", G, R_gt), axis=-1)  # max trace(G^T R) = min angle
        extra["loss_rot_cls"] = cross_entropy(out["rot_cls_logits"], nearest)
        loss = loss + lcfg.w_rot_cls * extra["loss_rot_cls"]
    aux = {
        "loss": loss,
        "loss_rot": loss_rot,
        "loss_xy": loss_xy,
        "loss_z": loss_z,
        "loss_mask": loss_mask,
        "rot_top1": jnp.mean((jnp.argmax(logits, axis=-1) == 0).astype(jnp.float32)),
        "z_abs_err": jnp.mean(jnp.abs(jax.lax.stop_gradient(code_pred) - code)),
        "z_rel_err": jnp.mean(jnp.abs(jax.lax.stop_gradient(code_pred) - code) / code),
        "xy_abs_err": jnp.mean(jnp.abs(jax.lax.stop_gradient(out["delta_xy"]) - dxy)),
        **extra,
    }
    return loss, aux


def view_loss(pred: jax.Array, view: jax.Array, top: float = 0.25) -> jax.Array:
    """Bootstrapped L2 of a predicted clean view (B,V,V,3) against the stream's ``view`` uint8
    (B,V,V,3) (divided by 255): per pixel the squared error summed over the colour channels, the
    mean of each crop's ``ceil(top * V * V)`` largest, averaged over the batch."""
    target = jnp.asarray(view, jnp.float32) / 255.0
    err = jnp.sum(jnp.square(pred - target), axis=-1).reshape(pred.shape[0], -1)
    k = max(1, int(math.ceil(top * err.shape[1])))
    return jnp.mean(jax.lax.top_k(err, k)[0]) if k < err.shape[1] else jnp.mean(err)


def _check_dense(mcfg: ModelConfig, lcfg: LossConfig, batch: dict) -> None:
    if not mcfg.dense_head:
        raise ValueError("loss.w_dense or loss.w_dense_xyz > 0 needs a model with model.dense_head=True")
    if lcfg.w_dense_xyz > 0 and not mcfg.dense_xyz:
        raise ValueError("loss.w_dense_xyz > 0 needs a model with model.dense_xyz=True")
    if "dense" not in batch or "dense_w" not in batch:
        raise ValueError("loss.w_dense or loss.w_dense_xyz > 0 needs a batch with 'dense' and 'dense_w' "
                         "(a stream with dense=True)")


def dense_loss(out: dict, batch: dict, channels: slice = slice(0, 4)) -> jax.Array:
    """L1 of the dense head's ``channels`` (0-3: normal and relative depth; 4-6: object-frame
    points) against the stream's targets (``batch['dense']`` (B,h,w,4 or 7)), averaged over
    blocks weighted by ``batch['dense_w']`` (B,h,w)."""
    target = jnp.asarray(batch["dense"], jnp.float32)
    w = jnp.asarray(batch["dense_w"], jnp.float32)
    if target.shape != out["dense"].shape or w.shape != target.shape[:-1]:
        raise ValueError(f"dense targets {target.shape} / weights {w.shape} do not match the head {out['dense'].shape}")
    err = jnp.sum(jnp.abs(out["dense"][..., channels] - target[..., channels]), axis=-1)
    return jnp.sum(w * err) / (jnp.sum(w) + 1e-6)
