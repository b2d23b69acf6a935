"""Compare finished models on one BOP test set, paired per target against the first.

    python experiments/compare_runs.py --dataset runs/big --out runs/compare_big \\
        --run fast=runs/cpu-h1-fast --run ray=runs/cpu-h1-ray --tta none,fuse \\
        --csv experiments/results/learning_curves/cpu_14objects_h1_ray_test.csv

Each ``--run NAME=RUN`` (a training folder or a shipped model's name, e.g. ``builtin``) is scored
by ``sc6d predict`` (``--tta`` for ``fuse``) and ``sc6d eval`` (ground-truth boxes) into
``OUT/NAME_none_*`` / ``OUT/NAME_tta_*``; scores already there are reused, so a rerun, or a run
added later, costs only what is new. Printed and written per run and TTA mode: BOP19 AR with its
standard error over the targets, the paired difference from the first run on the same targets
(``sc6d_jax.metrics.paired_difference``: much surer than either AR alone), AR_VSD / MSSD / MSPD,
and the pose-error breakdown's medians (rotation, depth, signed depth, centre).
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "experiments"))

from learning_curve import _uncertainty, run_scores  # noqa: E402

TTA_TAGS = {"none": ("none", ()), "fuse": ("tta", ("--tta",))}
COLUMNS = ("run", "tta", "targets", "ar", "ar_se", "ar_diff_vs_first", "ar_diff_se", "ar_vsd", "ar_mssd", "ar_mspd",
           "rot_median_deg", "depth_rel_median", "depth_bias_median", "centre_median_px")


def parse_runs(items: list[str]) -> list[tuple[str, str]]:
    """``NAME=RUN`` items -> [(name, run)], names unique and usable in file names."""
    out: list[tuple[str, str]] = []
    for item in items:
        name, sep, run = item.partition("=")
        if not sep or not name or not run:
            raise ValueError(f"--run must be NAME=RUN, got {item!r}")
        if not name.replace("-", "").replace("_", "").isalnum():
            raise ValueError(f"--run name {name!r}: use letters, digits, - and _ only")
        if name in (n for n, _ in out):
            raise ValueError(f"--run name {name!r} given twice")
        out.append((name, run))
    return out


def compare(dataset: Path, out: Path, runs: list[tuple[str, str]], ttas: list[str],
            predict_args: tuple[str, ...] = ()) -> list[dict]:
    """Score every run (cached in ``out``) and return one row per TTA mode and run."""
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for tta in ttas:
        tag, args = TTA_TAGS[tta]
        scores = {name: run_scores(run, dataset, out, f"{name}_{tag}", (*args, *predict_args)) for name, run in runs}
        base = scores[runs[0][0]]
        for name, _ in runs:
            s = scores[name]
            b = s.get("breakdown", {}).get("overall", {})
            rows.append({
                "run": name, "tta": tta, "targets": b.get("n"), "ar": s["bop19_average_recall"], **_uncertainty(s, base),
                **{k: s.get(f"bop19_average_recall_{k[3:]}") for k in ("ar_vsd", "ar_mssd", "ar_mspd")},
                **{k: b.get(k) for k in ("rot_median_deg", "depth_rel_median", "depth_bias_median", "centre_median_px")},
            })
    return rows


def _f(v, spec: str, scale: float = 1.0) -> str:
    return "-" if v is None else format(float(v) * scale, spec)


def format_rows(rows: list[dict]) -> str:
    lines = []
    for r in rows:
        diff = "" if r["ar_diff_vs_first"] is None else \
            f" ({r['ar_diff_vs_first']:+.3f} +- {_f(r['ar_diff_se'], '.3f')} paired)"
        lines.append(
            f"{r['tta']:>4} {r['run']:>12}: AR {r['ar']:.3f} +- {_f(r['ar_se'], '.3f')}{diff}, "
            f"VSD/MSSD/MSPD {_f(r['ar_vsd'], '.3f')}/{_f(r['ar_mssd'], '.3f')}/{_f(r['ar_mspd'], '.3f')}, "
            f"rotation {_f(r['rot_median_deg'], '.1f')} deg, depth {_f(r['depth_rel_median'], '.2f', 100)} % "
            f"(bias {_f(r['depth_bias_median'], '+.2f', 100)} %), centre {_f(r['centre_median_px'], '.1f')} px, "
            f"{r['targets']} targets")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--dataset", required=True, type=Path, help="BOP test set (ground-truth boxes)")
    p.add_argument("--out", required=True, type=Path, help="folder of the results and scores (reused)")
    p.add_argument("--run", action="append", required=True, help="NAME=RUN (repeatable; the first is the reference)")
    p.add_argument("--tta", default="none,fuse", help="comma-separated: none, fuse (default both)")
    p.add_argument("--library-size", type=int, help="rotation library size passed to sc6d predict")
    p.add_argument("--csv", type=Path, help="also write the rows to this CSV")
    args = p.parse_args(argv)
    try:
        runs = parse_runs(args.run)
        ttas = [t.strip() for t in args.tta.split(",") if t.strip()]
        bad = [t for t in ttas if t not in TTA_TAGS]
        if bad or not ttas:
            raise ValueError(f"--tta takes none and/or fuse, got {args.tta!r}")
        if not (args.dataset / "models").is_dir():
            raise ValueError(f"--dataset {args.dataset}: not a BOP dataset (no models/ folder)")
        from sc6d_jax.pretrained import is_name

        for name, run in runs:
            if not (Path(run).is_dir() or is_name(run)):
                raise ValueError(f"--run {name}={run}: neither a run folder nor a shipped model's name")
    except ValueError as e:
        print(f"compare_runs: error: {e}", file=sys.stderr)
        return 2
    extra = () if args.library_size is None else ("--library-size", str(args.library_size))
    rows = compare(args.dataset, args.out, runs, ttas, extra)
    print(format_rows(rows))
    if args.csv:
        args.csv.parent.mkdir(parents=True, exist_ok=True)
        tmp = args.csv.with_suffix(args.csv.suffix + ".tmp")
        with open(tmp, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=COLUMNS)
            w.writeheader()
            w.writerows(rows)
        tmp.replace(args.csv)
        print(f"compare_runs: wrote {args.csv}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
