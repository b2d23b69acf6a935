"""``sc6d eval``: BOP19 average recall of a results CSV on a BOP dataset.

    sc6d eval --dataset DIR --results METHOD_DATASET-SPLIT.csv --out SCORES.json [--split test]
              [--figures FIG_DIR [--run RUN_DIR]] [--oracle PART[,PART]]

Prints a table (overall and per object) and writes the scores as JSON with the BOP toolkit's key
names (bop19_average_recall, bop19_average_recall_vsd/_mssd/_mspd, bop19_average_time_per_image)
plus per-object recalls. It also prints and writes (key ``breakdown``) the pose-error breakdown
of the same targets (``sc6d_jax.metrics.summarize_breakdown``): median symmetry-aware rotation
error [deg], median relative depth error, median projected-centre error [px], the fractions
under 5/10/20 deg and 2/5 % depth, overall and per object; a target without an estimate counts
as a miss (180 deg, inf), and an infinite median is written as null. VSD needs depth images; where the dataset has none it is skipped, the
AR is the mean of AR_MSSD and AR_MSPD, and the output says so.

With ``--oracle rotation`` every estimate's rotation is replaced by the ground truth's before
scoring (``--oracle translation``: its translation), so that the AR measures the other head
alone (``sc6d_jax.metrics.with_ground_truth``; the scores JSON says ``"oracle"``): the two
oracles beside the plain AR show which head holds a model back. The translation splits into
``depth`` (the estimate moved along its own ray to the ground truth's z) and ``centre`` (onto
the ground truth's ray at its own z); parts combine with commas (``--oracle rotation,depth``).

With ``--figures DIR`` it then writes pictures (``sc6d_jax.viz.write_eval_figures``): overlays of
the estimated poses on the first images, a per-object AR bar chart and, with ``--run RUN_DIR``
(the model that made the results), rotation-distribution plots of a few targets.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

from sc6d_jax._io import atomic_write_json
from sc6d_jax.metrics._oracle import ORACLE_PARTS, POSE_PIECES, oracle_parts, oracle_pieces, with_ground_truth
from sc6d_jax.metrics._breakdown import GROUPINGS


def _fmt(v: Any) -> str:
    if v is None:
        return "   -  "
    return f"{float(v):.4f}"


def format_table(scores: dict[str, Any]) -> str:
    """The overall and per-object AR table printed by ``sc6d eval``."""
    lines = [f"{'object':>8}  {'targets':>7}  {'AR':>6}  {'AR_VSD':>6}  {'AR_MSSD':>7}  {'AR_MSPD':>7}"]
    for obj_id, d in scores["per_object"].items():
        lines.append(
            f"{obj_id:>8}  {d['targets']:>7}  {_fmt(d['ar']):>6}  {_fmt(d.get('ar_vsd')):>6}  "
            f"{_fmt(d['ar_mssd']):>7}  {_fmt(d['ar_mspd']):>7}"
        )
    lines.append(
        f"{'all':>8}  {scores['counts']['targets']:>7}  {_fmt(scores['bop19_average_recall']):>6}  "
        f"{_fmt(scores['bop19_average_recall_vsd']):>6}  {_fmt(scores['bop19_average_recall_mssd']):>7}  "
        f"{_fmt(scores['bop19_average_recall_mspd']):>7}"
    )
    se = scores.get("average_recall_standard_error")
    if se is not None:
        lines.append(f"AR standard error over the {scores['counts']['targets']} targets: {se:.4f} (compare two "
                     f"estimators on the same targets per target: sc6d_jax.metrics.paired_difference)")
    if not scores["vsd_available"]:
        lines.append(f"VSD skipped ({scores.get('vsd_skipped_reason', 'unavailable')}): AR = mean of AR_MSSD and AR_MSPD")
    t = scores.get("bop19_average_time_per_image", -1.0)
    if t is not None and t >= 0:
        lines.append(f"average time per image: {t:.4f} s")
    if scores.get("breakdown"):
        lines.append("")
        lines.append(format_breakdown_table(scores["breakdown"]))
    return "\n".join(lines)


def _bd_num(v: Any, scale: float = 1.0) -> str:
    return "inf" if v is None or not math.isfinite(float(v)) else f"{float(v) * scale:.1f}"


def _bd_signed(v: Any) -> str:
    return "-" if v is None or not math.isfinite(float(v)) else f"{100.0 * float(v):+.1f} %"


def _bd_pct(v: Any) -> str:
    return "-" if v is None else f"{100.0 * float(v):.0f}"


def format_breakdown_table(breakdown: dict[str, Any]) -> str:
    """The pose-error breakdown table of ``sc6d eval``: per object and overall.

    Columns: targets, targets without an estimate, median rotation error [deg] and % under 5 / 10 /
    20 deg and over 90 deg (turned the wrong way round), median relative depth error [%] and %
    under 2 / 5 %, median signed depth error [%] (positive = too far), median projected-centre
    error [px]; rows per object, overall, per visible fraction and per angle of the target's ray
    from the optical axis.
    """
    head = (f"{'object':>8}  {'targets':>7}  {'missed':>6}  {'rot_med':>7}  {'<5deg':>5}  {'<10deg':>6}  "
            f"{'<20deg':>6}  {'>90deg':>6}  {'depth_med':>9}  {'<2%':>4}  {'<5%':>4}  {'bias':>7}  {'centre_med':>10}")
    lines = ["pose-error breakdown (medians; % of targets under the thresholds; a target without an "
             "estimate counts as 180 deg, inf depth and centre errors)", head]

    def row(name: str, d: dict[str, Any]) -> str:
        return (f"{name:>8}  {d['n']:>7}  {d.get('missed', 0):>6}  {_bd_num(d['rot_median_deg']):>7}  "
                f"{_bd_pct(d['rot_under_5']):>5}  {_bd_pct(d['rot_under_10']):>6}  {_bd_pct(d['rot_under_20']):>6}  "
                f"{_bd_pct(d.get('rot_over_90')):>6}  "
                f"{_bd_num(d['depth_rel_median'], 100.0) + ' %':>9}  {_bd_pct(d['depth_under_2pct']):>4}  "
                f"{_bd_pct(d['depth_under_5pct']):>4}  {_bd_signed(d.get('depth_bias_median')):>7}  "
                f"{_bd_num(d['centre_median_px']) + ' px':>10}")

    for obj_id, d in breakdown["per_object"].items():
        lines.append(row(str(obj_id), d))
    lines.append(row("all", breakdown["overall"]))
    for g in GROUPINGS:
        if breakdown.get(g.key):
            lines.append(g.title)
            for label, d in breakdown[g.key].items():
                lines.append(row(label, d))
    return "\n".join(lines)


def _finite_or_none(v: Any) -> Any:
    """Non-finite floats -> None (JSON has no inf), recursively through dicts and lists."""
    if isinstance(v, float) and not math.isfinite(v):
        return None
    if isinstance(v, dict):
        return {k: _finite_or_none(x) for k, x in v.items()}
    if isinstance(v, list):
        return [_finite_or_none(x) for x in v]
    return v


def _jsonable(scores: dict[str, Any]) -> dict[str, Any]:
    out = dict(scores)
    out["per_object"] = {str(k): v for k, v in scores["per_object"].items()}
    for k, v in list(out.items()):
        if isinstance(v, float) and not math.isfinite(v):
            out[k] = None
    if isinstance(scores.get("breakdown"), dict):
        bd = scores["breakdown"]
        out["breakdown"] = _finite_or_none(
            {"overall": bd["overall"], "per_object": {str(k): v for k, v in bd["per_object"].items()},
             **{g.key: bd[g.key] for g in GROUPINGS if g.key in bd}}
        )
    return out


def _rest(oracle: str) -> str:
    """What an oracle of the comma-joined ``oracle`` parts leaves to the estimates, in words."""
    taken = oracle_pieces(oracle)
    rest = [p for p in POSE_PIECES if p not in taken]
    if rest == ["depth", "centre"]:
        return "the translation"
    return " and ".join(f"the {p}" for p in rest) if rest else "nothing of the estimates"


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="sc6d eval", description="BOP19 metrics (AR) of a results CSV.")
    ap.add_argument("--dataset", required=True, help="BOP dataset folder (models/, models_eval/, SPLIT/, test_targets_bop19.json)")
    ap.add_argument("--results", required=True, help="results CSV (scene_id,im_id,obj_id,score,R,t,time)")
    ap.add_argument("--out", required=True, help="output JSON with the scores")
    ap.add_argument("--split", default="test", help="dataset split folder (default: test)")
    ap.add_argument("--no-vsd", action="store_true", help="skip VSD even when the dataset has depth")
    ap.add_argument("--visib-gt-min", type=float, default=0.1,
                    help="minimum visible fraction of a ground truth to count (default 0.1; negative = the "
                         "toolkit's 'inst_count most visible' rule)")
    ap.add_argument("--no-progress", action="store_true", help="no progress bar")
    ap.add_argument("--figures", default=None, help="folder for figures (pose overlays, AR per object, "
                                                     "rotation distributions with --run)")
    ap.add_argument("--run", default=None, help="training run that made the results (rotation-distribution figures)")
    ap.add_argument("--n-images", type=int, default=4, help="images with overlays in --figures (default 4)")
    ap.add_argument("--oracle", default=None, metavar="PART[,PART]",
                    help=f"take these parts of every pose from the ground truth ({', '.join(ORACLE_PARTS)}; "
                         "depth: along the estimate's own ray, centre: onto the ground truth's ray at the "
                         "estimate's depth); the AR then measures the rest")
    args = ap.parse_args(argv)
    if args.oracle is not None:
        args.oracle = ",".join(oracle_parts(args.oracle))
    if args.run is not None and args.figures is None:
        raise ValueError("--run is only used with --figures DIR")
    if args.run is not None:
        from sc6d_jax.pretrained import check_run

        check_run(args.run)
    if args.oracle is not None and args.figures is not None:
        raise ValueError("--oracle and --figures do not go together: the figures show the results as they are")
    if args.n_images < 0:
        raise ValueError(f"--n-images must be >= 0, got {args.n_images}")

    from sc6d_jax.bop import BopDataset, read_results_csv
    from sc6d_jax.metrics._evaluate import evaluate_bop19

    ds = BopDataset(args.dataset, split=args.split)
    estimates = read_results_csv(args.results)
    if args.oracle is not None:
        estimates = with_ground_truth(ds, estimates, args.oracle)
    scores = evaluate_bop19(
        ds, estimates, renderer=None if args.no_vsd else "auto", visib_gt_min=args.visib_gt_min,
        progress=not args.no_progress,
    )
    if args.no_vsd and ds.has_depth():
        scores["vsd_skipped_reason"] = "--no-vsd"
    scores["dataset"] = Path(args.dataset).name
    scores["split"] = args.split
    scores["results"] = Path(args.results).name
    if args.oracle is not None:
        scores["oracle"] = args.oracle
        print(f"oracle: every estimate's {args.oracle.replace(',', ' and ')} taken from the ground truth "
              f"(the AR measures {_rest(args.oracle)} alone)")
    print(format_table(scores))
    atomic_write_json(args.out, _jsonable(scores))
    print(f"scores written to {args.out}")
    if args.figures is not None:
        from sc6d_jax.viz import write_eval_figures

        figs = write_eval_figures(args.dataset, args.results, args.figures, run=args.run, n_images=args.n_images,
                                  split=args.split, scores=_jsonable(scores))
        print(f"{len(figs)} figures written to {args.figures}")
    return 0
