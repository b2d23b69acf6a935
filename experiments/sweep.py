"""Experiment sweeps: the paper's ablation (Table 3) and SO(3) sample count (supplementary table).

    python experiments/sweep.py ablation --out DIR [--budget tiny|medium|full] [--seeds 0,1,2] [--rows A0,A4,TTA]
    python experiments/sweep.py so3-samples --run RUN_DIR|builtin --out DIR [--budget tiny|medium|full] [--sizes 20000,60000]
                                            [--no-refine] [--dataset BOP_DIR]

The IPDF row is the paper's variant: the full model (+ TTA) with an Implicit-PDF-style head,
as wide as the preset's SO(3) encoder, instead of the encoder. ``ablation.md`` also puts the
paper's row differences (``DELTAS``) beside ours (``deltas.csv``: paired over seeds, with their
separation in seed spreads).

Every configuration runs as separate processes (``sc6d train`` / ``sc6d predict`` / ``sc6d eval``
through ``python -m sc6d_jax.cli``) with fixed seeds. The built-in objects and a rendered BOP
test set are created once inside DIR. A run is finished when its scores JSON exists
(``DIR/scores/NAME.json``); a rerun of the same command skips finished runs, resumes a killed
training with ``sc6d train --resume`` and redoes only what is missing. Results: ``DIR/ablation.csv``
+ ``.md`` (mean and spread over seeds per row) and ``DIR/runs.csv`` (one line per run), or
``DIR/so3_samples.csv`` + ``.md``; figures (``DIR/*.png``) with :mod:`sc6d_jax.viz`.
``DIR/.gitignore`` leaves out the trainings, the data and the logs: a committed sweep folder
holds its scores, results and tables (a few hundred kB), so a rerun on a fresh machine skips
every finished run.

Budgets: ``tiny`` = the tiny preset for a few steps on objects 1 and 2 (one asymmetric, one
continuous symmetric), 1 scene x 2 images, a 20k library (a test runs a sweep in about a minute);
``medium`` = the cpu preset for 4,000 steps (about 14 minutes on 2 cores) on four objects of
different symmetry types (1 L-bracket: none, 3 cone: continuous, 5 box: three 180-degree
flips, 8 mug: none but a handle that can hide), 4 scenes x 10 images, the 480k library: 7 rows x
3 seeds (6 trainings per seed: TTA reuses A4's; IPDF's steps cost about twice the others') in
about 6 CPU-hours, resumable in legs;
``full`` = the cpu preset on all 14 built-in objects, 4 scenes x 10 images, the paper's 480k
library (an hour of training per run: 18 hours for 3 seeds).

The ablation's budgets other than tiny train with ``loss.w_z_l1=0``: the cpu recipe adds an L1
loss on the expectation-decoded depth to every depth head, which would blur the difference the
rows measure (how the depth bins are trained and decoded). The rows keep the rest of the cpu
recipe (GroupNorm(4), the focal-normalised depth code in log bins, the mask gate, local
negatives): the paper's choices of those did not learn at CPU budgets (README, Learning curves).
The ``medium`` budget also pins the learning rate (0.002) and the pose decoder (the paper's S/16,
``model.pose_downsample=2``) its runs trained with, so that a later change of the cpu preset does
not split its seeds.
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import math
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

from sc6d_jax._subprocess import experiment_main, run_sc6d

# --------------------------------------------------------------------------- configuration


@dataclass(frozen=True)
class Budget:
    preset: str
    steps: int | None  # None = the preset's
    obj_ids: tuple[int, ...] | None  # None = all built-in objects
    scenes: int
    images_per_scene: int
    objects_per_image: int
    library_size: int
    so3_sizes: tuple[int, ...]
    seeds: tuple[int, ...]
    checkpoint_every: int | None = None
    train_sets: tuple[str, ...] = ()
    workers: int | None = None  # renderer processes of the training stream (None = sc6d train's default)


BUDGETS: dict[str, Budget] = {
    "tiny": Budget(preset="tiny", steps=12, obj_ids=(1, 2), scenes=1, images_per_scene=2, objects_per_image=2,
                   library_size=20_000, so3_sizes=(20_000, 60_000), seeds=(0,), checkpoint_every=12,
                   train_sets=("stream.occlusion=0.0", "val_crops=0"), workers=0),
    "medium": Budget(preset="cpu", steps=4000, obj_ids=(1, 3, 5, 8), scenes=4, images_per_scene=10,
                     objects_per_image=4, library_size=480_000,
                     so3_sizes=(20_000, 60_000, 180_000, 480_000, 1_440_000), seeds=(0, 1, 2),
                     # the committed medium sweep's settings, pinned as the cpu preset moved on
                     checkpoint_every=1000, train_sets=("loss.w_z_l1=0", "optim.lr=0.002", "model.pose_downsample=2",
                                                        "stream.batch_size=32"),
                     workers=1),
    "full": Budget(preset="cpu", steps=None, obj_ids=None, scenes=4, images_per_scene=10, objects_per_image=5,
                   library_size=480_000, so3_sizes=(20_000, 60_000, 180_000, 480_000, 1_440_000), seeds=(0, 1, 2),
                   train_sets=("loss.w_z_l1=0",)),
}


@dataclass(frozen=True)
class Row:
    """One line of the ablation table: training overrides (``sc6d train --set``) + predict flags."""

    name: str
    label: str
    train: str  # name of the training this row evaluates (rows may share one)
    sets: tuple[str, ...]
    predict: tuple[str, ...] = field(default=())


# without the PE map the depth head has no ray either (the cpu preset reads it off the map)
_NO_PE = ("model.use_pe=false", "model.z_ray_input=false")
_PAPER_TTA = ("--tta", "--tta-mode", "best")
ROWS: tuple[Row, ...] = (
    Row("A0", "z regression", "A0", ("loss.z_mode=regression", "loss.z_loss=ce", *_NO_PE)),
    Row("A1", "z classification", "A1", ("loss.z_mode=classification", "loss.z_loss=ce", *_NO_PE)),
    Row("A2", "+ focal loss", "A2", ("loss.z_mode=classification", "loss.z_loss=focal", *_NO_PE)),
    Row("A3", "+ expectation", "A3", ("loss.z_mode=expectation", "loss.z_loss=focal", *_NO_PE)),
    Row("A4", "+ PE map", "A4", ("loss.z_mode=expectation", "loss.z_loss=focal", "model.use_pe=true")),
    # TTA as the paper's (the copy with the highest cosine; sc6d predict --tta fuses the copies)
    Row("TTA", "+ TTA (ours)", "A4", ("loss.z_mode=expectation", "loss.z_loss=focal", "model.use_pe=true"), _PAPER_TTA),
    # The paper's variant: the full model (+ TTA) with an Implicit-PDF head instead of the SO(3)
    # encoder (0.720 vs 0.739). Its MLP has the SO(3) encoder's hidden width (so3_hidden), so
    # that the two heads differ in how they score rotations, not in size.
    Row("IPDF", "+ TTA with an Implicit-PDF head", "IPDF",
        ("loss.z_mode=expectation", "loss.z_loss=focal", "model.use_pe=true", "model.rot_head=ipdf",
         "model.ipdf_hidden=@so3_hidden"), _PAPER_TTA),
)
ROW_BY_NAME = {r.name: r for r in ROWS}
METRICS = (("AR", "bop19_average_recall"), ("AR_MSSD", "bop19_average_recall_mssd"),
           ("AR_MSPD", "bop19_average_recall_mspd"), ("AR_VSD", "bop19_average_recall_vsd"))
#: The pose-error breakdown (``sc6d eval``'s ``breakdown.overall``) beside the recalls: the
#: median rotation error in degrees and the median relative depth error in per cent.
BREAKDOWN = (("rot_deg", "rot_median_deg", 1.0), ("depth_pct", "depth_rel_median", 100.0))
#: The paper's Table 3 (T-LESS, PBR training; ../shared/REFERENCE.md section 1) and the row
#: pairs whose differences it reports: (row, against, what the difference measures).
PAPER_AR = {"A0": 0.658, "A1": 0.707, "A2": 0.716, "A3": 0.718, "A4": 0.729, "TTA": 0.739, "IPDF": 0.720}
DELTAS = (("A1", "A0", "z classification over regression"), ("A2", "A1", "focal loss"),
          ("A3", "A2", "expectation decoding"), ("A4", "A3", "PE map"), ("TTA", "A4", "TTA"),
          ("TTA", "IPDF", "SO(3) encoder over an Implicit-PDF head"))


# --------------------------------------------------------------------------- processes


def run_eval(args: Sequence[Any], scores: Path, log: Path) -> None:
    """``sc6d eval ARGS --out`` a hidden name, renamed to ``scores`` once the command (figures
    included) has succeeded: the scores JSON exists only for finished runs."""
    tmp = scores.with_name(f".{scores.name}.partial")
    run_sc6d([*args, "--out", tmp], log)
    os.replace(tmp, scores)


def _say(msg: str) -> None:
    print(msg, flush=True)


def _parse_ints(text: str, what: str) -> tuple[int, ...]:
    try:
        vals = tuple(int(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise ValueError(f"{what} must be comma-separated integers, got {text!r}") from None
    if not vals:
        raise ValueError(f"{what} is empty")
    if any(v < 0 for v in vals):
        raise ValueError(f"{what} must be non-negative, got {text!r}")
    return vals


def _check_settings(out: Path, kind: str, settings: dict[str, Any]) -> None:
    """Record the sweep's settings in DIR/sweep.json; refuse to mix another budget into DIR."""
    from sc6d_jax._io import atomic_write_json, atomic_write_text

    path = out / "sweep.json"
    if path.is_file():
        saved = json.loads(path.read_text(encoding="utf-8"))
        for k in ("kind", "budget", "run"):
            if saved.get(k) != ({"kind": kind, **settings}).get(k):
                raise ValueError(
                    f"{out} holds a {saved.get('kind')} sweep with {k}={saved.get(k)!r}; this command has "
                    f"{k}={({'kind': kind, **settings}).get(k)!r} (use another --out)"
                )
    atomic_write_json(path, {"kind": kind, **settings})
    # committed, the folder keeps only what the tables are made of (and what a rerun skips on)
    atomic_write_text(out / ".gitignore", GITIGNORE)


