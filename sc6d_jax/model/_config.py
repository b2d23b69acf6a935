"""ModelConfig: every architectural choice of the SC6D network as a hashable, frozen dataclass."""

from __future__ import annotations

import dataclasses

#: Residual blocks per stage (BasicBlock) and channel multipliers of the four stages.
BACKBONES: dict[str, tuple[tuple[int, int, int, int], tuple[int, int, int, int]]] = {
    # name: (blocks per stage, stage width multipliers of ``width``)
    "tiny": ((1, 1, 1, 1), (1, 1, 2, 2)),
    "resnet10": ((1, 1, 1, 1), (1, 2, 4, 8)),
    "resnet18": ((2, 2, 2, 2), (1, 2, 4, 8)),
    "resnet34": ((3, 4, 6, 3), (1, 2, 4, 8)),
}

ROT_HEADS = ("so3", "ipdf")


@dataclasses.dataclass(frozen=True)
class ModelConfig:
    """Architecture of the SC6D network (static: hashable, usable as a jit static argument).

    Defaults are the paper's model (ResNet34 at 256x256, 1000 z bins). Fields:

    - n_objects: objects the model knows (per-object decoders / SO(3) output layers).
    - crop_size: S, the input crop side (multiple of 16); features and mask come out at S/4.
    - backbone: "tiny" | "resnet10" | "resnet18" | "resnet34" (BasicBlock ResNets; "tiny" has
      one block per stage and stage widths (w, w, 2w, 2w)); width: channels of stage 1 (64 in
      torchvision ResNets).
    - stem_kernel: kernel of the new stride-2 stem conv (7 as torchvision); no max-pool.
    - decoder_width: channels of the U-Net up-block at S/8 (the block at S/4 has half);
      0 = the backbone's last-stage width (512 for ResNet34, the authors' choice).
    - feat_dim: feature channels at S/4 (64); emb_dim: rotation embedding size (32).
    - n_z_bins: K, bins of delta_z (1000); the "regression" z mode uses output unit 0 only.
    - use_pe: concatenate the 2-channel PE map to RGB (5 input channels) or not (3).
    - per_object_decoder: one U-Net decoder per object (paper) or one shared decoder whose
      bottleneck gets a learned per-object embedding added.
    - rot_head: "so3" (SO(3) encoder + cosine) or "ipdf" (Implicit-PDF style scoring MLP).
    - conv_impl: "auto" | "im2col" | "lax" (see sc6d_jax.model._layers).
    - pose_width: channels of the pose decoder (128 in the paper; 8 branches -> 8*pose_width).
    - head_hidden: FC width of the three heads (256); so3_hidden: SO(3) encoder width (256).
    - ipdf_hidden: width of the IPDF MLP (256); ipdf_pe_freqs: positional-encoding
      frequencies of the rotation input to IPDF (0 = the raw 9 matrix entries).
    - so3_pe_freqs: the same encoding of the SO(3) encoder's input (0 = the raw 9 entries,
      paper): sin/cos(2^k pi r) for k < so3_pe_freqs lets the encoder make embeddings that turn
      within a few degrees (an MLP on the raw entries is smooth at the scale of tens of degrees).
    - dense_head: a per-pixel linear head on the decoder features at S/4 predicting the
      visible surface's normal (allocentric frame) and its depth relative to the object centre
      (``out["dense"]`` (B,S/4,S/4,4)), trained by ``LossConfig.w_dense`` against the stream's
      ``dense`` targets: geometry supervision for the features the pose decoder reads, which
      needs no symmetry labels. Not used at inference.
    - dense_xyz: the dense head also predicts the visible surface's points in the object's own
      frame (3 more channels, ``out["dense"]`` (B,S/4,S/4,7)), trained by
      ``LossConfig.w_dense_xyz``: object coordinates tell the small parts that break a nearly
      symmetric object's symmetry (the dumbbell's cube) by where they are, pixel by pixel
      (measured on the dumbbell: no gain, README). Needs dense_head. Not used at inference.
    - gn_groups: maximum GroupNorm groups (32; fewer when channels are few).
    - mask_gate: multiply the decoder features by sigmoid(mask logit) before the pose decoder,
      so that clutter and occluders reach the heads damped by the predicted visible mask
      (False = paper: the mask is only concatenated).
    - z_size_input: give the depth head the apparent size of the predicted visible mask (log
      area, log spread in x and y; ``_pose_decoder.mask_size_features``) next to its features.
    - pe_turns: the PE map turns with the crop (``sc6d_jax.geometry.turn_pe``) wherever the
      crop is turned by quarter turns: the training stream's in-plane augmentation and the
      TTA copies. Off (the authors'): the map stays as it was, so for 3 crops in 4 an off-axis
      object's perspective stretch lies along another image axis than its rays say, and the
      depth head cannot learn the stretch's correction (it over-estimates near the image
      centre and under-estimates towards the edges).
    - z_ray_input: give the depth head the crop centre's ray (the mean of the PE map) and its
      second-order terms (``_pose_decoder.ray_features``): an off-axis object looks stretched
      along its ray by up to ``1/cos`` of the ray's angle, which the depth code (read off the
      apparent size) has to undo; GroupNorm removes such a near-constant input from the
      features. Needs ``use_pe``; use with ``pe_turns`` (else the ray disagrees with turned crops).
    - xy_vote: the projected centre's offset delta_xy read off votes instead of the xy head's
      one regression from pooled features: every cell of the decoder's S/4 map predicts the
      offset from itself to the projected centre and a confidence, and delta_xy is the average
      of the cells' votes (cell position + offset) weighted by the softmax of confidence plus
      log of the predicted visible mask (``_network.vote_delta_xy``). A centre is a position,
      which a map finds where it is; pooled features must carry it as a number. Train with
      ``loss.w_xy_vote`` (each cell's offset against the ground truth, on the visible mask).
      Measured on obj 11: worse than the regression (README "The projected centre read off votes").
    - xy_rot: a per-object MLP of the allocentric rotation (the ground truth, turned by
      ``loss.z_rot_noise_deg``, in training; the matched rotation at inference) adds an offset to
      delta_xy: where the projected centre lies in the box is a function of the rotation (the
      pyramid's origin halfway up its axis), which the xy head shrinks towards the silhouette's
      centre. Measured: obj 11 better, obj 1 worse (README "The centre's offset from the rotation").
    - xy_vote_from: which map votes: "feat" (the decoder's S/4 features, before the mask gate)
      or "block" (the pose decoder's dilated block, whose dilations and pooled branch span the
      whole crop; its cells are weighted by the mask averaged over them).
    - z_scale_input: give the depth head the crop's angular size (the log of the side its PE map
      spans, ``_pose_decoder.scale_features``). The depth code is nearly scale-invariant, but not
      at close range: the near side of an object looks larger than the far side, so the box (and
      the code) grows with the ratio of the object's size to its distance, which the crop's
      appearance shows only faintly at 64 pixels and the angular size shows directly. GroupNorm
      removes the PE map's spread as it removes its mean. Needs ``use_pe``.
    - rot_readout: a per-object linear map from the unit rotation embedding to the first two
      columns of the allocentric rotation (``out["rot_6d"]`` (B,6)), trained by
      ``LossConfig.w_rot_readout``: the embedding itself has to carry the angle wherever the
      crop shows it. Not used at inference.
    - rot_cls: an auxiliary per-object classifier of the allocentric rotation over a fixed grid
      of about ``rot_cls`` rotations (:func:`sc6d_jax.model.rot_cls_grid`), read off the
      rotation head's hidden layer (``out["rot_cls_logits"]``), trained by
      ``LossConfig.w_rot_cls`` with cross-entropy on the grid rotation nearest to the ground
      truth (0 = off, paper). Its classes are free parameters, so unlike the SO(3) encoder it
      cannot give a ring of turns one class; unlike the readout's regression, cross-entropy
      over distinct classes does not settle on the mean of an ambiguous target. No symmetry
      labels: for a symmetric object it learns a spread over the equivalent classes. Not used
      at inference.
    - view_head: side V of an auxiliary linear decoder from the rotation head's hidden layer to a
      clean view of the target (``out["view"]`` (B,V,V,3) in [0, 1] units), trained by
      ``LossConfig.w_view`` against the stream's ``view`` (the crop before colour augmentation,
      black off the visible target): the Augmented Autoencoder's reconstruction, asking the
      vector the rotation embedding is read from to carry everything the object shows, including
      the small parts that break a near-symmetry (the dumbbell's cube), which InfoNCE alone can
      leave out while it has a ring of equally good rotations. No symmetry labels (alike views
      give one target). 0 = off. Not used at inference.
    - view_from: what the view head decodes: "hidden" (the rotation head's hidden layer, one
      linear map to the whole view), "map" (the m x m map the rotation head flattens, each
      cell linearly to its (V/m)^2 patch of the view: local, as a decoder of the spatial layout
      the head reads; V must be a multiple of m) or "block" (the same from the dilated block's
      output, 8 pose_width channels at S/8 in the cpu preset, that all three heads read).
    - view_per_object: one view decoder per object (stacked, chosen by the crop's object) instead
      of one shared by all: with several objects, the shared linear decoder makes them share
      what each cell of the decoded map means.
    - per_object_heads: the output layers of the pose decoder's three heads (rotation embedding,
      delta_xy, z logits) one per object, chosen by the crop's object, as the SO(3) encoder's
      output layer is (paper: shared). The rest of the pose decoder stays shared: each object
      reads its own embedding and depth code off the shared hidden layers.
    - pose_downsample: stride-2 convs of the pose decoder before its dilated block (2, paper:
      the block runs at S/16 and the heads see S/32). 1 runs the block at S/8, the heads at
      S/16 (the second conv keeps its weights, with stride 1): for a 64-px crop the heads read
      a 4x4 map instead of 2x2, and the dilations 2-7 span that map as they span the paper's
      16x16 at 256 px. 0 runs the block at S/4 and the heads at S/8 (both convs stride 1): at
      64 px the paper's map sizes at 256 px (block 16x16, heads 8x8).
    - z_rot: a per-object depth prior from the rotation: an MLP of the allocentric rotation
      (9 entries -> head_hidden -> head_hidden -> n_z_bins, output layer zero at init) whose
      logits are added to the image's z logits (:func:`with_rotation_priors`). With a box around the
      whole object, depth is the object's extent across the view over its extent in the crop,
      and the extent is a function of the rotation alone; the image head keeps what the
      rotation does not tell (perspective, occlusion). Training feeds the ground truth
      (``LossConfig.z_rot_noise_deg`` perturbs it), inference the matched rotation.
    - crop_pad: the crop's side over the box's longer side (1.5, the authors'): the training
      stream and the estimator both cut ``crop_pad * max(w, h)`` around the box centre. With
      exact boxes the object spans ``crop_size / crop_pad`` pixels; 1.2 gives it 1.56x the
      pixels of 1.5 at the same network cost. Must be >= 1 (the box fits).
    - crop_supersample: samples per crop pixel along each axis, averaged (1 = one sample at the
      pixel's centre, as before): the training stream renders its crops at this many times
      ``crop_size`` and averages blocks (``sc6d_jax.data.StreamConfig.supersample``), and the
      estimator cuts its crops the same way (``sc6d_jax.geometry.warp_crop``'s ``supersample``),
      so the object's outline falls between pixels as grey levels instead of a staircase.
      The network's cost is unchanged; the stream renders ``crop_supersample^2`` times the pixels.
    """

    n_objects: int = 1
    crop_size: int = 256
    backbone: str = "resnet34"
    width: int = 64
    stem_kernel: int = 7
    decoder_width: int = 0
    feat_dim: int = 64
    emb_dim: int = 32
    n_z_bins: int = 1000
    use_pe: bool = True
    per_object_decoder: bool = True
    rot_head: str = "so3"
    conv_impl: str = "auto"
    pose_width: int = 128
    head_hidden: int = 256
    so3_hidden: int = 256
    ipdf_hidden: int = 256
    ipdf_pe_freqs: int = 0
    so3_pe_freqs: int = 0
    dense_head: bool = False
    dense_xyz: bool = False
    gn_groups: int = 32
    mask_gate: bool = False
    z_size_input: bool = False
    pose_downsample: int = 2
    rot_readout: bool = False
    rot_cls: int = 0
    view_head: int = 0
    view_from: str = "hidden"
    view_per_object: bool = False
    per_object_heads: bool = False
    z_rot: bool = False
    pe_turns: bool = False
    z_ray_input: bool = False
    z_scale_input: bool = False
    xy_vote: bool = False
    xy_rot: bool = False
    xy_vote_from: str = "feat"
    crop_pad: float = 1.5
    crop_supersample: int = 1

    def __post_init__(self) -> None:
        if self.backbone not in BACKBONES:
            raise ValueError(f"backbone must be one of {sorted(BACKBONES)}, got {self.backbone!r}")
        if self.rot_head not in ROT_HEADS:
            raise ValueError(f"rot_head must be one of {ROT_HEADS}, got {self.rot_head!r}")
        if self.conv_impl not in ("auto", "im2col", "lax"):
            raise ValueError(f"conv_impl must be 'auto', 'im2col' or 'lax', got {self.conv_impl!r}")
        if self.crop_size < 32 or self.crop_size % 16:
            raise ValueError(f"crop_size must be a multiple of 16 and >= 32, got {self.crop_size}")
        if not (isinstance(self.crop_pad, (int, float)) and 1.0 <= self.crop_pad <= 4.0):
            raise ValueError(f"crop_pad must be a number in [1, 4], got {self.crop_pad!r}")
        if (not isinstance(self.crop_supersample, int) or isinstance(self.crop_supersample, bool)
                or not 1 <= self.crop_supersample <= 8):
            raise ValueError(f"crop_supersample must be an integer in [1, 8], got {self.crop_supersample!r}")
        if self.stem_kernel < 1 or self.stem_kernel % 2 == 0:
            raise ValueError(f"stem_kernel must be odd and positive, got {self.stem_kernel}")
        for name in ("n_objects", "width", "feat_dim", "emb_dim", "n_z_bins", "pose_width",
                     "head_hidden", "so3_hidden", "ipdf_hidden", "gn_groups"):
            v = getattr(self, name)
            if not isinstance(v, int) or v < 1:
                raise ValueError(f"{name} must be a positive int, got {v!r}")
        if self.pose_downsample not in (0, 1, 2):
            raise ValueError(f"pose_downsample must be 0, 1 or 2, got {self.pose_downsample!r}")
        if self.z_ray_input and not self.use_pe:
            raise ValueError("z_ray_input needs use_pe=True (the ray is read off the PE map)")
        if self.z_scale_input and not self.use_pe:
            raise ValueError("z_scale_input needs use_pe=True (the crop's angular size is read off the PE map)")
        if self.decoder_width < 0 or self.ipdf_pe_freqs < 0 or self.so3_pe_freqs < 0:
            raise ValueError("decoder_width, ipdf_pe_freqs and so3_pe_freqs must be >= 0")
        if not isinstance(self.rot_cls, int) or self.rot_cls < 0:
            raise ValueError(f"rot_cls must be an int >= 0 (0 = off), got {self.rot_cls!r}")
        if 0 < self.rot_cls < 8:
            raise ValueError(f"rot_cls must be 0 (off) or at least 8 grid rotations, got {self.rot_cls}")
        if not isinstance(self.view_head, int) or self.view_head < 0 or (self.view_head and self.crop_size % self.view_head):
            raise ValueError(f"view_head must be 0 (off) or a positive int dividing crop_size {self.crop_size}, "
                             f"got {self.view_head!r}")
        if self.view_from not in ("hidden", "map", "block"):
            raise ValueError(f"view_from must be 'hidden', 'map' or 'block', got {self.view_from!r}")
        if self.view_per_object and not self.view_head:
            raise ValueError("view_per_object chooses the view decoder per object: it needs view_head > 0")
        if self.xy_vote_from not in ("feat", "block"):
            raise ValueError(f"xy_vote_from must be 'feat' or 'block', got {self.xy_vote_from!r}")
        if self.dense_xyz and not self.dense_head:
            raise ValueError("dense_xyz adds channels to the dense head: it needs dense_head=True")

    @property
    def in_channels(self) -> int:
        """Input channels of the stem: 5 with the PE map, 3 without."""
        return 5 if self.use_pe else 3

    @property
    def stage_blocks(self) -> tuple[int, ...]:
        return BACKBONES[self.backbone][0]

    @property
    def stage_widths(self) -> tuple[int, ...]:
        return tuple(m * self.width for m in BACKBONES[self.backbone][1])

    @property
    def dec_width(self) -> int:
        """Channels of the S/8 up-block (decoder_width or the last stage's width)."""
        return self.decoder_width or self.stage_widths[-1]

    @property
    def mask_size(self) -> int:
        """Side of the feature map and of the mask logit: S/4."""
        return self.crop_size // 4
