"""Poses from the dense head's object coordinates and PnP, against the network's own estimates.

    python experiments/pnp_probe.py --run runs/lc-pnp/xyz --models runs/objects/models --out runs/pnp \\
        [--step 6000] [--crops 512] [--min-mask 0.5] [--reproj 3]

A run trained with ``model.dense_xyz`` predicts, for each S/4 cell of its crop, the visible
surface's point in the object's own frame (in diameters). Those points and the cells' centres in
the crop form 2D-3D correspondences for a camera of the crop's own intrinsics K_B, and OpenCV's
RANSAC PnP gives a pose without the object's model (the network's coordinates stand in for it).
On the run's validation crops (its own seed, as ``error_anatomy.py``) this prints and writes
(``OUT/pnp.json``) the validation AR and breakdown of:

- ``network``: the run's estimate (library matching, the depth and centre heads);
- ``pnp``: the PnP pose (rotation and translation), where PnP finds one, else the network's;
- ``pnp_rot``: the PnP rotation with the network's translation;
- ``pnp_depth``: the network's rotation and centre with the PnP depth (along the network's ray);
- ``gated``: the PnP pose where its rotation lies within ``--gate`` degrees of the network's,
  else the network's (a symmetric object's coordinates are ambiguous: there the two disagree).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from sc6d_jax._subprocess import experiment_main  # noqa: E402
from error_anatomy import checkpoint_parser, load_scored_checkpoint  # noqa: E402


def dense_outputs(params, cfg, data: dict, batch: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """(xyz (n,h,w,3) in diameters, mask probability (n,h,w)) of the validation crops."""
    import jax
    import jax.numpy as jnp

    from sc6d_jax.model import apply

    mcfg = cfg.model
    fwd = jax.jit(lambda p, rgb, pe, o: apply(p, mcfg, rgb, pe if mcfg.use_pe else None, o))
    xyz, mask = [], []
    for s in range(0, len(data["rgb"]), batch):
        out = fwd(params, jnp.asarray(data["rgb"][s:s + batch]), jnp.asarray(data["pe"][s:s + batch]),
                  jnp.asarray(data["obj_idx"][s:s + batch]))
        xyz.append(np.asarray(out["dense"][..., -3:], np.float64))
        mask.append(np.asarray(jax.nn.sigmoid(out["mask_logit"]), np.float64))
    return np.concatenate(xyz), np.concatenate(mask)


def pnp_poses(xyz: np.ndarray, mask: np.ndarray, K_B: np.ndarray, diam: np.ndarray, crop: int,
              min_mask: float = 0.5, reproj: float = 3.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(R (n,3,3), t (n,3) mm, ok (n,) bool) by RANSAC PnP on the cells whose mask >= min_mask."""
    import cv2

    n, h, w, _ = xyz.shape
    f = crop / h
    v, u = np.meshgrid((np.arange(h) + 0.5) * f - 0.5, (np.arange(w) + 0.5) * f - 0.5, indexing="ij")
    R_out, t_out, ok = np.tile(np.eye(3), (n, 1, 1)), np.zeros((n, 3)), np.zeros(n, bool)
    for i in range(n):
        sel = mask[i] >= min_mask
        if sel.sum() < 6:
            continue
        obj = (xyz[i][sel] * diam[i]).astype(np.float64)
        img = np.stack([u[sel], v[sel]], -1).astype(np.float64)
        good, rvec, tvec, inl = cv2.solvePnPRansac(obj, img, K_B[i].astype(np.float64), None, reprojectionError=reproj,
                                                   iterationsCount=200, flags=cv2.SOLVEPNP_EPNP)
        if not good or inl is None or len(inl) < 6:
            continue
        idx = inl[:, 0]
        rvec, tvec = cv2.solvePnPRefineLM(obj[idx], img[idx], K_B[i].astype(np.float64), None, rvec, tvec)
        if tvec[2, 0] <= 0:
            continue
        R_out[i] = cv2.Rodrigues(rvec)[0]
        t_out[i] = tvec[:, 0]
        ok[i] = True
    return R_out, t_out, ok


def rot_deg(Ra: np.ndarray, Rb: np.ndarray) -> np.ndarray:
    c = (np.einsum("nij,nij->n", Ra, Rb) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def main(argv: list[str] | None = None) -> int:
    p = checkpoint_parser(__doc__)
    p.add_argument("--crops", type=int, default=512, help="validation crops (default 512)")
    p.add_argument("--min-mask", type=float, default=0.5, help="cells with this mask probability are used")
    p.add_argument("--reproj", type=float, default=3.0, help="RANSAC inlier threshold, crop pixels")
    p.add_argument("--gate", type=float, default=20.0, help="degrees: 'gated' keeps PnP within this of the network")
    a = p.parse_args(argv)

    def body() -> int:
        from sc6d_jax._io import atomic_write_text
        from sc6d_jax.geometry import crop_intrinsics, crop_transform
        from sc6d_jax.train.validate import Validator

        step, params, cfg = load_scored_checkpoint(a)
        if not cfg.model.dense_xyz:
            raise ValueError(f"{a.run}: not trained with model.dense_xyz; no object coordinates to use")
        v = Validator(cfg, a.models, n=a.crops)
        d = v.data
        net = v.predict(params)
        xyz, mask = dense_outputs(params, cfg, d)
        S = cfg.model.crop_size
        T = np.asarray(crop_transform(d["center"], d["side"], S), np.float64)
        K_B = np.asarray(crop_intrinsics(d["K"], T), np.float64)
        diam = np.array([v.diam[int(o)] for o in d["obj_id"]])
        R_p, t_p, ok = pnp_poses(xyz, mask, K_B, diam, S, a.min_mask, a.reproj)
        R_p = np.where(ok[:, None, None], R_p, net["R"])
        t_p = np.where(ok[:, None], t_p, net["t"])
        agree = rot_deg(R_p, net["R"]) <= a.gate
        z_ray = net["t"] * (t_p[:, 2] / net["t"][:, 2])[:, None]
        variants = {
            "network": net,
            "pnp": {"R": R_p, "t": t_p},
            "pnp_rot": {"R": R_p, "t": net["t"]},
            "pnp_depth": {"R": net["R"], "t": z_ray},
            "gated": {"R": np.where(agree[:, None, None], R_p, net["R"]), "t": np.where(agree[:, None], t_p, net["t"])},
        }
        res = {"run": str(a.run), "step": step, "crops": a.crops, "pnp_found": float(ok.mean()),
               "agree_within_gate": float(agree.mean()), "variants": {}}
        print(f"step {step}: PnP found a pose for {ok.mean():.0%} of {a.crops} crops; "
              f"within {a.gate:g} deg of the network's rotation: {agree.mean():.0%}")
        print(f"{'variant':<10} {'val AR':>7} {'+-':>6} {'rot deg':>8} {'depth %':>8} {'centre px':>9}")
        for name, pred in variants.items():
            s = v.score(pred)
            res["variants"][name] = s
            print(f"{name:<10} {s['val_ar']:7.3f} {s['val_ar_se']:6.3f} {s['val_rot_median_deg']:8.1f} "
                  f"{100 * s['val_depth_rel_median']:8.2f} {s['val_centre_median_px']:9.2f}")
        a.out.mkdir(parents=True, exist_ok=True)
        atomic_write_text(a.out / "pnp.json", json.dumps(res, indent=1))
        print(f"wrote {a.out / 'pnp.json'}")
        return 0

    return experiment_main("pnp_probe", body)


if __name__ == "__main__":
    raise SystemExit(main())