#: DIR/.gitignore: the bulky, reproducible parts of a sweep folder; the scores JSONs, the results
#: CSVs and the tables stay, so a sweep folder can be committed and reruns skip its finished runs.
GITIGNORE = "# written by experiments/sweep.py\n/runs/\n/models/\n/dataset/\n/logs/\n/figures/\n"


def prepare_data(out: Path, budget: Budget, obj_ids: Sequence[int] | None) -> tuple[Path, Path]:
    """Built-in objects (``DIR/models``) and a rendered BOP test set (``DIR/dataset``), once."""
    models, dataset = out / "models", out / "dataset"
    if not (models / "models_info.json").is_file():
        _say(f"objects -> {models}")
        run_sc6d(["objects", "--out", models, "--overwrite"], out / "logs" / "objects.log")
    if not (dataset / "test_targets_bop19.json").is_file():
        _say(f"rendering {budget.scenes} scene(s) x {budget.images_per_scene} images -> {dataset}")
        args = ["render", "--models", models, "--out", dataset, "--scenes", budget.scenes,
                "--images-per-scene", budget.images_per_scene, "--objects-per-image", budget.objects_per_image,
                "--seed", 0, "--overwrite", "--no-progress"]
        if obj_ids:
            args += ["--obj-ids", ",".join(map(str, obj_ids))]
        run_sc6d(args, out / "logs" / "render.log")
    return models, dataset


