"""Held-out validation during training: the pose-error breakdown on a fixed set of rendered crops.

:class:`Validator` renders ``n`` crops once, from the run's seed through a stream seed of its own
(so they are never trained on), at full difficulty (textured backgrounds, occluders with the
run's probability; no colour augmentation, no in-plane turns). At each checkpoint the loop calls
it with the current parameters: every crop is estimated as the estimator would (rotation: the
best of a fixed SO(3) grid by cosine, allocentric to egocentric; translation: the decoded
offset and depth), and the errors against the ground truth are summarised:

- ``val_rot_median_deg``: median symmetry-aware rotation error (symmetries from models_info;
  only the validation reads them, training never does);
- ``val_depth_rel_median``: median |t_z - t_z*| / t_z*; ``val_centre_median_px``;
- ``val_rot_under_{5,10,20}``, ``val_depth_under_{2,5}pct``;
- ``val_ar``: mean of AR_MSSD and AR_MSPD over the crops (the BOP19 thresholds; no VSD: a crop
  has no depth image), a proxy of the BOP AR that moves with it; ``val_ar_se``: its standard
  error over the crops (each crop's share of it: the fraction of thresholds it passes).

The grid has ``lib_size`` rotations (so3_grid), coarser than the estimator's 480,000: its
covering radius bounds the rotation error from below (about 3 degrees at 60,000 rotations).
"""

from __future__ import annotations

import hashlib
import math
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["Validator", "VAL_SEED_TAG"]

#: Mixed into the run's seed for the validation crops (the training stream uses the seed itself).
VAL_SEED_TAG = 0x5A1D


def _val_seed(seed: int) -> int:
    from sc6d_jax.data import derive_seed

    return derive_seed(seed, VAL_SEED_TAG)


