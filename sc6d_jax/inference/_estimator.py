"""``Estimator``: a trained SC6D model ready to estimate poses from an image, K and boxes.

    est = Estimator.load(run_dir)                 # params, config, cached rotation library
    poses = est.predict(image, K, boxes, obj_ids, tta=False, top_k=1, refine=False, tta_mode="fuse")

Crops are made exactly as the training stream makes them (:mod:`sc6d_jax.geometry`: square
box of side ``crop_pad * max(w, h)`` around the box centre, with the model's ``crop_pad``, 1.5
by default; ``warp_crop`` bilinear with zero border, each pixel the mean of the model's
``crop_supersample``-squared samples; PE map from K and T). The box count is padded to the next power of two so that calls with the
same bucket reuse one compiled predictor. Input is validated before anything is compiled.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from sc6d_jax.geometry import crop_box, crop_transform, validate_boxes, validate_K, warp_crop
from sc6d_jax.inference._library import (
    DEFAULT_LIBRARY_SIZE,
    RotationLibrary,
    load_or_build_library,
    pack_library,
)
from sc6d_jax.inference._predictor import predict_crops

#: Rows per library block in the estimator (see Estimator.packed_library).
ESTIMATOR_BLOCK = 8192


@dataclass(frozen=True)
class PosePrediction:
    """One box's estimate: ``x_cam = R x_model + t`` (t in mm).

    score: cosine between the crop embedding and the chosen rotation's embedding (in [-1, 1]);
    prob: softmax(cosine / tau) of that rotation over the whole library; R_topk ``(k,3,3)``
    with prob_topk / score_topk ``(k,)``, best first (egocentric, with the same t).
    """

    obj_id: int
    box: np.ndarray
    R: np.ndarray
    t: np.ndarray
    score: float
    prob: float
    R_topk: np.ndarray
    prob_topk: np.ndarray
    score_topk: np.ndarray


def bucket_size(n: int) -> int:
    """Next power of two >= n (>= 1): the padded batch size."""
    return 1 << max(int(n) - 1, 0).bit_length()


def _check_image(image: Any) -> np.ndarray:
    if not isinstance(image, np.ndarray):
        raise ValueError(f"image must be a numpy array, got {type(image).__name__}")
    if image.dtype != np.uint8:
        raise ValueError(f"image must be uint8, got {image.dtype}")
    if image.ndim == 2:
        image = np.repeat(image[:, :, None], 3, axis=2)
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"image must be HxWx3 (RGB) or HxW (grayscale), got shape {image.shape}")
    if image.shape[0] == 0 or image.shape[1] == 0:
        raise ValueError(f"image is empty: shape {image.shape}")
    return image


class Estimator:
    """A trained model plus its rotation library. Build with :meth:`load` (or the constructor)."""

    def __init__(
        self,
        params: dict,
        config: Any,
        library: RotationLibrary,
        models_dir: str | None = None,
        block: int | None = None,
    ) -> None:
        if not config.resolved:
            raise ValueError("the training config has no obj_ids / z_range (training never started?)")
        self.config = config
        self.mcfg = config.model
        self.obj_ids: list[int] = [int(i) for i in config.stream.obj_ids]
        self.z_range = tuple(float(v) for v in config.z_range)
        self.lcfg = config.loss
        self.tau = float(config.loss.tau)
        self.models_dir = models_dir
        self.params = jax.tree.map(jnp.asarray, params)
        self.library = library
        self._block = block
        self._packed: tuple[jax.Array, int] | None = None
        self._lib_R = jnp.asarray(library.R)

    # ------------------------------------------------------------------ construction
    @classmethod
    def load(
        cls,
        run_dir: str | os.PathLike,
        library_size: int | tuple[int, int] = DEFAULT_LIBRARY_SIZE,
        step: int | None = None,
        cache: bool = True,
        progress: bool = True,
    ) -> Estimator:
        """Newest (or ``step``) checkpoint of a training run and its rotation library (cached in
        ``RUN_DIR/library``, rebuilt when the model changed).

        ``run_dir`` may also name a shipped model (``"builtin"``, ``"lmo"``; see
        :mod:`sc6d_jax.pretrained`); its library is cached in the user cache."""
        from sc6d_jax.checkpoint import find_checkpoint, load_checkpoint, read_meta
        from sc6d_jax.pretrained import resolve

        run_dir, cache_dir = resolve(run_dir)
        ckpt = find_checkpoint(run_dir, step)
        params, cfg = load_checkpoint(ckpt)
        models_dir = read_meta(ckpt).get("models_dir")  # informative (absent in shipped models)
        lib = load_or_build_library(
            params, cfg.model, library_size, cache_dir=cache_dir if cache else None, progress=progress
        )
        return cls(params, cfg, lib, models_dir=models_dir)

    # ------------------------------------------------------------------ helpers
    def packed_library(self) -> tuple[jax.Array, int]:
        """The library packed in blocks (built once): one block size for every batch size, so
        the estimator holds one packed copy (855 MB for 14 objects x 480k), not one per batch
        bucket.  8,192 rows per block was as fast as the per-batch best at batches 1, 8 and 64
        (480k x 32, 2 CPU cores)."""
        if self._packed is None:
            block = self._block or min(ESTIMATOR_BLOCK, max(self.library.size, 1))
            blocks, n = pack_library(self.library.emb, block)
            self._packed = (jnp.asarray(blocks), n)
        return self._packed

    def obj_index(self, obj_ids: Sequence[int]) -> np.ndarray:
        """BOP ids -> model object indices (ValueError naming unknown ids)."""
        known = {o: i for i, o in enumerate(self.obj_ids)}
        ids = np.asarray(obj_ids).reshape(-1)
        if ids.size and not np.issubdtype(ids.dtype, np.integer):
            if not np.all(np.isfinite(ids.astype(float))) or np.any(ids != np.round(ids)):
                raise ValueError(f"obj_ids must be integers, got {ids.tolist()}")
        bad = sorted({int(i) for i in ids if int(i) not in known})
        if bad:
            raise ValueError(f"unknown object id(s) {bad}; the model knows {self.obj_ids}")
        return np.asarray([known[int(i)] for i in ids], np.int32)

    def make_crops(self, image: np.ndarray, boxes: np.ndarray, n_pad: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(rgb crops uint8 (n_pad,S,S,3), center (n_pad,2), side (n_pad,)); padding repeats box 0."""
        S = self.mcfg.crop_size
        b = np.concatenate([boxes, np.repeat(boxes[:1], n_pad - len(boxes), axis=0)]).astype(np.float32)
        center, side = crop_box(b, pad=self.mcfg.crop_pad)
        T = crop_transform(center, side, S)
        crops = warp_crop(image, np.asarray(T), S, interpolation="linear",
                          supersample=getattr(self.mcfg, "crop_supersample", 1))
        return crops, np.asarray(center, np.float32), np.asarray(side, np.float32)

    def crops_fn(self, batch: int, tta: bool = False, top_k: int = 1, refine: bool = False,
                 tta_mode: str = "fuse"):
        """``f(params, blocks, lib_R, rgb, K, center, side, obj_idx) -> dict`` (jitted, static
        options bound) and its library arguments, for a batch of ``batch`` crops."""
        blocks, n = self.packed_library()
        kw = dict(mcfg=self.mcfg, lcfg=self.lcfg, z_range=self.z_range, n_valid=n, tta=tta,
                  top_k=top_k, refine=refine, tau=self.tau, tta_mode=tta_mode)
        return kw, blocks

    # ------------------------------------------------------------------ prediction
    def predict(
        self,
        image: np.ndarray,
        K: Any,
        boxes: Any,
        obj_ids: Sequence[int],
        tta: bool = False,
        top_k: int = 1,
        refine: bool = False,
        tta_mode: str = "fuse",
    ) -> list[PosePrediction]:
        """Poses of the objects in ``boxes`` (N x 4, x y w h px) of ``image`` (HxWx3 / HxW uint8).

        A box is the object's extent with pixel centres at integer coordinates (pixels 10..19
        make x = 9.5, w = 10); BOP's pixel boxes (``bbox_visib``) convert with
        :func:`sc6d_jax.bop.bbox_extent`.

        Args:
            K: (3, 3) intrinsics of the image. obj_ids: N BOP object ids known to the model.
            tta: 4-fold in-plane rotation test-time augmentation (the authors': the crop turned
                by 0/90/180/270 degrees; depth and centre offset averaged).
            top_k: number of library rotations returned per box (best first).
            refine: continuous refinement of the best rotation (BFGS on the cosine).
            tta_mode: with ``tta``, how the four copies choose the rotation: ``"fuse"`` (the
                default: candidates pooled from all copies, scored by their mean cosine) or
                ``"best"`` (the authors': the copy with the highest cosine alone).

        Returns:
            One :class:`PosePrediction` per box, in order; [] for no boxes.
        """
        image = _check_image(image)
        Kn = np.asarray(K, dtype=np.float64) if not isinstance(K, np.ndarray) else K.astype(np.float64)
        if Kn.shape != (3, 3):
            raise ValueError(f"K must be 3x3, got shape {Kn.shape}")
        validate_K(Kn)
        bx = np.asarray(boxes, dtype=np.float64)
        if bx.size == 0:
            if len(np.asarray(obj_ids).reshape(-1)):
                raise ValueError(f"no boxes but {len(np.asarray(obj_ids).reshape(-1))} obj_ids")
            return []
        if bx.ndim != 2 or bx.shape[1] != 4:
            raise ValueError(f"boxes must be N x 4 (x, y, w, h), got shape {bx.shape}")
        h, w = image.shape[:2]
        validate_boxes(bx, image_size=(w, h))
        ids = np.asarray(obj_ids).reshape(-1)
        if len(ids) != len(bx):
            raise ValueError(f"{len(bx)} boxes but {len(ids)} obj_ids")
        obj_idx = self.obj_index(ids)
        if isinstance(top_k, bool) or not isinstance(top_k, (int, np.integer)) or not 1 <= top_k <= self.library.size:
            raise ValueError(f"top_k must be an int in [1, {self.library.size}], got {top_k!r}")
        n = len(bx)
        n_pad = bucket_size(n)
        crops, center, side = self.make_crops(image, bx, n_pad)
        obj_p = np.concatenate([obj_idx, np.repeat(obj_idx[:1], n_pad - n)])
        K_b = np.broadcast_to(Kn.astype(np.float32), (n_pad, 3, 3))
        out = self.predict_crops(crops, K_b, center, side, obj_p, tta=tta, top_k=int(top_k), refine=refine,
                                 tta_mode=tta_mode)
        res = []
        for i in range(n):
            res.append(
                PosePrediction(
                    obj_id=int(ids[i]), box=bx[i].copy(), R=out["R"][i], t=out["t"][i],
                    score=float(out["score"][i]), prob=float(out["prob"][i]), R_topk=out["R_topk"][i],
                    prob_topk=out["prob_topk"][i], score_topk=out["score_topk"][i],
                )
            )
        return res

    def export(self, path: str | os.PathLike, tta: bool = False, top_k: int = 1, tta_mode: str = "fuse") -> Path:
        """Serialise the predictor (crops in, poses out; params and library baked into the file)
        with ``jax.export``; run it with :func:`sc6d_jax.inference.load_exported`."""
        from sc6d_jax.inference._export import export_predictor

        return export_predictor(self, path, tta=tta, top_k=top_k, tta_mode=tta_mode)

    def predict_crops(
        self, rgb: np.ndarray, K: np.ndarray, center: np.ndarray, side: np.ndarray, obj_idx: np.ndarray,
        tta: bool = False, top_k: int = 1, refine: bool = False, tta_mode: str = "fuse",
    ) -> dict[str, np.ndarray]:
        """Run the jitted predictor on prepared crops; returns host arrays with finite poses."""
        kw, blocks = self.crops_fn(rgb.shape[0], tta=tta, top_k=top_k, refine=refine, tta_mode=tta_mode)
        out = predict_crops(
            self.params, blocks, self._lib_R, jnp.asarray(rgb), jnp.asarray(K, jnp.float32),
            jnp.asarray(center, jnp.float32), jnp.asarray(side, jnp.float32), jnp.asarray(obj_idx, jnp.int32), **kw,
        )
        out = {k: np.asarray(v) for k, v in out.items()}
        return sanitize(out, K, center, side, self.mcfg.crop_size, self.z_range)


def sanitize(out: dict, K, center, side, S: int, z_range) -> dict:
    """Never a NaN pose: a non-finite t falls back to the ray through the box centre at the middle
    of the depth range, a non-finite R to the identity (score -1, prob 0)."""
    t, R = out["t"], out["R"]
    bad_t = ~np.all(np.isfinite(t), axis=-1)
    if np.any(bad_t):
        Kn = np.asarray(K, np.float64)
        for i in np.nonzero(bad_t)[0]:
            ray = np.linalg.solve(Kn[i], np.array([center[i][0], center[i][1], 1.0]))
            tz = 0.5 * (z_range[0] + z_range[1]) * S / float(side[i])
            t[i] = (tz * ray / ray[2]).astype(t.dtype)
    bad_R = ~np.all(np.isfinite(R), axis=(-1, -2))
    if np.any(bad_R):
        R[bad_R] = np.eye(3, dtype=R.dtype)
        out["R_topk"][bad_R] = np.eye(3, dtype=R.dtype)
        out["score"][bad_R] = -1.0
        out["prob"][bad_R] = 0.0
    return out
