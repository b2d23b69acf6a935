"""Oracle rescoring of a finished ablation sweep: which head limits each row's AR, and how much
of the seed spread each head causes.

    python experiments/ablation_oracle.py --out experiments/results/ablation [--seeds 0,1,2]

For every finished run of ``experiments/sweep.py ablation`` (``DIR/results/NAME.csv``) it scores
two rewritten copies of the results on the sweep's own test set (``DIR/dataset``; the rewrite is
``sc6d_jax.metrics.with_ground_truth``, as ``sc6d eval --oracle``):

- ``gtR``: every estimate's rotation replaced by the ground truth's (the instance the box was
  cut from, the most visible one of the object, as ``sc6d predict`` picks it): the AR the run's
  translation alone reaches;
- ``gtt``: the translation replaced by the ground truth's: the AR its rotation alone reaches.

The paper's row differences whose rows differ only in the depth head (A1 - A0: classification
over regression; focal loss; expectation; PE map) are then measured again with the rotation
held perfect, and the one that differs only in the rotation head (TTA - IPDF) with the
translation held perfect: what is left is that head's effect without the other head's
seed-to-seed noise. Scores go to ``DIR/oracle/NAME.gtR.json`` / ``.gtt.json`` (a rerun skips
them); the tables to ``DIR/oracle.csv``, ``DIR/oracle_deltas.csv`` and ``DIR/oracle.md``, the
bars to ``DIR/oracle.png``.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import sys
from pathlib import Path
from typing import Any, Sequence

from sc6d_jax._subprocess import experiment_main

_HERE = Path(__file__).resolve().parent
_spec = importlib.util.spec_from_file_location("_sweep_for_oracle", _HERE / "sweep.py")
sweep = importlib.util.module_from_spec(_spec)
sys.modules[_spec.name] = sweep  # dataclasses look their module up while the file runs
_spec.loader.exec_module(sweep)

#: The oracle copies of each run (file suffix -> the part taken from the ground truth).
VARIANTS = {"gtR": "rotation", "gtt": "translation"}
#: Which oracle isolates the head each of the paper's differences changes.
DELTA_VARIANT = {"A1 - A0": "gtR", "A2 - A1": "gtR", "A3 - A2": "gtR", "A4 - A3": "gtR", "TTA - A4": "gtt",
                 "TTA - IPDF": "gtt"}


def oracle_estimates(dataset: Any, estimates: Sequence[Any], variant: str) -> list[Any]:
    """``estimates`` with R (``gtR``) or t (``gtt``) from the ground truth
    (:func:`sc6d_jax.metrics.with_ground_truth`)."""
    from sc6d_jax.metrics import with_ground_truth

    if variant not in VARIANTS:
        raise ValueError(f"variant must be one of {list(VARIANTS)}, got {variant!r}")
    return with_ground_truth(dataset, estimates, VARIANTS[variant])


def score_oracles(out: Path, names: Sequence[str]) -> dict[str, dict[str, float]]:
    """AR of each run's results and of its two oracle copies (computed once, then read back)."""
    from tqdm import tqdm

    from sc6d_jax._io import atomic_write_text
    from sc6d_jax.bop import BopDataset, read_results_csv
    from sc6d_jax.metrics import evaluate_bop19

    ds = BopDataset(out / "dataset")
    (out / "oracle").mkdir(exist_ok=True)
    ar: dict[str, dict[str, float]] = {}
    todo = [(n, v) for n in names for v in VARIANTS if not (out / "oracle" / f"{n}.{v}.json").is_file()]
    bar = tqdm(total=len(todo), desc="oracle", unit="score", file=sys.stderr, disable=not todo)
    for name in names:
        base = sweep._read_scores(out / "scores" / f"{name}.json")
        ar[name] = {"AR": float(base["bop19_average_recall"])}
        ests = None
        for v in VARIANTS:
            p = out / "oracle" / f"{name}.{v}.json"
            if not p.is_file():
                if ests is None:
                    ests = read_results_csv(out / "results" / f"{name}.csv")
                sc = evaluate_bop19(ds, oracle_estimates(ds, ests, v))
                keep = {k: sc[k] for k in ("bop19_average_recall", "bop19_average_recall_vsd",
                                            "bop19_average_recall_mssd", "bop19_average_recall_mspd", "counts")}
                atomic_write_text(p, json.dumps(keep, indent=1) + "\n")
                bar.update(1)
            ar[name][v] = float(json.loads(p.read_text(encoding="utf-8"))["bop19_average_recall"])
    bar.close()
    return ar


