"""Learning curves: train several configurations on the same objects and validation crops, one
after the other, and plot validation AR, rotation error and depth error against training minutes
and crops per object.

    python experiments/learning_curve.py --out runs/lc1 --obj-ids 1 --steps 2000 \\
        --config base: --config norm:loss.z_norm=focal,loss.z_bins=log

Each ``--config NAME:KEY=VALUE,KEY=VALUE`` is a ``--set`` list applied to ``--preset`` (empty after
the colon = the preset itself). Every run validates at each checkpoint on the same held-out crops
(``sc6d_jax.train.validate``: the run's seed, never trained on), so the curves are a same-run
A/B. Runs are sequential (two cores run one training at a time) and resumable: a finished run is
skipped, an interrupted one resumed. Writes ``OUT/curves.csv`` (one row per run and checkpoint)
and ``OUT/curves.png``; ``--test-images N`` also renders N test images of the objects (clutter,
occlusion; the ``sc6d render`` set) and scores each run's final model on them with the BOP19 AR
and the pose-error breakdown (``OUT/test.csv``; ``--test-tta`` adds a row per run scored with
fused test-time augmentation, ``sc6d predict --tta``). ``--test-dataset DIR`` scores each final model on
an existing BOP test set instead (e.g. the real LM-O images, with ``--models DIR/models``; ground-
truth boxes, only the targets of the trained objects): one row per run and object in
``OUT/test.csv``, and a pooled row (object ``all``) with the AR over those targets. The test set
only scores the runs: choose between configurations on the validation curves or on principles
when the test set is the benchmark.

``--from-run NAME=RUN_DIR`` (repeatable) trains nothing: it reads the validation records of
existing runs (a training folder or a carried state, ``sc6d carry``) and writes their curves, e.g.
the long run's figure in the README, drawn from its last carried state (commit ``e3a5a9f``)::

    git checkout e3a5a9f -- experiments/state/long
    python experiments/learning_curve.py --out experiments/results/learning_curves \\
        --name long_14objects --from-run long=experiments/state/long

``--from-csv NAME=CSV:CONFIG`` (repeatable, alone or with ``--from-run``) takes the rows of one
configuration from a CSV this script wrote earlier (``experiments/results/learning_curves/``), so a
new run can be drawn beside a finished one whose run folder is gone; ``--x steps`` draws them
against training steps, for runs timed on different machines, ``--x crops`` against crops per
object (also for runs of different batch sizes).

Curves longer than three hours are drawn against hours instead of minutes. A run continued under
a changed stream or losses (``sc6d train --resume --amend``) gets a dotted line where it changed.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from sc6d_jax.metrics import standard_error  # noqa: E402
from sc6d_jax.train.loop import RAW_LOGGED as RAW  # noqa: E402  (validation of a moving average's raw parameters)

COLUMNS = ("config", "step", "train_min", "crops_per_object", "val_ar", "val_ar_se", "val_ar_diff_vs_first",
           "val_ar_diff_se", "val_rot_median_deg", "val_depth_rel_median", "val_centre_median_px",
           "val_rot_under_10", "val_rot_over_90", "val_depth_under_2pct", *RAW)


def parse_config(text: str) -> tuple[str, list[str]]:
    if ":" not in text:
        raise ValueError(f"--config expects NAME:KEY=VALUE,... (e.g. norm:loss.z_norm=focal), got {text!r}")
    name, _, rest = text.partition(":")
    if not name or any(c in name for c in "/ ,"):
        raise ValueError(f"--config name {name!r} must be non-empty without '/', ' ' or ','")
    items = [x for x in rest.split(",") if x]
    # a value may itself hold a comma (stream.distance=2.5,12): glue items without '=' to the previous one
    out: list[str] = []
    for x in items:
        if "=" in x or not out:
            out.append(x)
        else:
            out[-1] += "," + x
    return name, out


def curve_rows(name: str, run_dir: Path, base_dir: Path | None = None) -> list[dict]:
    """The validation records of one run as CSV rows; with ``base_dir`` (the first configuration's
    run), also the paired difference of val_ar from it at each step both validated on the same
    crops (``val_ar_diff_vs_first`` +- ``val_ar_diff_se``, from ``val_shares.jsonl``)."""
    cfg = json.loads((run_dir / "config.json").read_text())
    n_obj = len(cfg["stream"]["obj_ids"])
    bs = cfg["stream"]["batch_size"]
    mine = val_shares(run_dir)
    base = val_shares(base_dir) if base_dir is not None and base_dir != run_dir else {}
    rows = []
    for line in (run_dir / "metrics.jsonl").read_text().splitlines():
        rec = json.loads(line)
        if "val_ar" not in rec:
            continue
        rows.append({
            "config": name, "step": rec["step"], "train_min": rec["train_s"] / 60.0,
            "crops_per_object": rec["step"] * bs / n_obj,
            **{k: rec.get(k) for k in COLUMNS if k.startswith("val_")},
        })
        a, b = base.get(rec["step"]), mine.get(rec["step"])
        if a is not None and b is not None and a[0] == b[0] and len(a[1]) == len(b[1]) > 1:
            d = b[1] - a[1]
            rows[-1]["val_ar_diff_vs_first"] = float(d.mean())
            rows[-1]["val_ar_diff_se"] = standard_error(d)
    return rows


def val_shares(run_dir: Path) -> dict[int, tuple[str | None, "np.ndarray"]]:
    """step -> (crops fingerprint, each validation crop's share of val_ar) of a run (its folder,
    or its ``val_shares.jsonl`` itself; the last record of a step wins: a resumed run validates
    its step again); {} for runs before the file."""
    import numpy as np

    from sc6d_jax.train.loop import VAL_SHARES

    path = run_dir if run_dir.is_file() else run_dir / VAL_SHARES
    out = {}
    if path.is_file():
        for line in path.read_text().splitlines():
            rec = json.loads(line)
            out[int(rec["step"])] = (rec.get("crops"), np.asarray(rec["shares"], np.float64))
    return out


def amendment_marks(name: str, run_dir: Path, rows: list[dict], x_axis: str = "minutes") -> list[tuple[float, str]]:
    """(x, label) of each mid-run change of the run's config (``sc6d train --amend``), placed at
    the validation record of its step (an amendment starts at a checkpoint); x in the plot's
    ``x_axis`` units (training minutes, steps or crops per object, as :func:`x_values`)."""
    from sc6d_jax.train.loop import read_amendments

    mine = [r for r in rows if r["config"] == name]
    at = dict(zip((r["step"] for r in mine), x_values(mine, x_axis)))
    marks = []
    for a in read_amendments(run_dir):
        if a["step"] in at:
            fields = ", ".join(sorted({c.split(" ")[0] for c in a.get("changes", [])}))
            marks.append((at[a["step"]], f"{name}: from step {a['step']:,}: {fields}"))
    return marks


def x_values(rows: list[dict], x_axis: str, hours: bool = False) -> list[float]:
    """The x coordinates of one configuration's rows: training minutes (hours with ``hours``),
    steps, or crops per object (``x_axis`` "minutes", "steps", "crops")."""
    key = {"minutes": "train_min", "steps": "step", "crops": "crops_per_object"}[x_axis]
    return [float(r[key]) / (60 if hours and x_axis == "minutes" else 1) for r in rows]


def plot(rows: list[dict], path: Path, marks: list[tuple[float, str]] = (), x_axis: str = "minutes") -> None:
    """``marks``: (x in ``x_axis`` units, label) drawn as vertical lines (mid-run config changes).
    ``x_axis``: "minutes" (training time), "steps" or "crops" (crops per object; for runs from
    different machines, "crops" also for runs of different batch sizes)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    names = list(dict.fromkeys(r["config"] for r in rows))
    hours = x_axis == "minutes" and max((r["train_min"] for r in rows), default=0.0) > 180
    for name in names:
        rs = [r for r in rows if r["config"] == name]
        x = x_values(rs, x_axis, hours)
        lines = [axes[i].plot(x, [r[k] * (100 if i == 2 else 1) for r in rs], "o-", label=name)[0]
                 for i, k in enumerate(("val_ar", "val_rot_median_deg", "val_depth_rel_median"))]
        raw = [(xi, r) for xi, r in zip(x, rs) if r.get("val_raw_ar") is not None]
        if raw:  # a moving average is validated as val_*; its raw parameters beside it, dashed
            xr = [xi for xi, _ in raw]
            for i, k in enumerate(RAW):
                axes[i].plot(xr, [r[k] * (100 if i == 2 else 1) for _, r in raw], "x--", color=lines[i].get_color(),
                             alpha=0.6, label=f"{name}: raw parameters (val_* = their moving average)")
    for x_at, label in marks:  # x_at in x_axis units (minutes on a minutes axis, drawn in hours if hours)
        for i, ax in enumerate(axes):
            ax.axvline(x_at / 60 if hours else x_at, color="0.4", ls=":", lw=1.2, label=label if i == 0 else None)
    for ax, t in zip(axes, ("validation AR (MSSD, MSPD)", "median rotation error [deg]", "median depth error [%]")):
        ax.set_xlabel({"crops": "training crops per object", "steps": "training steps"}.get(
            x_axis, f"training {'hours' if hours else 'minutes'} (2 CPU cores)"))
        ax.set_title(t)
        ax.grid(alpha=0.3)
    from matplotlib.ticker import FuncFormatter, LogLocator

    for ax in axes[1:]:  # log scales, ticked in plain numbers (1, 1.5, 2, 3, 5, 7, 10, ...)
        ax.set_yscale("log")
        ax.yaxis.set_major_locator(LogLocator(subs=(1.0, 1.5, 2.0, 3.0, 5.0, 7.0)))
        ax.yaxis.set_minor_locator(LogLocator(subs="all"))
        ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        ax.yaxis.set_minor_formatter(FuncFormatter(lambda v, _: ""))
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True, help="output folder (runs, curves.csv, curves.png)")
    p.add_argument("--models", default=None, help="BOP models folder (default: the built-in objects, written to OUT/models)")
    p.add_argument("--preset", default="cpu")
    p.add_argument("--obj-ids", default="1", help="comma-separated object ids (default 1)")
    p.add_argument("--steps", type=int, default=2000)
    p.add_argument("--checkpoint-every", type=int, default=250)
    p.add_argument("--workers", type=int, default=1)
    p.add_argument("--config", action="append", default=[], help="NAME:KEY=VALUE,... (repeatable)")
    p.add_argument("--test-images", type=int, default=0, help="also score each final model on N rendered test images")
    p.add_argument("--test-dataset", default=None,
                   help="score each final model on this BOP test set (GT boxes; trained objects only)")
    p.add_argument("--from-run", action="append", default=[], metavar="NAME=RUN_DIR",
                   help="plot the validation records of an existing run (repeatable); trains nothing")
    p.add_argument("--from-csv", action="append", default=[], metavar="NAME=CSV:CONFIG",
                   help="plot the rows of CONFIG in an earlier curves CSV as NAME (repeatable; with --from-run "
                        "or alone); trains nothing")
    p.add_argument("--x", choices=("minutes", "steps", "crops"), default="minutes",
                   help="x axis of --from-run / --from-csv plots (steps: runs timed on different machines; crops: "
                        "crops per object, also for runs of different batch sizes)")
    p.add_argument("--test-tta", action="store_true",
                   help="also score each final model with fused test-time augmentation (sc6d predict --tta)")
    p.add_argument("--name", default="curves", help="file name of the CSV and the plot in OUT (default curves)")
    args = p.parse_args(argv)
    if args.from_run or args.from_csv:
        return _from_runs(args)
    os.environ.setdefault("MUJOCO_GL", "egl")
    try:
        configs = [parse_config(c) for c in (args.config or ["preset:"])]
    except ValueError as exc:
        print(f"learning_curve: error: {exc}", file=sys.stderr)
        return 2
    if len({n for n, _ in configs}) != len(configs):
        print("learning_curve: error: config names must be distinct", file=sys.stderr)
        return 2
    if args.test_dataset and not (Path(args.test_dataset) / "test_targets_bop19.json").is_file():
        print(f"learning_curve: error: --test-dataset {args.test_dataset}: not a BOP test set "
              "(no test_targets_bop19.json)", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    models = Path(args.models) if args.models else out / "models"
    if args.models is None and not models.is_dir():
        from sc6d_jax.objects import write_models

        write_models(models)
    from sc6d_jax.train.cli import main as train_main

    all_rows: list[dict] = []
    for name, sets in configs:
        run = out / name
        argv_t = ["--models", str(models), "--out", str(run), "--preset", args.preset, "--obj-ids", args.obj_ids,
                  "--steps", str(args.steps), "--checkpoint-every", str(args.checkpoint_every),
                  "--workers", str(args.workers)]
        for s in sets:
            argv_t += ["--set", s]
        if (run / "checkpoints").is_dir():
            argv_t.append("--resume")
        print(f"learning_curve: {name}: sc6d train {' '.join(argv_t)}", flush=True)
        rc = train_main(argv_t)
        if rc != 0:
            print(f"learning_curve: error: run {name} failed (exit {rc})", file=sys.stderr)
            return rc
        all_rows += curve_rows(name, run, out / configs[0][0])
        _write_csv(out / f"{args.name}.csv", all_rows, COLUMNS)
        plot(all_rows, out / f"{args.name}.png")
    if args.test_dataset:
        _test_dataset(args, out, [n for n, _ in configs])
    elif args.test_images:
        _test(args, out, models, [n for n, _ in configs])
    for name, _ in configs:
        last = [r for r in all_rows if r["config"] == name][-1]
        d = last.get("val_ar_diff_vs_first")
        vs = "" if d is None else f" ({d:+.3f} +- {last['val_ar_diff_se']:.3f} vs {configs[0][0]}, same crops)"
        print(f"{name:>16}: {last['train_min']:.1f} min, val AR {last['val_ar']:.3f}{_pm(last.get('val_ar_se'))}{vs}, "
              f"rotation {last['val_rot_median_deg']:.1f} deg, depth {100 * last['val_depth_rel_median']:.2f} %")
    print(f"learning_curve: wrote {out / (args.name + '.csv')} and {out / (args.name + '.png')}")
    return 0


def csv_rows(name: str, path: Path, config: str) -> list[dict]:
    """The rows of ``config`` in a curves CSV written by this script, renamed ``name``."""
    rows = []
    with open(path, newline="") as f:
        for r in csv.DictReader(f):
            if r["config"] != config:
                continue
            row: dict = {k: (float(v) if v not in ("", None) else None) for k, v in r.items() if k != "config"}
            row["step"] = int(row["step"])
            rows.append({**row, "config": name})
    return rows


def _from_runs(args) -> int:
    """``--from-run`` / ``--from-csv``: the curves of existing runs or CSVs, nothing trained."""
    csv_parts = []
    for item in args.from_csv:
        name, sep, rest = item.partition("=")
        path, sep2, config = rest.rpartition(":")
        if not (sep and sep2 and name and path and config):
            print(f"learning_curve: error: --from-csv expects NAME=CSV:CONFIG, got {item!r}", file=sys.stderr)
            return 2
        if not Path(path).is_file():
            print(f"learning_curve: error: --from-csv {path}: no such file", file=sys.stderr)
            return 2
        got = csv_rows(name, Path(path), config)
        if not got:
            print(f"learning_curve: error: --from-csv {path}: no rows of config {config!r}", file=sys.stderr)
            return 2
        csv_parts.append((name, got))
    runs = []
    for item in args.from_run:
        name, sep, d = item.partition("=")
        run = Path(d)
        if not sep or not name or not d:
            print(f"learning_curve: error: --from-run expects NAME=RUN_DIR, got {item!r}", file=sys.stderr)
            return 2
        if not (run / "metrics.jsonl").is_file() or not (run / "config.json").is_file():
            print(f"learning_curve: error: --from-run {d}: not a training run (no metrics.jsonl and config.json)",
                  file=sys.stderr)
            return 2
        runs.append((name, run))
    rows = [r for name, run in runs for r in curve_rows(name, run, runs[0][1])] + [r for _, got in csv_parts for r in got]
    if not rows:
        print("learning_curve: error: no validation records in those runs", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    _write_csv(out / f"{args.name}.csv", rows, COLUMNS)
    plot(rows, out / f"{args.name}.png", [m for name, run in runs for m in amendment_marks(name, run, rows, args.x)],
         x_axis=args.x)
    for name in [n for n, _ in runs] + [n for n, _ in csv_parts]:
        last = [r for r in rows if r["config"] == name][-1]
        print(f"{name:>16}: step {last['step']}, {last['train_min']:.1f} min, val AR {last['val_ar']:.3f}, rotation "
              f"{last['val_rot_median_deg']:.1f} deg, depth {100 * last['val_depth_rel_median']:.2f} %")
    print(f"learning_curve: wrote {out / (args.name + '.csv')} and {out / (args.name + '.png')}")
    return 0


def _write_csv(path: Path, rows: list[dict], columns) -> None:
    tmp = path.with_suffix(".tmp")
    with open(tmp, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(columns), extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    tmp.replace(path)


def run_scores(run: str | Path, ds: Path, out: Path, tag: str, predict_args: tuple[str, ...] = ()) -> dict:
    """The scores of a model (a run folder or a shipped name) on the test set ``ds``: ``sc6d predict``
    + ``sc6d eval`` into ``out/{tag}_results.csv`` and ``out/{tag}_scores.json``; kept, so a rerun
    skips them."""
    from sc6d_jax.cli import main as sc6d

    res, scores = out / f"{tag}_results.csv", out / f"{tag}_scores.json"
    if not scores.is_file():
        for cmd in (["predict", "--run", str(run), "--dataset", str(ds), "--out", str(res), *predict_args],
                    ["eval", "--dataset", str(ds), "--results", str(res), "--out", str(scores)]):
            rc = sc6d(cmd)
            if rc != 0:
                raise SystemExit(rc)
    return json.loads(scores.read_text())


def _scores(run: Path, ds: Path, tag: str, predict_args: tuple[str, ...] = ()) -> dict:
    """A run's scores kept in the run's own folder (``run_scores``)."""
    return run_scores(run, ds, run, tag, predict_args)


def _test(args, out: Path, models: Path, names: list[str]) -> None:
    """Render a test set of the objects once and score every run's final model on it."""
    from sc6d_jax.cli import main as sc6d

    ds = out / "testset"
    ids = args.obj_ids
    n_obj = len(ids.split(","))
    if not ds.is_dir():
        imgs = max(1, args.test_images // 2)
        rc = sc6d(["render", "--models", str(models), "--out", str(ds), "--scenes", "2", "--images-per-scene",
                   str(imgs), "--seed", "7", "--obj-ids", ids, "--objects-per-image", str(min(n_obj, 5))])
        if rc != 0:
            raise SystemExit(rc)
    rows, first = [], {}
    for name in names:
        for tta in ("none", "fuse") if args.test_tta else ("none",):
            sc = _scores(out / name, ds, "test" if tta == "none" else "test_tta", () if tta == "none" else ("--tta",))
            b = sc.get("breakdown", {}).get("overall", {})
            rows.append({"config": name, "tta": tta, "ar": sc["bop19_average_recall"],
                         **{k: sc.get(f"bop19_average_recall_{k[3:]}") for k in ("ar_vsd", "ar_mssd", "ar_mspd")},
                         "rot_median_deg": b.get("rot_median_deg"), "depth_rel_median": b.get("depth_rel_median"),
                         "centre_median_px": b.get("centre_median_px"), **_uncertainty(sc, first.setdefault(tta, sc))})
            r = rows[-1]
            print(f"{name:>16} (TTA {tta}): test AR {r['ar']:.3f}{_pm(r['ar_se'])}{_vs(r, names[0])}, "
                  f"rotation {b.get('rot_median_deg')}, depth {b.get('depth_rel_median')}")
    _write_csv(out / "test.csv", rows, ("config", "tta", "ar", "ar_se", "ar_diff_vs_first", "ar_diff_se", "ar_vsd",
                                        "ar_mssd", "ar_mspd", "rot_median_deg", "depth_rel_median",
                                        "centre_median_px"))


def _uncertainty(scores: dict, base: dict, obj_ids: list[int] | None = None) -> dict:
    """AR's standard error over the targets (``ar_se``) and the paired difference from ``base``, the
    first configuration's scores on the same targets (``ar_diff_vs_first`` +- ``ar_diff_se``):
    None where the scores predate per-target shares."""
    from sc6d_jax.metrics import paired_difference

    keep = None if obj_ids is None else set(obj_ids)
    shares = [r[4] for r in scores.get("per_target") or [] if keep is None or r[3] in keep]
    out = {"ar_se": standard_error(shares),
           "ar_diff_vs_first": None, "ar_diff_se": None}
    if base is not scores and scores.get("per_target") and base.get("per_target"):
        try:
            out["ar_diff_vs_first"], out["ar_diff_se"], _ = paired_difference(base, scores, obj_ids)
        except ValueError:
            pass
    return out


def _pm(se: float | None) -> str:
    return "" if se is None else f" +- {se:.3f}"


def _vs(row: dict, first: str) -> str:
    d = row.get("ar_diff_vs_first")
    return "" if d is None else f" ({d:+.3f}{_pm(row.get('ar_diff_se'))} vs {first}, same targets)"


BREAKDOWN_COLUMNS = ("rot_median_deg", "depth_rel_median", "centre_median_px", "rot_under_10", "rot_over_90")
TEST_DATASET_COLUMNS = ("config", "obj_id", "targets", "ar", "ar_se", "ar_diff_vs_first", "ar_diff_se", "ar_mssd",
                        "ar_mspd", "ar_vsd", *BREAKDOWN_COLUMNS)


def dataset_rows(name: str, scores: dict, obj_ids: list[int] | None, key: str = "config") -> list[dict]:
    """Rows of one model's scores on a test set (``key`` = ``name``): one per object of ``obj_ids``
    (every scored object when None), then a pooled ``all`` row (per-object recalls weighted by
    their targets: the recall the toolkit pools over targets; with every object, also the
    overall pose-error breakdown)."""
    per, bd = scores.get("per_object", {}), scores.get("breakdown", {})
    ids = sorted(int(k) for k in per) if obj_ids is None else obj_ids
    rows = []
    for o in ids:
        d, b = per.get(str(o)), bd.get("per_object", {}).get(str(o), {})
        if d is None or not d.get("targets"):
            continue
        rows.append({key: name, "obj_id": o, "targets": int(d["targets"]), "ar": d["ar"], "ar_mssd": d["ar_mssd"],
                     "ar_mspd": d["ar_mspd"], "ar_vsd": d.get("ar_vsd"),
                     **{k: b.get(k) for k in BREAKDOWN_COLUMNS}})
    n = sum(r["targets"] for r in rows)
    if n:
        pooled = {k: sum(r[k] * r["targets"] for r in rows) / n for k in ("ar", "ar_mssd", "ar_mspd")}
        if all(r["ar_vsd"] is not None for r in rows):
            pooled["ar_vsd"] = sum(r["ar_vsd"] * r["targets"] for r in rows) / n
        over = bd.get("overall", {}) if obj_ids is None else {}
        rows.append({key: name, "obj_id": "all", "targets": n, **pooled, **{k: over[k] for k in BREAKDOWN_COLUMNS
                                                                             if k in over}})
    return rows


def _test_dataset(args, out: Path, names: list[str]) -> None:
    """Score every run's final model on an existing BOP test set (GT boxes, trained objects)."""
    ds = Path(args.test_dataset)
    obj_ids = [int(x) for x in args.obj_ids.split(",")]
    rows, first = [], None
    for name in names:
        sc = _scores(out / name, ds, "testset")
        first = first or sc
        got = dataset_rows(name, sc, obj_ids)
        for r in got:
            r.update(_uncertainty(sc, first, obj_ids if r["obj_id"] == "all" else [r["obj_id"]]))
        rows += got
        for r in got:
            rot = r.get("rot_median_deg")
            print(f"{name:>16}: object {r['obj_id']}: {r['targets']} targets, AR {r['ar']:.3f}{_pm(r['ar_se'])}"
                  + _vs(r, names[0])
                  + ("" if rot is None else f", rotation {rot:.1f} deg, depth {100 * r['depth_rel_median']:.1f} %"))
    _write_csv(out / "test.csv", rows, TEST_DATASET_COLUMNS)


if __name__ == "__main__":
    sys.exit(main())
