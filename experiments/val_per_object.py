"""Each object's part of a run's validation AR, and its paired difference from another run.

    python experiments/val_per_object.py --run runs/long4w --models runs/objects/models \\
        --base runs/long3 --csv experiments/results/learning_curves/long4w_vs_long3_per_object.csv

A run validates on fixed crops and logs each crop's share of ``val_ar`` (``val_shares.jsonl``);
this script renders the same crops again through the run's own validator (its seed and stream
settings: the crops' digest must match the one logged) to learn which object each crop shows, and
prints, at every validated step, each object's AR over its crops. With ``--base`` (another run's
folder, or its ``val_shares.jsonl`` alone, e.g. from a commit: ``git show REV:PATH > FILE``) that
validated on the same crops, it also prints the paired difference per object and overall, with
the standard error over the crops (an easy crop is easy for both runs, so the difference is much
surer than either AR alone). Steps that only one of the two validated are left out of the
comparison. ``--csv`` writes one row per step and object (``all`` for the whole set).
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "experiments"))

from learning_curve import val_shares  # noqa: E402

from sc6d_jax.metrics import standard_error  # noqa: E402

COLUMNS = ("step", "obj_id", "crops", "ar", "base_ar", "diff", "diff_se")


def read_shares(path: Path) -> dict[int, tuple[str | None, np.ndarray]]:
    """step -> (crops digest, each crop's share of val_ar) from a run folder or a val_shares.jsonl
    file (``learning_curve.val_shares``); an error when there are none."""
    if not path.exists():
        raise FileNotFoundError(f"no validation shares at {path}")
    out = val_shares(path)
    if not out:
        raise ValueError(f"no validation records at {path} (runs log them since the per-crop shares were added)")
    return out


def crop_objects(run_dir: Path, models: Path) -> tuple[str, np.ndarray]:
    """(digest, object id of each validation crop) of a run, from its config."""
    from sc6d_jax.train.config import TrainConfig
    from sc6d_jax.train.validate import Validator

    cfg = TrainConfig.from_json((run_dir / "config.json").read_text())
    v = Validator(cfg, models, n=cfg.val_crops, lib_size=1000)
    return v.fingerprint, np.asarray(v.data["obj_id"], np.int64)


def per_object_rows(obj_id: np.ndarray, digest: str, mine: dict, base: dict | None = None) -> list[dict]:
    """One row per validated step and object (and ``all``), with the base's AR and the paired
    difference where the base validated the same step on the same crops."""
    groups = [(int(i), obj_id == i) for i in sorted(set(obj_id.tolist()))] + [("all", np.ones(len(obj_id), bool))]
    rows = []
    for step in sorted(mine):
        crops, s = mine[step]
        if crops is not None and crops != digest:
            raise ValueError(f"step {step}: the logged shares are of other crops ({crops}) than the run's validator "
                             f"renders ({digest}): not the run's own shares?")
        if len(s) != len(obj_id):
            raise ValueError(f"step {step}: {len(s)} logged shares for the validator's {len(obj_id)} crops")
        b = None
        if base is not None and step in base:
            bc, bs = base[step]
            if bc != digest or len(bs) != len(s):
                raise ValueError(f"step {step}: the base validated on other crops ({bc}) than the run ({digest}): "
                                 "no paired comparison")
            b = bs
        for name, m in groups:
            row = {"step": step, "obj_id": name, "crops": int(m.sum()), "ar": float(s[m].mean())}
            if b is not None:
                d = s[m] - b[m]
                row.update(base_ar=float(b[m].mean()), diff=float(d.mean()), diff_se=standard_error(d))
            rows.append(row)
    return rows


def format_table(rows: list[dict], key: str) -> str:
    """Steps down, objects across: ``key`` (``ar`` or ``diff``) of each."""
    objs = list(dict.fromkeys(r["obj_id"] for r in rows))
    steps = sorted({r["step"] for r in rows if r.get(key) is not None})
    at = {(r["step"], r["obj_id"]): r for r in rows}
    fmt = "{:+.2f}" if key == "diff" else "{:.2f}"
    lines = ["  step " + " ".join(f"{str(o):>5}" for o in objs)]
    for st in steps:
        cells = []
        for o in objs:
            r = at.get((st, o))
            f = fmt.replace(".2f", ".3f") if o == "all" else fmt
            cells.append(f"{f.format(r[key]):>5}" if r is not None and r.get(key) is not None else "    -")
        tail = ""
        if key == "diff" and at[(st, "all")].get("diff_se") is not None:
            tail = f"  (+- {at[(st, 'all')]['diff_se']:.3f})"
        lines.append(f"{st:6d} " + " ".join(cells) + tail)
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", type=Path, required=True, help="a training folder (or its carried state)")
    ap.add_argument("--models", type=Path, required=True, help="the BOP models folder the run trained on")
    ap.add_argument("--base", type=Path, help="another run's folder or val_shares.jsonl, validated on the same crops")
    ap.add_argument("--csv", type=Path, help="write one row per step and object here")
    a = ap.parse_args(argv)
    try:
        if not (a.run / "config.json").is_file():
            raise FileNotFoundError(f"{a.run} is not a training folder (no config.json)")
        mine = read_shares(a.run)
        base = read_shares(a.base) if a.base is not None else None
        digest, obj_id = crop_objects(a.run, a.models)
        rows = per_object_rows(obj_id, digest, mine, base)
    except (FileNotFoundError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"validation AR per object of {a.run} ({len(obj_id)} crops; crops per object: "
          + ", ".join(f"{r['obj_id']}: {r['crops']}" for r in rows if r["step"] == rows[0]["step"] and r["obj_id"] != "all")
          + ")")
    print(format_table(rows, "ar"))
    if base is not None:
        print(f"\npaired difference from {a.base} (run minus base; SE over the crops of the whole set)")
        print(format_table(rows, "diff"))
    if a.csv is not None:
        a.csv.parent.mkdir(parents=True, exist_ok=True)
        tmp = a.csv.with_name(a.csv.name + ".tmp")
        with tmp.open("w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=COLUMNS)
            w.writeheader()
            for r in rows:
                w.writerow({k: r.get(k, "") for k in COLUMNS})
        tmp.replace(a.csv)
        print(f"wrote {a.csv}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