def oracle_tables(out: Path, seeds: Sequence[int]) -> list[Path]:
    from sc6d_jax._io import atomic_write_text

    names = [f"{r.name}_s{s}" for r in sweep.ROWS for s in seeds if (out / "scores" / f"{r.name}_s{s}.json").is_file()
             and (out / "results" / f"{r.name}_s{s}.csv").is_file()]
    if not names:
        raise ValueError(f"{out}: no finished ablation run with results (scores/NAME.json + results/NAME.csv)")
    ar = score_oracles(out, names)
    keys = ["AR", *VARIANTS]
    per_row: dict[str, dict[int, dict[str, float]]] = {}
    for n, vals in ar.items():
        row, seed = n.rsplit("_s", 1)
        per_row.setdefault(row, {})[int(seed)] = vals
    stats, md = [], ["Oracle rescoring of the ablation runs (`python experiments/ablation_oracle.py`): AR as run, "
                     "with the ground-truth rotation (`gtR`: what the translation alone reaches) and with the "
                     "ground-truth translation (`gtt`: what the rotation alone reaches); mean ± sample std over seeds.",
                     "", "| row | seeds | AR | AR, rotation from GT | AR, translation from GT |", "|---|---|---|---|---|"]
    for r in sweep.ROWS:
        d = per_row.get(r.name, {})
        if not d:
            continue
        st = {k: sweep._mean_std([d[s][k] for s in sorted(d)]) for k in keys}
        stats.append((r, len(d), st))
        md.append(f"| {r.name} | {','.join(map(str, sorted(d)))} | " + " | ".join(sweep._fmt(*st[k]) for k in keys) + " |")
    rows_csv = [[r.name, r.label, n] + [x for k in keys for x in st[k]] for r, n, st in stats]
    md += ["", "The paper's differences, measured as run and with the other head held perfect (paired over "
           "seeds; separation = |mean| / the larger of the two rows' seed std of that AR):", "",
           "| difference | what | seeds | paper | as run | separation | oracle | with the oracle | separation |",
           "|---|---|---|---|---|---|---|---|---|"]
    deltas = {k: sweep.ablation_deltas(per_row, k) for k in keys}
    d_rows = []
    for i, d in enumerate(deltas["AR"]):
        v = DELTA_VARIANT[d["delta"]]
        o = deltas[v][i]
        d_rows.append([d["delta"], d["what"], d["n_seeds"], d["paper"], d["mean"], d["std"], d["separation"], v,
                       o["mean"], o["std"], o["separation"]])
        f = lambda x: "-" if not x["n_seeds"] else f"{x['mean']:+.3f} ± {x['std']:.3f}"
        g = lambda x: "-" if not math.isfinite(x["separation"]) else f"{x['separation']:.1f}"
        md.append(f"| {d['delta']} | {d['what']} | {d['n_seeds']} | {d['paper']:+.3f} | {f(d)} | {g(d)} | {v} | "
                  f"{f(o)} | {g(o)} |")
    header = ["row", "description", "n_seeds"] + [f"{k}_{s}" for k in keys for s in ("mean", "std")]
    written = [atomic_write_text(out / "oracle.csv", sweep._csv_text(header, rows_csv))]
    d_header = ["delta", "what", "n_seeds", "paper", "mean", "std", "separation", "oracle", "oracle_mean",
                "oracle_std", "oracle_separation"]
    written.append(atomic_write_text(out / "oracle_deltas.csv", sweep._csv_text(d_header, d_rows)))
    written.append(atomic_write_text(out / "oracle.md", "\n".join(md) + "\n"))
    from sc6d_jax.viz import grouped_bar_chart, save_figure

    labels = {"AR": "as run", "gtR": "rotation from GT", "gtt": "translation from GT"}
    fig = grouped_bar_chart(
        [r.name for r, _, _ in stats],
        {labels[k]: [st[k][0] for _, _, st in stats] for k in keys},
        errors={labels[k]: [st[k][1] for _, _, st in stats] for k in keys},
        ylabel="average recall", title="ablation runs with one head from the ground truth (mean ± std over seeds)",
    )
    written.append(save_figure(fig, out / "oracle.png"))
    return written


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="ablation_oracle.py", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, required=True, help="a sweep folder of experiments/sweep.py ablation")
    p.add_argument("--seeds", default="0,1,2", help="comma-separated seeds (default 0,1,2; missing runs are left out)")
    return p


def main(argv: list[str]) -> int:
    args = build_parser().parse_args(argv)

    def body() -> int:
        if not (args.out / "dataset").is_dir():
            raise FileNotFoundError(f"{args.out / 'dataset'} does not exist: run experiments/sweep.py ablation "
                                    f"--out {args.out} first (it renders the test set)")
        paths = oracle_tables(args.out, sweep._parse_ints(args.seeds, "--seeds"))
        print((args.out / "oracle.md").read_text(encoding="utf-8"))
        print(f"wrote {', '.join(p.name for p in paths)}", file=sys.stderr)
        return 0

    return experiment_main("ablation_oracle.py", body)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
