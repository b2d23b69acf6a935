"""Where a run's pose errors come from: per object, per difficulty, and which way rotations go wrong.

    python experiments/error_anatomy.py --run runs/long --models runs/objects/models --out runs/anatomy \\
        [--step 64000] [--crops 512] [--lib 60000] [--raw]

Scores one checkpoint (its moving average unless ``--raw``) on the run's own validation crops
(the same seed: the first ``val_crops`` of them are the ones the run validates on) at four
settings that differ only in what surrounds the object and how the crop is cut:

- ``full``: the run's stream (textured backgrounds, occluders with the run's probability);
- ``no-occlusion``: the same, without occluders;
- ``plain``: plain one-colour backgrounds and no occluders;
- ``exact-box``: the run's stream, but each crop cut from the object's exact (amodal) box, as
  from a perfect detector: no box jitter, so the object fills the crop as it does at inference
  with ground-truth boxes of unoccluded objects (the other three keep the training jitter).

Per object and difficulty: the median symmetry-aware rotation error, the fraction of crops off
by more than 90 degrees, the median relative depth error and its signed median (a bias), and,
for the crops off by more than 90 degrees, the mean absolute axis of the error rotation
R_est^T R_gt in the object's frame. A large error about one fixed object axis is a confusion of
two poses that differ by a turn about that axis: an object that is nearly symmetric about it,
whose distinguishing detail the network has not resolved (a mug's cap, a dumbbell's band).
Writes ``OUT/anatomy.csv``, ``OUT/anatomy.json`` (with the overall figures per difficulty) and
``OUT/anatomy.png`` (per object: rotation and depth errors at each difficulty).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from sc6d_jax._subprocess import experiment_main  # noqa: E402

#: difficulty name -> StreamConfig overrides of the validation crops (None = the run's own)
DIFFICULTIES: dict[str, dict | None] = {
    "full": None,
    "no-occlusion": {"occlusion": 0.0},
    "plain": {"occlusion": 0.0, "background": "plain"},
    "exact-box": {"box_shift": 0.0, "box_scale": (1.0, 1.0)},
}
COLUMNS = ("difficulty", "obj_id", "n", "rot_median_deg", "rot_over_90", "depth_rel_median",
           "depth_signed_median", "axis_x", "axis_y", "axis_z")


def error_axis(R_est: np.ndarray, R_gt: np.ndarray, syms: np.ndarray | None = None) -> tuple[float, np.ndarray]:
    """(angle in degrees, unit axis up to sign, as absolute values) of R_est^T R_gt S, the error
    rotation in the object's frame, for the symmetry S (N,3,3; None = identity only) that makes
    it smallest."""
    from sc6d_jax.geometry import matrix_to_axis_angle

    R_est, R_gt = np.asarray(R_est, np.float64), np.asarray(R_gt, np.float64)
    cands = [R_est.T @ R_gt @ S for S in (np.eye(3)[None] if syms is None else np.asarray(syms, np.float64))]
    aa = np.asarray(matrix_to_axis_angle(max(cands, key=np.trace)), np.float64)  # largest trace: smallest angle
    ang = float(np.linalg.norm(aa))
    return float(np.degrees(ang)), np.abs(aa) / ang if ang > 0 else np.zeros(3)


def anatomy_rows(name: str, pred: dict, data: dict, syms: dict) -> list[dict]:
    """One row per object of crops ``data`` (R, t, K, obj_id per crop) estimated as ``pred``
    (R (n,3,3), t (n,3) mm); ``syms``: obj_id -> (N,3,3) symmetry rotations (identity included)."""
    from sc6d_jax.metrics._breakdown import pose_errors

    oids = data["obj_id"].astype(int)
    rot = np.array([pose_errors(pred["R"][i], pred["t"][i], data["R"][i].astype(np.float64),
                                data["t"][i].astype(np.float64), data["K"][i].astype(np.float64),
                                syms[int(oids[i])])["rot_deg"] for i in range(len(oids))])
    signed = (pred["t"][:, 2] - data["t"][:, 2]) / data["t"][:, 2]
    rows = []
    for o in sorted(set(oids.tolist())):
        m = np.where(oids == o)[0]
        big = [i for i in m if rot[i] > 90.0]
        axes = np.array([error_axis(pred["R"][i], data["R"][i], syms[o])[1] for i in big]) if big else np.full((1, 3), np.nan)
        ax = axes.mean(0)
        rows.append({"difficulty": name, "obj_id": o, "n": len(m),
                     "rot_median_deg": float(np.median(rot[m])), "rot_over_90": len(big) / len(m),
                     "depth_rel_median": float(np.median(np.abs(signed[m]))),
                     "depth_signed_median": float(np.median(signed[m])),
                     "axis_x": float(ax[0]), "axis_y": float(ax[1]), "axis_z": float(ax[2])})
    return rows


def figure(rows: list[dict], path: Path) -> Path:
    from sc6d_jax.viz import save_figure

    import matplotlib.pyplot as plt

    objs = sorted({r["obj_id"] for r in rows})
    fig, axes = plt.subplots(2, 1, figsize=(max(6.0, 0.6 * len(objs) + 2), 6), sharex=True)
    w = 0.8 / len(DIFFICULTIES)
    for k, name in enumerate(DIFFICULTIES):
        by = {r["obj_id"]: r for r in rows if r["difficulty"] == name}
        x = np.arange(len(objs)) + (k - (len(DIFFICULTIES) - 1) / 2) * w
        axes[0].bar(x, [by[o]["rot_median_deg"] if o in by else np.nan for o in objs], w, label=name)
        axes[1].bar(x, [100 * by[o]["depth_rel_median"] if o in by else np.nan for o in objs], w, label=name)
    axes[0].set_ylabel("median rotation error (deg)")
    axes[1].set_ylabel("median depth error (%)")
    axes[1].set_xticks(np.arange(len(objs)), [str(o) for o in objs])
    axes[1].set_xlabel("object id")
    axes[0].legend(fontsize=8)
    for a in axes:
        a.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    return save_figure(fig, path)


def checkpoint_parser(doc: str) -> argparse.ArgumentParser:
    """The arguments of the scripts that score one checkpoint of a run on its validation crops:
    --run, --models, --out, --step, --raw (this one and ring_profile.py)."""
    p = argparse.ArgumentParser(description=doc.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run", required=True, type=Path, help="a training run's directory")
    p.add_argument("--models", required=True, type=Path, help="the BOP models/ folder the run trained on")
    p.add_argument("--out", required=True, type=Path)
    p.add_argument("--step", type=int, default=None, help="checkpoint step (default: the newest)")
    p.add_argument("--raw", action="store_true", help="the raw parameters, not their moving average")
    return p


def load_scored_checkpoint(a: argparse.Namespace):
    """(step, params, config) of the checkpoint named by :func:`checkpoint_parser`'s arguments;
    a models folder without models_info.json or a folder that is not a run is refused."""
    from sc6d_jax.checkpoint import find_checkpoint, load_checkpoint, read_meta
    from sc6d_jax.pretrained import check_run

    if not (a.models / "models_info.json").is_file():
        raise FileNotFoundError(f"{a.models}: no models_info.json (not a BOP models/ folder)")
    run = check_run(a.run)
    step = int(read_meta(find_checkpoint(run, a.step))["step"])
    params, cfg = load_checkpoint(run, step, raw=a.raw)
    return step, params, cfg


def main(argv: list[str] | None = None) -> int:
    p = checkpoint_parser(__doc__)
    p.add_argument("--crops", type=int, default=512, help="validation crops per difficulty (default 512)")
    p.add_argument("--lib", type=int, default=60_000, help="rotation grid size (default 60,000, as validation)")
    a = p.parse_args(argv)

    def body() -> int:
        from sc6d_jax._io import atomic_write_text
        from sc6d_jax.train.validate import Validator

        if a.crops < 1 or a.lib < 1:
            raise ValueError("--crops and --lib must be positive")
        step, params, cfg = load_scored_checkpoint(a)
        rows, overall = [], {}
        for name, ov in DIFFICULTIES.items():
            v = Validator(cfg, a.models, n=a.crops, lib_size=a.lib, stream_overrides=ov)
            pred = v.predict(params)
            rows += anatomy_rows(name, pred, v.data, v.syms)
            overall[name] = v.score(pred)
            o = overall[name]
            print(f"{name:>13}: AR {o['val_ar']:.3f}, rotation {o['val_rot_median_deg']:.1f} deg, "
                  f"depth {100 * o['val_depth_rel_median']:.2f} %", flush=True)
        lines = [",".join(COLUMNS)] + [",".join(f"{r[c]:.4g}" if isinstance(r[c], float) else str(r[c])
                                                for c in COLUMNS) for r in rows]
        a.out.mkdir(parents=True, exist_ok=True)
        atomic_write_text(a.out / "anatomy.csv", "\n".join(lines) + "\n")
        atomic_write_text(a.out / "anatomy.json", json.dumps(
            {"run": str(a.run), "step": step, "raw": a.raw, "overall": overall, "objects": rows}, indent=1))
        figure(rows, a.out / "anatomy.png")
        print(f"{'difficulty':>13} obj  rot(deg) >90deg depth(%) bias(%)  axis of >90-degree errors (object frame)")
        for r in rows:
            axis = "" if np.isnan(r["axis_x"]) else f"({r['axis_x']:.2f}, {r['axis_y']:.2f}, {r['axis_z']:.2f})"
            print(f"{r['difficulty']:>13} {r['obj_id']:3d} {r['rot_median_deg']:9.1f} {r['rot_over_90']:6.2f} "
                  f"{100 * r['depth_rel_median']:8.2f} {100 * r['depth_signed_median']:+7.2f}  {axis}")
        print(f"wrote {a.out / 'anatomy.csv'}, anatomy.json, anatomy.png")
        return 0

    return experiment_main("error_anatomy", body)


if __name__ == "__main__":
    sys.exit(main())