class Validator:
    """The fixed validation crops of a run and the function that scores parameters on them."""

    def __init__(
        self, cfg: Any, models_dir: str | Path, n: int = 256, lib_size: int = 60_000, batch: int = 64,
        stream_overrides: dict[str, Any] | None = None,
    ) -> None:
        """``stream_overrides``: StreamConfig fields of the validation crops other than the run's
        (e.g. ``{"background": "plain", "occlusion": 0.0}`` for an easy set); None = the run's."""
        from sc6d_jax.bop import load_models_info, model_path
        from sc6d_jax.data import CropStream, StreamConfig
        from sc6d_jax.geometry import so3_grid
        from sc6d_jax.metrics import symmetry_transformations
        from sc6d_jax.render import load_mesh

        if not cfg.resolved:
            raise ValueError("the validator needs a resolved config (obj_ids and z_range)")
        self.cfg = cfg
        self.n = int(n)
        self.batch = int(batch)
        kw: dict[str, Any] = dict(
            models_dir=str(models_dir), crop_size=cfg.model.crop_size, batch_size=self.batch,
            seed=_val_seed(cfg.seed), workers=0, obj_ids=tuple(cfg.stream.obj_ids), augment=False,
        )
        kw.update(cfg.crop_fields())  # the run's scenes, cut as its crops are
        kw.update(stream_overrides or {})
        n_batches = -(-self.n // self.batch)
        with CropStream(StreamConfig(**kw)) as stream:
            parts = [stream.batch(b) for b in range(n_batches)]
        keys = ("rgb", "pe", "R", "t", "K", "center", "side", "obj_idx", "obj_id")
        self.data = {k: np.concatenate([p[k] for p in parts])[: self.n] for k in keys}
        #: which crops these are (a digest of their pixels and poses): paired comparisons of two
        #: runs' per-crop scores (``last_shares``) only between runs that validate on the same crops
        self.fingerprint = hashlib.sha1(b"".join(np.ascontiguousarray(self.data[k]).tobytes()
                                                 for k in ("rgb", "R", "t"))).hexdigest()[:16]
        self.last_shares: np.ndarray | None = None  # each crop's share of val_ar at the last call
        infos = load_models_info(models_dir)
        ids = sorted(set(int(i) for i in self.data["obj_id"]))
        self.sym_transforms = {i: symmetry_transformations(infos[i]) for i in ids}
        self.syms = {i: np.stack([s["R"] for s in self.sym_transforms[i]]) for i in ids}
        self.diam = {i: float(infos[i].diameter) for i in ids}
        rng = np.random.default_rng(0)
        self.pts = {}
        for i in ids:
            v = np.asarray(load_mesh(model_path(models_dir, i)).vertices, np.float64)
            self.pts[i] = v[rng.choice(len(v), min(len(v), 500), replace=False)]
        grid = so3_grid(*_grid_shape(lib_size))
        self.lib_R = jnp.asarray(grid, jnp.float32)
        self._fn = jax.jit(self._predict)
        self._embed = jax.jit(self._embed_grid)

    def _embed_grid(self, params: Any) -> jax.Array:
        """The grid's embeddings for every object, as the estimator's matching blocks
        (O, nb, E, block): once per call, not per batch."""
        from sc6d_jax.inference._matching import auto_block, pad_library
        from sc6d_jax.inference._library import ipdf_library_features
        from sc6d_jax.model import encode_rotations

        if self.cfg.model.rot_head == "ipdf":  # the rotations' encodings, scored per crop by the head
            return pad_library(ipdf_library_features(self.cfg.model, self.lib_R), auto_block(self.batch, self.lib_R.shape[0]))[0]
        lib = jnp.stack([encode_rotations(params, self.cfg.model, self.lib_R, o) for o in range(self.cfg.model.n_objects)])
        return pad_library(lib, auto_block(self.batch, self.lib_R.shape[0]))[0]

    def _predict(self, params: Any, lib, rgb, pe, K, center, side, obj_idx) -> dict[str, jax.Array]:
        from sc6d_jax.geometry import allocentric_to_egocentric, decode_translation
        from sc6d_jax.inference._matching import match_library
        from sc6d_jax.model import apply, decode_delta_z, with_rotation_priors

        cfg = self.cfg
        mcfg = cfg.model
        out = apply(params, mcfg, rgb, pe if mcfg.use_pe else None, obj_idx)
        # the estimator's per-object matching: each object's grid scanned once with its own
        # crops, in blocks (gathering a (B, N, E) library per batch took ~0.5 GB at 60k rotations)
        m = match_library(params["rot_head"], mcfg.rot_head, out["rot_emb"], lib, self.lib_R.shape[0], 1, 0.1, False,
                          obj_idx)
        best = m.index[:, 0]
        R_allo = self.lib_R[best]
        out = with_rotation_priors(params, mcfg, out, R_allo, obj_idx)  # the rotation's priors (depth, centre)
        dz = decode_delta_z(out, cfg.loss, cfg.z_range, K)
        t = decode_translation(out["delta_xy"], dz, K, center, side, mcfg.crop_size)
        return {"R": allocentric_to_egocentric(R_allo, t), "t": t}

    def predict(self, params: Any) -> dict[str, np.ndarray]:
        """Estimated R (n,3,3) and t (n,3) mm of every validation crop."""
        d = self.data
        lib = self._embed(params)
        outs = []
        for s in range(0, self.n, self.batch):
            sl = slice(s, s + self.batch)
            o = self._fn(params, lib, jnp.asarray(d["rgb"][sl]), jnp.asarray(d["pe"][sl]), jnp.asarray(d["K"][sl]),
                         jnp.asarray(d["center"][sl]), jnp.asarray(d["side"][sl]), jnp.asarray(d["obj_idx"][sl]))
            outs.append({k: np.asarray(v, np.float64) for k, v in o.items()})
        return {k: np.concatenate([o[k] for o in outs]) for k in ("R", "t")}

    def __call__(self, params: Any) -> dict[str, float]:
        """The breakdown of ``params`` on the validation crops, as ``val_*`` floats."""
        return self.score(self.predict(params))

    def score(self, pred: dict[str, np.ndarray]) -> dict[str, float]:
        """The breakdown of estimates ``pred`` (as :meth:`predict` returns them), as ``val_*`` floats."""
        from sc6d_jax.metrics import MSPD_THRESHOLDS, MSSD_THRESHOLDS, mspd, mssd, standard_error
        from sc6d_jax.metrics._breakdown import SUMMARY_KEYS, pose_errors, summarize_breakdown

        d = self.data
        rows = []
        hit_mssd, hit_mspd = [], []
        for i in range(self.n):
            oid = int(d["obj_id"][i])
            R_e, t_e = pred["R"][i], pred["t"][i]
            R_g, t_g, K = d["R"][i].astype(np.float64), d["t"][i].astype(np.float64), d["K"][i].astype(np.float64)
            if not (np.all(np.isfinite(R_e)) and np.all(np.isfinite(t_e)) and t_e[2] > 0):
                rows.append({"obj_id": oid, "rot_deg": 180.0, "depth_rel": math.inf, "centre_px": math.inf})
                hit_mssd.append(np.zeros(len(MSSD_THRESHOLDS)))
                hit_mspd.append(np.zeros(len(MSPD_THRESHOLDS)))
                continue
            rows.append({"obj_id": oid, **pose_errors(R_e, t_e, R_g, t_g, K, self.syms[oid])})
            syms = self.sym_transforms[oid]
            e1 = mssd(R_e, t_e, R_g, t_g, self.pts[oid], syms)
            e2 = mspd(R_e, t_e, R_g, t_g, K, self.pts[oid], syms)
            hit_mssd.append(np.array([e1 < th * self.diam[oid] for th in MSSD_THRESHOLDS], float))
            hit_mspd.append(np.array([e2 < th for th in MSPD_THRESHOLDS], float))
        s = summarize_breakdown(rows)["overall"]
        ar_mssd, ar_mspd = float(np.mean(hit_mssd)), float(np.mean(hit_mspd))
        share = 0.5 * (np.mean(hit_mssd, axis=1) + np.mean(hit_mspd, axis=1))  # each crop's part of val_ar
        self.last_shares = share
        se = standard_error(share)
        out = {
            "val_ar": 0.5 * (ar_mssd + ar_mspd),
            "val_ar_se": float("nan") if se is None else se,
            "val_ar_mssd": ar_mssd,
            "val_ar_mspd": ar_mspd,
        }
        for k in SUMMARY_KEYS:
            if k not in ("n", "missed"):  # every crop is estimated
                out[f"val_{k}"] = float("nan") if s[k] is None else float(s[k])
        return out


def _grid_shape(size: int) -> tuple[int, int]:
    """(viewpoints, in-plane angles) of about ``size`` rotations, in the library's 4000:120 ratio."""
    n_in = max(4, int(round((size / 33.3) ** 0.5)))
    return max(4, int(round(size / n_in))), n_in
