"""What a model's AR would be with parts of its poses perfect, or their errors shrunk: the ladder
from its results to a target.

    python experiments/oracle_ladder.py --dataset DIR --results RESULTS.csv --out DIR [--no-vsd]
                                        [--rotation-objects 8,9,12,13]

Scores one results CSV on its BOP dataset as it is and rewritten rung by rung
(``sc6d_jax.metrics.with_ground_truth``, as ``sc6d eval --oracle``): the rotation, the
translation, the depth (the estimate moved along its own ray to the true z) or the projected
centre (moved onto the true ray at its own z) from the ground truth, the ground-truth rotation
with the depth error shrunk to a half and a quarter (z' = z_gt (z / z_gt)^a along the estimate's
ray, a = 1/2, 1/4), and the ground-truth rotation with the true depth or the true centre; with
``--rotation-objects``, also the ground-truth rotation for those objects only (what a few hard
objects cost). Each
rung's BOP19 AR (VSD, MSSD, MSPD) and pose-error breakdown (median rotation, relative depth
and centre errors) go to ``DIR/oracle_ladder.csv`` and ``DIR/oracle_ladder.md`` and are
printed: which head, and how much better, a target such as AR 0.85 needs.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import io
import sys
from pathlib import Path
from typing import Any, Callable, Sequence

from sc6d_jax._subprocess import experiment_main

#: The ladder's rungs: name, description; the rewrite is ``rung_estimates``.
RUNGS = (
    ("as_estimated", "as estimated"),
    ("rotation", "rotation from the ground truth"),
    ("translation", "translation from the ground truth"),
    ("depth", "depth from the ground truth (along the estimate's ray)"),
    ("centre", "projected centre from the ground truth (at the estimate's depth)"),
    ("rotation,depth/2", "rotation from the ground truth, depth error halved"),
    ("rotation,depth/4", "rotation from the ground truth, depth error quartered"),
    ("rotation,depth", "rotation and depth from the ground truth (the centre left)"),
    ("rotation,centre", "rotation and centre from the ground truth (the depth left)"),
)


def shrink_depth_error(estimates: Sequence[Any], true_depth: Sequence[Any], a: float) -> list[Any]:
    """Each estimate moved along its own ray to ``z_gt * (z / z_gt) ** a``: its relative depth
    error shrunk to the power ``a`` (0: the true depth, 1: as it is). ``true_depth`` are the same
    estimates moved to the true depth (``with_ground_truth(..., "depth")``)."""
    if not 0.0 <= a <= 1.0:
        raise ValueError(f"the depth error's exponent must be in [0, 1], got {a}")
    return [dataclasses.replace(e, t=g.t * (e.t[2] / g.t[2]) ** a) for e, g in zip(estimates, true_depth)]


def rung_estimates(dataset: Any, estimates: Sequence[Any], rung: str) -> list[Any]:
    """``estimates`` rewritten for one rung of ``RUNGS``, or ``"rotation@1,5"``: the ground-truth
    rotation for objects 1 and 5 only."""
    from sc6d_jax.metrics import with_ground_truth

    if rung.startswith("rotation@"):
        ids = {int(x) for x in rung.split("@", 1)[1].split(",")}
        fixed = iter(with_ground_truth(dataset, [e for e in estimates if e.obj_id in ids], "rotation"))
        return [next(fixed) if e.obj_id in ids else e for e in estimates]
    if rung not in dict(RUNGS):
        raise ValueError(f"rung must be one of {[r for r, _ in RUNGS]}, got {rung!r}")
    if rung == "as_estimated":
        return list(estimates)
    if "/" in rung:  # "rotation,depth/N": the true rotation, z / z_gt to its N-th root (about 1/N the error)
        rotated = with_ground_truth(dataset, estimates, "rotation")
        return shrink_depth_error(rotated, with_ground_truth(dataset, rotated, "depth"), 1.0 / float(rung.split("/")[1]))
    return with_ground_truth(dataset, estimates, rung)


def ladder(dataset_dir: Path, results: Path, *, vsd: bool = True, rotation_objects: Sequence[int] = (),
           progress: Callable[[str], None] | None = None) -> list[dict[str, Any]]:
    """One row per rung: AR, VSD, MSSD, MSPD and the breakdown's medians (``progress(rung)``
    after each); ``rotation_objects`` adds the rung with their rotations alone from the ground
    truth."""
    from sc6d_jax.bop import BopDataset, read_results_csv
    from sc6d_jax.metrics import evaluate_bop19

    ds = BopDataset(dataset_dir)
    ests = read_results_csv(results)
    if not ests:
        raise ValueError(f"{results}: no estimates")
    rungs = list(RUNGS)
    if rotation_objects:
        ids = ",".join(str(int(i)) for i in rotation_objects)
        missing = sorted(set(int(i) for i in rotation_objects) - {e.obj_id for e in ests})
        if missing:
            raise ValueError(f"--rotation-objects: no estimates of objects {missing} in {results}")
        rungs.insert(2, (f"rotation@{ids}", f"rotation from the ground truth for objects {ids} only"))
    rows = []
    for rung, what in rungs:
        s = evaluate_bop19(ds, rung_estimates(ds, ests, rung), renderer="auto" if vsd else None)
        b = s["breakdown"]["overall"]
        rows.append({"rung": rung, "what": what, "ar": s["bop19_average_recall"],
                     "vsd": s["bop19_average_recall_vsd"], "mssd": s["bop19_average_recall_mssd"],
                     "mspd": s["bop19_average_recall_mspd"], "rot_median_deg": b["rot_median_deg"],
                     "depth_rel_median": b["depth_rel_median"], "centre_median_px": b["centre_median_px"],
                     "targets": s["counts"]["targets"]})
        if progress is not None:
            progress(rung)
    return rows


def _f(v: Any, fmt: str) -> str:
    return "-" if v is None else format(v, fmt)


def write_tables(rows: Sequence[dict[str, Any]], out: Path, command: str) -> list[Path]:
    from sc6d_jax._io import atomic_write_text

    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(rows[0]), lineterminator="\n")
    w.writeheader()
    w.writerows([{k: "" if v is None else v for k, v in r.items()} for r in rows])
    md = [f"The oracle ladder of one results CSV (`{command}`), {rows[0]['targets']} targets:", "",
          "| rung | AR | VSD | MSSD | MSPD | rotation | depth | centre |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        md.append(f"| {r['what']} | {r['ar']:.3f} | {_f(r['vsd'], '.3f')} | {r['mssd']:.3f} | {r['mspd']:.3f} | "
                  f"{r['rot_median_deg']:.1f} deg | {_f(r['depth_rel_median'] and 100 * r['depth_rel_median'], '.2f')} % | "
                  f"{_f(r['centre_median_px'], '.2f')} px |")
    out.mkdir(parents=True, exist_ok=True)
    return [atomic_write_text(out / "oracle_ladder.csv", buf.getvalue()),
            atomic_write_text(out / "oracle_ladder.md", "\n".join(md) + "\n")]


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="oracle_ladder.py", description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", required=True, help="the BOP dataset the results were made on")
    ap.add_argument("--results", required=True, help="a BOP results CSV")
    ap.add_argument("--out", required=True, help="folder for oracle_ladder.csv / .md")
    ap.add_argument("--no-vsd", action="store_true", help="skip VSD (AR = mean of MSSD and MSPD)")
    ap.add_argument("--rotation-objects", default="", help="comma-separated object ids: also a rung with "
                                                            "their rotations alone from the ground truth")
    args = ap.parse_args(argv)

    def body() -> int:
        for p in (args.dataset, args.results):
            if not Path(p).exists():
                raise FileNotFoundError(f"{p} does not exist")
        try:
            objs = [int(x) for x in args.rotation_objects.split(",") if x.strip()]
        except ValueError:
            raise ValueError(f"--rotation-objects must be comma-separated object ids, got {args.rotation_objects!r}")
        from tqdm import tqdm

        bar = tqdm(total=len(RUNGS) + bool(objs), desc="oracle ladder", unit="rung", file=sys.stderr)
        rows = ladder(Path(args.dataset), Path(args.results), vsd=not args.no_vsd, rotation_objects=objs,
                      progress=lambda r: bar.update(1))
        bar.close()
        command = "python experiments/oracle_ladder.py " + " ".join(argv if argv is not None else sys.argv[1:])
        paths = write_tables(rows, Path(args.out), command)
        print((Path(args.out) / "oracle_ladder.md").read_text(encoding="utf-8"))
        print("written: " + ", ".join(str(p) for p in paths))
        return 0

    return experiment_main("oracle_ladder.py", body)


if __name__ == "__main__":
    sys.exit(main())