# --------------------------------------------------------------------------- summaries
def _mean_std(vals: list[float]) -> tuple[float, float]:
    v = [x for x in vals if x is not None and math.isfinite(x)]
    if not v:
        return float("nan"), float("nan")
    m = sum(v) / len(v)
    s = math.sqrt(sum((x - m) ** 2 for x in v) / (len(v) - 1)) if len(v) > 1 else 0.0
    return m, s


def _csv_text(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(header)
    for r in rows:
        w.writerow(["" if (isinstance(x, float) and not math.isfinite(x)) else (f"{x:.4f}" if isinstance(x, float) else x) for x in r])
    return buf.getvalue()


def _fmt(m: float, s: float | None = None) -> str:
    if not math.isfinite(m):
        return "-"
    return f"{m:.3f}" if s is None else f"{m:.3f} ± {s:.3f}"


def _read_scores(path: Path) -> dict[str, Any]:
    return json.loads(path.read_text(encoding="utf-8"))


def _run_values(sc: dict[str, Any]) -> dict[str, float]:
    """The recalls and the breakdown of one run's scores JSON (NaN where absent)."""
    vals = {}
    for m, key in METRICS:
        v = sc.get(key)
        vals[m] = float("nan") if v is None else float(v)
    overall = (sc.get("breakdown") or {}).get("overall") or {}
    for m, key, scale in BREAKDOWN:
        v = overall.get(key)
        vals[m] = float("nan") if v is None else scale * float(v)
    return vals


def ablation_deltas(per_seed: dict[str, dict[int, dict[str, float]]], key: str = "AR") -> list[dict[str, Any]]:
    """The paper's row differences (:data:`DELTAS`) measured on the seeds both rows finished:
    the mean and sample std of the paired differences of ``key`` (the AR by default), the larger
    of the two rows' seed spreads, how many of those spreads the difference is, and whether the
    paper's sign holds."""
    out = []
    for a, b, what in DELTAS:
        seeds = sorted(set(per_seed.get(a, {})) & set(per_seed.get(b, {})))
        diffs = [per_seed[a][sd][key] - per_seed[b][sd][key] for sd in seeds]
        mean, std = _mean_std(diffs)
        spread = max(_mean_std([per_seed[r][sd][key] for sd in seeds])[1] for r in (a, b)) if seeds else float("nan")
        paper = PAPER_AR[a] - PAPER_AR[b]
        sep = abs(mean) / spread if seeds and spread > 0 else float("nan")
        same = "-" if not seeds else ("yes" if mean * paper > 0 else "no")
        out.append({"delta": f"{a} - {b}", "what": what, "n_seeds": len(seeds), "paper": paper, "mean": mean,
                    "std": std, "spread": spread, "separation": sep, "sign_reproduced": same})
    return out


def summarize_ablation(out: Path, rows: Sequence[Row], seeds: Sequence[int], budget_name: str) -> list[Path]:
    """ablation.csv/.md, runs.csv, deltas.csv and ablation.png from the finished runs' scores."""
    from sc6d_jax._io import atomic_write_text
    from sc6d_jax.viz import grouped_bar_chart, save_figure

    names = [m for m, _ in METRICS] + [m for m, _, _ in BREAKDOWN]
    per_run, table = [], []
    per_seed: dict[str, dict[int, dict[str, float]]] = {}
    for row in rows:
        vals: dict[str, list[float]] = {m: [] for m in names}
        done_seeds = []
        for seed in seeds:
            p = out / "scores" / f"{row.name}_s{seed}.json"
            if not p.is_file():
                continue
            sc = _read_scores(p)
            done_seeds.append(seed)
            v = _run_values(sc)
            per_seed.setdefault(row.name, {})[seed] = v
            for m in names:
                vals[m].append(v[m])
            t = sc.get("bop19_average_time_per_image")
            per_run.append([row.name, row.label, seed] + [v[m] for m in names] + [float(t) if t is not None else float("nan")])
        stats = {m: _mean_std(vals[m]) for m in names}
        table.append((row, done_seeds, stats))
    header = ["row", "description", "seed"] + names + ["time_per_image_s"]
    written = [atomic_write_text(out / "runs.csv", _csv_text(header, per_run))]
    agg_header = ["row", "description", "n_seeds", "paper_AR"] + [f"{m}_{k}" for m in names for k in ("mean", "std")]
    agg = [[r.name, r.label, len(s), PAPER_AR.get(r.name, float("nan"))] + [v for m in names for v in st[m]]
           for r, s, st in table]
    written.append(atomic_write_text(out / "ablation.csv", _csv_text(agg_header, agg)))
    deltas = ablation_deltas(per_seed)
    d_header = ["delta", "what", "n_seeds", "paper", "mean", "std", "spread", "separation", "sign_reproduced"]
    written.append(atomic_write_text(out / "deltas.csv", _csv_text(d_header, [[d[k] for k in d_header] for d in deltas])))
    md = [f"Ablation (paper Table 3) on the built-in objects, budget `{budget_name}`; "
          "mean ± sample std over seeds; rotation and depth: medians of the pose-error breakdown.", "",
          "| row | setting | seeds | AR | AR_MSSD | AR_MSPD | AR_VSD | rotation [deg] | depth [%] | paper AR |",
          "|---|---|---|---|---|---|---|---|---|---|"]
    for r, s, st in table:
        md.append(f"| {r.name} | {r.label} | {','.join(map(str, s)) or '-'} | "
                  + " | ".join(_fmt(*st[m]) for m in names) + f" | {PAPER_AR.get(r.name, float('nan')):.3f} |")
    md += ["", "Differences (paired over the seeds both rows finished; spread = the larger of the two rows' "
           "seed std; separation = |difference| / spread):", "",
           "| difference | what | seeds | paper | ours | separation | paper's sign |", "|---|---|---|---|---|---|---|"]
    for d in deltas:
        sep = "-" if not math.isfinite(d["separation"]) else f"{d['separation']:.1f}"
        md.append(f"| {d['delta']} | {d['what']} | {d['n_seeds']} | {d['paper']:+.3f} | "
                  + ("-" if not d["n_seeds"] else f"{d['mean']:+.3f} ± {d['std']:.3f}") + f" | {sep} | {d['sign_reproduced']} |")
    written.append(atomic_write_text(out / "ablation.md", "\n".join(md) + "\n"))
    shown = [(r, st) for r, s, st in table if s]
    if shown:
        fig = grouped_bar_chart(
            [r.name for r, _ in shown],
            {m: [st[m][0] for _, st in shown] for m, _ in METRICS},
            errors={m: [st[m][1] for _, st in shown] for m, _ in METRICS},
            ylabel="average recall", title=f"ablation ({budget_name} budget): mean ± std over seeds",
        )
        written.append(save_figure(fig, out / "ablation.png"))
    return written


# --------------------------------------------------------------------------- ablation
def _train_args(budget: Budget, models: Path, run_dir: Path, seed: int, sets: Sequence[str]) -> list[Any]:
    args: list[Any] = ["train", "--models", models, "--out", run_dir, "--preset", budget.preset, "--seed", seed,
                       "--resume", "--no-progress", "--quiet"]
    if budget.workers is not None:
        args += ["--workers", budget.workers]
    if budget.steps is not None:
        args += ["--steps", budget.steps]
    if budget.checkpoint_every is not None:
        args += ["--checkpoint-every", budget.checkpoint_every]
    if budget.obj_ids:
        args += ["--obj-ids", ",".join(map(str, budget.obj_ids))]
    for s in (*budget.train_sets, *sets):
        args += ["--set", _resolve_set(budget.preset, s)]
    return args


def _resolve_set(preset_name: str, item: str) -> str:
    """``model.X=@Y``: the value of the preset's ``model.Y`` (e.g. the IPDF row's width)."""
    key, _, value = item.partition("=")
    if not value.startswith("@"):
        return item
    from sc6d_jax.train import preset

    return f"{key}={getattr(preset(preset_name).model, value[1:])}"


def _training_finished(run_dir: Path) -> bool:
    """The newest checkpoint is at the configured last step."""
    cfg_path = run_dir / "config.json"
    if not cfg_path.is_file():
        return False
    from sc6d_jax.checkpoint import checkpoint_dirs

    found = checkpoint_dirs(run_dir)
    steps = json.loads(cfg_path.read_text(encoding="utf-8")).get("steps")
    return bool(found) and found[-1][0] == steps


def ablation(out: Path, budget_name: str, seeds: Sequence[int] | None, row_names: Sequence[str] | None,
             figures: bool = True) -> int:
    budget = BUDGETS[budget_name]
    seeds = tuple(seeds) if seeds else budget.seeds
    rows = [ROW_BY_NAME[n] for n in row_names] if row_names else list(ROWS)
    out.mkdir(parents=True, exist_ok=True)
    _check_settings(out, "ablation", {"budget": budget_name})
    models, dataset = prepare_data(out, budget, budget.obj_ids)
    jobs = [(r, s) for s in seeds for r in rows]
    t_all = time.perf_counter()
    for i, (row, seed) in enumerate(jobs, 1):
        tag = f"[ablation {i}/{len(jobs)}] {row.name} ({row.label}) seed {seed}"
        name = f"{row.name}_s{seed}"
        scores = out / "scores" / f"{name}.json"
        if scores.is_file():
            _say(f"{tag}: skipped (finished earlier: {scores.relative_to(out)})")
            continue
        t0 = time.perf_counter()
        run_dir = out / "runs" / f"{row.train}_s{seed}"
        logs = out / "logs"
        if _training_finished(run_dir):
            _say(f"{tag}: training {run_dir.name} finished earlier")
        else:
            resumed = (run_dir / "checkpoints").is_dir()
            _say(f"{tag}: training {run_dir.name}" + (" (resuming)" if resumed else ""))
            run_sc6d(_train_args(budget, models, run_dir, seed, row.sets), logs / f"{run_dir.name}.train.log")
        results = out / "results" / f"{name}.csv"
        if not results.is_file():
            run_sc6d(["predict", "--run", run_dir, "--dataset", dataset, "--out", results,
                      "--library-size", budget.library_size, "--no-progress", *row.predict],
                     logs / f"{name}.predict.log")
        ev = ["eval", "--dataset", dataset, "--results", results, "--no-progress"]
        if figures and seed == seeds[0]:
            ev += ["--figures", out / "figures" / name]
        run_eval(ev, scores, logs / f"{name}.eval.log")
        ar = _read_scores(scores).get("bop19_average_recall")
        _say(f"{tag}: done in {time.perf_counter() - t0:.0f} s, AR {ar if ar is None else round(ar, 4)}")
    paths = summarize_ablation(out, rows, seeds, budget_name)
    _say((out / "ablation.md").read_text(encoding="utf-8"))
    _say(f"ablation finished in {time.perf_counter() - t_all:.0f} s; wrote {', '.join(p.name for p in paths)}")
    return 0


# --------------------------------------------------------------------------- so3-samples
def ms_per_crop(results_csv: Path) -> float:
    """Median over images of (image time / crops in the image) in ms, leaving out the first image of
    each crop count (its time includes compiling the predictor) when others remain."""
    from sc6d_jax.bop import read_results_csv

    per_image: dict[tuple[int, int], list[float]] = {}
    for e in read_results_csv(results_csv):
        per_image.setdefault((e.scene_id, e.im_id), []).append(float(e.time))
    items = [(len(v), v[0]) for _, v in sorted(per_image.items())]
    if not items:
        return float("nan")
    seen: set[int] = set()
    warm = []
    for n, t in items:
        if n in seen:
            warm.append(t / n)
        seen.add(n)
    vals = sorted(warm or [t / n for n, t in items])
    mid = len(vals) // 2
    med = vals[mid] if len(vals) % 2 else 0.5 * (vals[mid - 1] + vals[mid])
    return 1000.0 * med


def so3_samples(run: Path, out: Path, budget_name: str, sizes: Sequence[int] | None, refine: bool,
                figures: bool = True, dataset: Path | None = None) -> int:
    from sc6d_jax._io import atomic_write_text
    from sc6d_jax.viz import grouped_bar_chart, save_figure

    from sc6d_jax import pretrained

    budget = BUDGETS[budget_name]
    path = pretrained.check_run(run)  # a run directory or a shipped model's name (builtin, lmo)
    if (path / "config.json").is_file():
        config = json.loads((path / "config.json").read_text(encoding="utf-8"))
    else:
        config = json.loads((path / "meta.json").read_text(encoding="utf-8"))["config"]
    obj_ids = config.get("stream", {}).get("obj_ids")
    sizes = tuple(sizes) if sizes else budget.so3_sizes
    out.mkdir(parents=True, exist_ok=True)
    _check_settings(out, "so3-samples", {"budget": budget_name,
                                         "run": str(run) if pretrained.is_name(run) else str(run.resolve())})
    if dataset is None:
        _, dataset = prepare_data(out, budget, obj_ids)
    elif not (dataset / "test_targets_bop19.json").is_file():
        raise FileNotFoundError(f"{dataset / 'test_targets_bop19.json'}: --dataset is not a BOP test set")
    configs = [(f"lib{n}", n, False) for n in sizes]
    if refine:
        configs.append((f"lib{min(sizes)}_refine", min(sizes), True))
    t_all = time.perf_counter()
    for i, (name, n, ref) in enumerate(configs, 1):
        tag = f"[so3-samples {i}/{len(configs)}] {n} rotations" + (" + refinement" if ref else "")
        scores = out / "scores" / f"{name}.json"
        if scores.is_file():
            _say(f"{tag}: skipped (finished earlier: {scores.relative_to(out)})")
            continue
        t0 = time.perf_counter()
        results = out / "results" / f"{name}.csv"
        if not results.is_file():
            run_sc6d(["predict", "--run", run, "--dataset", dataset, "--out", results, "--library-size", n,
                      "--no-progress", *(["--refine"] if ref else [])], out / "logs" / f"{name}.predict.log")
        ev = ["eval", "--dataset", dataset, "--results", results, "--no-progress"]
        if figures and i == 1:
            ev += ["--figures", out / "figures" / name]
        run_eval(ev, scores, out / "logs" / f"{name}.eval.log")
        ar = _read_scores(scores).get("bop19_average_recall")
        _say(f"{tag}: done in {time.perf_counter() - t0:.0f} s, AR {ar if ar is None else round(ar, 4)}, "
             f"{ms_per_crop(results):.1f} ms/crop")
    lines, md = [], [f"AR and time per crop by rotation-library size (run `{run.name}`, budget `{budget_name}`).", "",
                     "| library | refine | AR | AR_MSSD | AR_MSPD | AR_VSD | ms/crop |", "|---|---|---|---|---|---|---|"]
    for name, n, ref in configs:
        p = out / "scores" / f"{name}.json"
        if not p.is_file():
            continue
        sc = _read_scores(p)
        vals = [float("nan") if sc.get(k) is None else float(sc[k]) for _, k in METRICS]
        ms = ms_per_crop(out / "results" / f"{name}.csv")
        lines.append([n, int(ref), *vals, ms])
        md.append(f"| {n:,} | {'yes' if ref else 'no'} | " + " | ".join(_fmt(v) for v in vals) + f" | {ms:.1f} |")
    header = ["library_size", "refine"] + [m for m, _ in METRICS] + ["ms_per_crop"]
    written = [atomic_write_text(out / "so3_samples.csv", _csv_text(header, lines)),
               atomic_write_text(out / "so3_samples.md", "\n".join(md) + "\n")]
    if lines:
        labels = [f"{r[0] // 1000}k" + ("+ref" if r[1] else "") for r in lines]
        written.append(save_figure(grouped_bar_chart(labels, {m: [r[2 + j] for r in lines] for j, (m, _) in enumerate(METRICS)},
                                                     ylabel="average recall", title="AR by library size"),
                                   out / "so3_samples_ar.png"))
        written.append(save_figure(grouped_bar_chart(labels, {"ms per crop": [r[-1] for r in lines]}, ylabel="ms per crop",
                                                     title="time per crop (median over images)", ylim=None),
                                   out / "so3_samples_ms.png"))
    _say("\n".join(md))
    _say(f"so3-samples finished in {time.perf_counter() - t_all:.0f} s; wrote {', '.join(p.name for p in written)}")
    return 0


# --------------------------------------------------------------------------- command line
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="sweep.py", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="sweep", required=True)
    a = sub.add_parser("ablation", help="the paper's Table 3 (+ SO(3) encoder vs Implicit-PDF head)")
    a.add_argument("--out", type=Path, required=True, help="sweep folder (created; rerun to resume)")
    a.add_argument("--budget", choices=sorted(BUDGETS), default="tiny")
    a.add_argument("--seeds", default=None, help="comma-separated training seeds (tiny: 0; full: 0,1,2)")
    a.add_argument("--rows", default=None, help=f"comma-separated rows (default all: {','.join(ROW_BY_NAME)})")
    a.add_argument("--no-figures", action="store_true", help="no per-run evaluation figures")
    s = sub.add_parser("so3-samples", help="AR and ms per crop by rotation-library size")
    s.add_argument("--run", type=Path, required=True, help="trained run directory or a shipped model's name (builtin)")
    s.add_argument("--out", type=Path, required=True, help="sweep folder (created; rerun to resume)")
    s.add_argument("--budget", choices=sorted(BUDGETS), default="tiny")
    s.add_argument("--sizes", default=None, help="comma-separated library sizes (tiny: 20000,60000; full: 20k..1.44M)")
    s.add_argument("--no-refine", action="store_true", help="leave out the refined smallest library")
    s.add_argument("--no-figures", action="store_true", help="no evaluation figures")
    s.add_argument("--dataset", type=Path, default=None,
                   help="existing BOP dataset to evaluate on (default: built-in objects rendered into --out)")
    return p


def main(argv: list[str]) -> int:
    args = build_parser().parse_args(argv)
    return experiment_main("sweep.py", lambda: _run(args))


def _run(args: argparse.Namespace) -> int:
    if args.sweep == "ablation":
        seeds = _parse_ints(args.seeds, "--seeds") if args.seeds else None
        rows = None
        if args.rows:
            rows = [r.strip() for r in args.rows.split(",") if r.strip()]
            bad = [r for r in rows if r not in ROW_BY_NAME]
            if bad or not rows:
                raise ValueError(f"unknown row(s) {bad or args.rows!r}; rows: {', '.join(ROW_BY_NAME)}")
        return ablation(args.out, args.budget, seeds, rows, figures=not args.no_figures)
    sizes = _parse_ints(args.sizes, "--sizes") if args.sizes else None
    return so3_samples(args.run, args.out, args.budget, sizes, refine=not args.no_refine,
                       figures=not args.no_figures, dataset=args.dataset)

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
