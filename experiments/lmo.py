"""The real benchmark: train on MuJoCo renders of the 8 LM-O models, evaluate on real LM-O test images.

    python experiments/lmo.py --out DIR [--budget tiny|full] [--steps N] [--data ../shared/data/lmo]
                              [--run RUN_DIR|lmo] [--reference ../shared/REFERENCE.md]

Stages, each a separate ``python -m sc6d_jax.cli`` process (output in ``DIR/logs``):

1. ``sc6d train --models DATA/models --out DIR/run --preset P --workers 1 --resume``: the
   training stream renders the models (vertex colours baked, random backgrounds and occluders).
   The real test images are never used for training. ``--run`` skips this stage and uses an
   existing run directory or a shipped model name (``lmo``). A rerun of the same command resumes
   a killed training and skips a finished one.
2. ``sc6d predict --run RUN --dataset DATA --out DIR/sc6d_lmo-test.csv``: poses for every target
   of the objects the model knows, from the ground-truth visible boxes (no detector).
3. ``sc6d eval --dataset DATA --results ... --out DIR/scores.json --figures DIR/figures``: the
   dataset has no depth images, so VSD is skipped and the reported AR is the mean of AR_MSSD and
   AR_MSPD (checked here).
4. ``DIR/lmo.md`` + ``DIR/lmo.csv``: our row (AR_MSSD, AR_MSPD, their mean, training steps,
   training wall time, ms per image) beside the published LM-O numbers of other methods, read from
   the reference file (a heading that names LM-O followed by a Markdown table with a ``method``
   column and AR columns). Nothing is quoted from memory: without such a table the report says so.

Budgets: ``tiny`` = the tiny preset for 12 steps on objects 8 (driller) and 10 (eggbox,
symmetric), a 20k rotation library (a test runs it in about a minute; its AR is near zero);
``full`` = the cpu preset on all 8 objects and the default 480k library.
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import math
import re
import shlex
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

from sc6d_jax._subprocess import experiment_main, run_sc6d

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATA = REPO.parent / "shared" / "data" / "lmo"
DEFAULT_REFERENCE = REPO.parent / "shared" / "REFERENCE.md"
RESULTS_NAME = "sc6d_lmo-test.csv"  # BOP naming: METHOD_DATASET-SPLIT.csv


@dataclass(frozen=True)
class Budget:
    preset: str
    steps: int | None  # None = the preset's
    obj_ids: tuple[int, ...] | None  # None = every model in DATA/models
    library_size: int | None  # None = sc6d predict's default (480k)
    checkpoint_every: int | None = None
    overrides: tuple[str, ...] = ()  # sc6d train --set KEY=VALUE


BUDGETS: dict[str, Budget] = {
    "tiny": Budget(preset="tiny", steps=12, obj_ids=(8, 10), library_size=20_000, checkpoint_every=12,
                   overrides=("val_crops=0",)),
    # LM-O's test objects sit 3 to 11 diameters from the camera (the stream's default is 2.5-9);
    # photographs need the authors' colour augmentation, which the cpu preset leaves out for renders
    "full": Budget(preset="cpu", steps=None, obj_ids=None, library_size=None,
                   overrides=("stream.distance=2.5,12", "stream.colour_p=0.8")),
}


def _say(msg: str) -> None:
    print(msg, flush=True)




# --------------------------------------------------------------------------- inputs
def check_data(data: Path) -> None:
    """FileNotFoundError naming the folder when ``data`` is not an LM-O BOP test set."""
    if not data.is_dir():
        raise FileNotFoundError(f"LM-O data folder not found: {data} (pass --data DIR, a BOP dataset folder)")
    missing = [n for n in ("models/models_info.json", "test_targets_bop19.json", "test")
               if not (data / n).exists()]
    if missing:
        raise FileNotFoundError(f"{data} is not a BOP test set: missing {', '.join(missing)}")


def _last_metrics(run_dir: Path) -> dict[str, Any] | None:
    path = run_dir / "metrics.jsonl"
    if not path.is_file():
        return None
    last = None
    for line in path.read_text(encoding="utf-8").splitlines():
        try:
            last = json.loads(line)
        except json.JSONDecodeError:
            continue
    return last


def loop_seconds(run_dir: Path) -> float | None:
    """Training-loop wall time from ``metrics.jsonl``: ``elapsed_s`` restarts at each resume, so
    the last value of every segment is summed."""
    path = run_dir / "metrics.jsonl"
    if not path.is_file():
        return None
    total, prev = 0.0, None
    for line in path.read_text(encoding="utf-8").splitlines():
        try:
            e = json.loads(line).get("elapsed_s")
        except (json.JSONDecodeError, AttributeError):
            continue
        if e is None:
            continue
        if prev is not None and e < prev:
            total += prev
        prev = float(e)
    return None if prev is None else total + prev


@dataclass(frozen=True)
class RunInfo:
    path: Path  # run directory or shipped checkpoint
    name: str  # as given to sc6d predict
    steps: int
    obj_ids: tuple[int, ...] | None  # None = all objects of the models folder it was trained on
    preset: str | None
    is_training_run: bool  # has config.json (rotation-distribution figures need it)


def run_info(run: str | Path) -> RunInfo:
    """Steps, objects and preset of a training run directory or a shipped model name."""
    from sc6d_jax import pretrained

    name = str(run)
    path, _ = pretrained.resolve(run)  # FileNotFoundError naming what is shipped
    path = Path(path)
    if (path / "config.json").is_file():
        from sc6d_jax.checkpoint import checkpoint_dirs

        cfg = json.loads((path / "config.json").read_text(encoding="utf-8"))
        found = checkpoint_dirs(path)
        if not found:
            raise FileNotFoundError(f"{path}: the training run has no checkpoint yet")
        steps, is_run = found[-1][0], True
    elif (path / "meta.json").is_file():
        meta = json.loads((path / "meta.json").read_text(encoding="utf-8"))
        cfg, steps, is_run = meta.get("config", {}), int(meta["step"]), False
    else:
        raise FileNotFoundError(f"{path}: --run is neither a training run (config.json) nor a shipped model (meta.json)")
    ids = (cfg.get("stream") or {}).get("obj_ids")
    return RunInfo(path=path, name=name, steps=int(steps), obj_ids=tuple(ids) if ids else None,
                   preset=cfg.get("preset"), is_training_run=is_run)


# --------------------------------------------------------------------------- stage 1: train
def _record(out: Path) -> dict[str, Any]:
    p = out / "lmo.json"
    return json.loads(p.read_text(encoding="utf-8")) if p.is_file() else {}


def _save_record(out: Path, rec: dict[str, Any]) -> None:
    from sc6d_jax._io import atomic_write_json

    atomic_write_json(out / "lmo.json", rec)


def train_stage(out: Path, data: Path, budget_name: str, steps: int | None, workers: int = 1) -> tuple[Path, float]:
    """Train (or resume, or skip a finished) ``DIR/run``; returns it and the training wall time
    accumulated over the invocations that trained."""
    budget = BUDGETS[budget_name]
    run_dir = out / "run"
    rec = _record(out)
    settings = {"budget": budget_name, "steps": steps}
    for k, v in settings.items():
        if k in rec and rec[k] != v:
            raise ValueError(f"{out} holds an experiment with {k}={rec[k]!r}; this command has {k}={v!r} "
                             "(use another --out)")
    rec.update(settings)
    _save_record(out, rec)
    target = steps if steps is not None else budget.steps
    if (run_dir / "config.json").is_file():
        from sc6d_jax.checkpoint import checkpoint_dirs

        cfg_steps = json.loads((run_dir / "config.json").read_text(encoding="utf-8")).get("steps")
        found = checkpoint_dirs(run_dir)
        if found and found[-1][0] == cfg_steps and (target is None or target == cfg_steps):
            _say(f"[1/4] train: finished earlier ({cfg_steps} steps in {run_dir})")
            return run_dir, float(rec.get("train_wall_s", float("nan")))
    args: list[Any] = ["train", "--models", data / "models", "--out", run_dir, "--preset", budget.preset,
                       "--workers", workers, "--resume", "--no-progress", "--quiet"]
    if target is not None:
        args += ["--steps", target]
    if budget.checkpoint_every is not None:
        args += ["--checkpoint-every", min(budget.checkpoint_every, target or budget.checkpoint_every)]
    if budget.obj_ids:
        args += ["--obj-ids", ",".join(map(str, budget.obj_ids))]
    for item in budget.overrides:
        args += ["--set", item]
    objs = ",".join(map(str, budget.obj_ids)) if budget.obj_ids else "all 8"
    resumed = (run_dir / "checkpoints").is_dir()
    _say(f"[1/4] train: preset {budget.preset}, {target or 'preset'} steps, objects {objs} -> {run_dir}"
         + (" (resuming)" if resumed else ""))
    t_start = time.perf_counter()

    def heartbeat() -> None:
        m = _last_metrics(run_dir)
        if m:
            _say(f"[1/4] train: step {m.get('step')}/{target or '?'}, loss {m.get('loss', float('nan')):.3f}, "
                 f"{time.perf_counter() - t_start:.0f} s")

    secs = run_sc6d(args, out / "logs" / "train.log", heartbeat=heartbeat,
                    every_s=30.0 if budget_name == "tiny" else 120.0)
    total = float(rec.get("train_wall_s", 0.0)) + secs
    rec["train_wall_s"] = total
    _save_record(out, rec)
    _say(f"[1/4] train: done in {secs:.0f} s")
    return run_dir, total


# --------------------------------------------------------------------------- stage 2-3
def predict_stage(out: Path, data: Path, run: RunInfo, library_size: int | None) -> Path:
    results = out / RESULTS_NAME
    args: list[Any] = ["predict", "--run", run.name, "--dataset", data, "--out", results, "--no-progress"]
    if library_size is not None:
        args += ["--library-size", library_size]
    _say(f"[2/4] predict: real test images with ground-truth visible boxes -> {results}")
    secs = run_sc6d(args, out / "logs" / "predict.log")
    n = sum(1 for _ in open(results, encoding="utf-8")) - 1
    _say(f"[2/4] predict: {n} estimates in {secs:.0f} s")
    return results


def eval_stage(out: Path, data: Path, results: Path, run: RunInfo) -> dict[str, Any]:
    scores_path = out / "scores.json"
    scores_path.unlink(missing_ok=True)  # never report the scores of an earlier prediction
    args: list[Any] = ["eval", "--dataset", data, "--results", results, "--out", scores_path, "--figures", out / "figures",
                       "--no-progress"]
    if run.is_training_run:
        args += ["--run", run.path]
    _say("[3/4] eval: BOP19 MSSD and MSPD (no depth images: no VSD)")
    secs = run_sc6d(args, out / "logs" / "eval.log")
    scores = json.loads(scores_path.read_text(encoding="utf-8"))
    check_scores(scores)
    _say(f"[3/4] eval: done in {secs:.0f} s; {(out / 'logs' / 'eval.log').read_text().count('VSD skipped')} "
         f"'VSD skipped' line(s) in the eval output")
    return scores


def check_scores(scores: dict[str, Any]) -> None:
    """The eval skipped VSD and its AR is the mean of AR_MSSD and AR_MSPD (ValueError otherwise)."""
    if scores.get("vsd_available") or scores.get("bop19_average_recall_vsd") is not None:
        raise ValueError("sc6d eval computed VSD on a dataset that should have no depth images")
    mssd, mspd, ar = (scores.get(k) for k in ("bop19_average_recall_mssd", "bop19_average_recall_mspd",
                                               "bop19_average_recall"))
    if mssd is None or mspd is None or ar is None or not math.isclose(ar, 0.5 * (mssd + mspd), abs_tol=1e-9):
        raise ValueError(f"sc6d eval's AR {ar} is not the mean of AR_MSSD {mssd} and AR_MSPD {mspd}")


def ms_per_image(results_csv: Path) -> float:
    """Median time per image in ms over the images after the first (whose time includes compiling)."""
    from sc6d_jax.bop import read_results_csv

    per_image: dict[tuple[int, int], float] = {}
    for e in read_results_csv(results_csv):
        per_image.setdefault((e.scene_id, e.im_id), float(e.time))
    times = [t for _, t in sorted(per_image.items())]
    times = sorted(times[1:] or times)
    if not times:
        return float("nan")
    mid = len(times) // 2
    return 1000.0 * (times[mid] if len(times) % 2 else 0.5 * (times[mid - 1] + times[mid]))


def subset_recall(scores: dict[str, Any], obj_ids: Sequence[int]) -> tuple[float, float, int]:
    """AR_MSSD and AR_MSPD over the targets of ``obj_ids`` only (per-object recalls weighted by
    their target counts: the same pooled recall the toolkit computes over all targets)."""
    per = scores.get("per_object", {})
    rows = [per[str(o)] for o in obj_ids if str(o) in per]
    n = sum(int(r["targets"]) for r in rows)
    if n == 0:
        return float("nan"), float("nan"), 0
    mssd = sum(r["ar_mssd"] * r["targets"] for r in rows) / n
    mspd = sum(r["ar_mspd"] * r["targets"] for r in rows) / n
    return mssd, mspd, n


# --------------------------------------------------------------------------- published numbers
_COLUMNS = {  # our field -> accepted header names (lower case, spaces/dashes as underscores)
    "method": ("method", "name"),
    "ar": ("ar", "ar_bop", "ar_lm_o", "ar_lmo"),
    "ar_vsd": ("ar_vsd", "vsd"),
    "ar_mssd": ("ar_mssd", "mssd"),
    "ar_mspd": ("ar_mspd", "mspd"),
    "training": ("training", "training_data", "train_data", "trained_on"),
    "boxes": ("boxes", "detections", "detector", "input"),
    "time": ("time", "time_s", "time_per_image", "time_per_image_s"),
    "source": ("source", "citation", "reference", "ref"),
}


def _norm_header(h: str) -> str:
    return re.sub(r"[\s\-/]+", "_", h.strip().strip("*`").lower()).strip("_")


def _number(text: str) -> float | None:
    m = re.search(r"-?\d+(?:\.\d+)?", text.replace(",", ""))
    if not m:
        return None
    v = float(m.group(0))
    return v / 100.0 if v > 1.0 else v  # BOP papers print AR in percent


def parse_published(text: str) -> list[dict[str, Any]]:
    """Published LM-O rows from Markdown: every table under a heading that names LM-O (``LM-O``
    or ``LMO``, any level) with a ``method`` column and at least one AR column. Values printed in
    percent are converted to fractions; absent cells are None."""
    rows: list[dict[str, Any]] = []
    in_section = False
    lines = text.splitlines()
    i = 0
    while i < len(lines):
        line = lines[i].strip()
        if line.startswith("#"):
            in_section = bool(re.search(r"\bLM-?O\b", line, flags=re.IGNORECASE))
            i += 1
            continue
        if not (in_section and line.startswith("|")):
            i += 1
            continue
        block = []
        while i < len(lines) and lines[i].strip().startswith("|"):
            block.append(lines[i].strip())
            i += 1
        cells = [[c.strip() for c in r.strip("|").split("|")] for r in block]
        if len(cells) < 3:
            continue
        header = [_norm_header(h) for h in cells[0]]
        col = {f: next((j for j, h in enumerate(header) if h in names), None) for f, names in _COLUMNS.items()}
        if col["method"] is None or all(col[k] is None for k in ("ar", "ar_mssd", "ar_mspd")):
            continue
        for r in cells[2:]:  # cells[1] is the |---| line
            get = lambda f: r[col[f]] if col[f] is not None and col[f] < len(r) else ""  # noqa: E731
            if not get("method"):
                continue
            rows.append({
                "method": get("method"),
                **{k: _number(get(k)) if get(k) else None for k in ("ar", "ar_vsd", "ar_mssd", "ar_mspd")},
                "training": get("training") or None, "boxes": get("boxes") or None,
                "time": get("time") or None, "source": get("source") or None,
            })
    return rows


def load_published(reference: Path) -> tuple[list[dict[str, Any]], str]:
    """Rows of the reference file and a sentence on where they come from (or why there are none)."""
    if not reference.is_file():
        return [], f"The reference file {reference} was not found: no published numbers are shown."
    rows = parse_published(reference.read_text(encoding="utf-8"))
    if not rows:
        return [], (f"{reference.name} holds no table of published LM-O numbers (a heading naming LM-O "
                    "followed by a Markdown table with a `method` column and AR columns), so none are shown; "
                    "nothing is quoted from memory.")
    return rows, f"Published rows are copied from {reference.name}; each names its source."


# --------------------------------------------------------------------------- stage 4: report
def _f(v: Any, nd: int = 3) -> str:
    return "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else f"{float(v):.{nd}f}"


def build_report(scores: dict[str, Any], run: RunInfo, all_obj_ids: Sequence[int], published: list[dict[str, Any]],
                 published_note: str, train_wall_s: float | None, ms_image: float, budget_name: str | None,
                 commands: Sequence[str], wall_note: str = "") -> tuple[str, str]:
    """``(markdown, csv)`` of the LM-O comparison."""
    trained = list(run.obj_ids) if run.obj_ids else list(all_obj_ids)
    mssd, mspd = scores["bop19_average_recall_mssd"], scores["bop19_average_recall_mspd"]
    ours_label = "sc6d-jax (ours)" + (f", {budget_name} budget" if budget_name else "")
    n_targets = scores["counts"]["targets"]
    ours_training = "MuJoCo renders of the models only (no real images)"
    ours_boxes = "ground-truth visible boxes"
    wall = "-" if train_wall_s is None or not math.isfinite(train_wall_s) else f"{train_wall_s:.0f} s"
    ours = [{
        "method": ours_label, "ar_mssd": mssd, "ar_mspd": mspd, "mean": 0.5 * (mssd + mspd), "ar": None,
        "objects": f"{len(trained)} of {len(all_obj_ids)}", "targets": n_targets, "training": ours_training,
        "boxes": ours_boxes, "steps": run.steps, "train_wall": wall, "ms_image": ms_image, "source": "this run",
    }]
    if len(trained) < len(all_obj_ids):
        s_mssd, s_mspd, s_n = subset_recall(scores, trained)
        ours.append({**ours[0], "method": ours_label + ", trained objects' targets only",
                     "ar_mssd": s_mssd, "ar_mspd": s_mspd,
                     "mean": 0.5 * (s_mssd + s_mspd) if s_n else float("nan"),
                     "objects": ",".join(map(str, trained)), "targets": s_n})
    pub = []
    for p in published:
        mean = 0.5 * (p["ar_mssd"] + p["ar_mspd"]) if p["ar_mssd"] is not None and p["ar_mspd"] is not None else None
        pub.append({"method": p["method"], "ar_mssd": p["ar_mssd"], "ar_mspd": p["ar_mspd"], "mean": mean,
                    "ar": p["ar"], "objects": "8 of 8", "targets": "full BOP19 test set",
                    "training": p["training"] or "-", "boxes": p["boxes"] or "detections", "steps": None,
                    "train_wall": "-", "ms_image": None, "time": p["time"], "source": p["source"] or "-"})

    md = [
        "# LM-O (Linemod-Occluded): real test images",
        "",
        f"Test data: {n_targets} targets (visible fraction >= 0.1) of {len(all_obj_ids)} objects in "
        f"{scores['counts']['images']} real images of LM-O scene 2 (a subset of the 200 BOP19 test images). "
        "There are no depth images, so VSD is not computed: **AR here is the mean of AR_MSSD and AR_MSPD** "
        "(BOP19 thresholds, MSPD scaled to 640 px width).",
        "",
        f"Ours: trained only on MuJoCo renders of the LM-O models (vertex colours baked to a texture, random "
        f"backgrounds and occluders), never on real images; {run.steps} training steps"
        + (f" (preset {run.preset})" if run.preset else "") + "; poses from the ground-truth visible boxes "
        "(no detector); no refinement. ms/image: median time per image on this machine's CPU (2 cores, "
        "shared), first image (compilation) left out." + (f" Training wall time: {wall_note}." if wall_note else ""),
        "",
        "| method | AR_MSSD | AR_MSPD | AR (MSSD+MSPD)/2 | AR incl. VSD | objects | targets | training data | "
        "boxes | steps | training wall time | ms/image | source |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in ours + pub:
        ms = _f(r["ms_image"], 1) if r["ms_image"] is not None else (r.get("time") or "-")
        md.append(f"| {r['method']} | {_f(r['ar_mssd'])} | {_f(r['ar_mspd'])} | {_f(r['mean'])} | {_f(r['ar'])} | "
                  f"{r['objects']} | {r['targets']} | {r['training']} | {r['boxes']} | "
                  f"{r['steps'] if r['steps'] is not None else '-'} | {r['train_wall']} | {ms} | {r['source']} |")
    md += ["", published_note]
    if pub:
        md += ["", "The published methods were evaluated by the BOP toolkit on the full LM-O BOP19 test set (200 "
               "images), with their own detections unless a row says otherwise, and their AR includes VSD; "
               "compare AR_MSSD and AR_MSPD where a row gives them. Our subset of 50 images is not the same "
               "test set, so the comparison is indicative."]
    md += ["", "Per object (ours):", "", "| object | targets | AR_MSSD | AR_MSPD | AR (MSSD+MSPD)/2 | trained |",
           "|---|---|---|---|---|---|"]
    for oid, d in scores.get("per_object", {}).items():
        md.append(f"| {oid} | {d['targets']} | {_f(d['ar_mssd'])} | {_f(d['ar_mspd'])} | {_f(d['ar'])} | "
                  f"{'yes' if int(oid) in trained else 'no'} |")
    md += ["", "Commands:", "", "```"] + list(commands) + ["```", ""]

    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["method", "AR_MSSD", "AR_MSPD", "AR_mean_MSSD_MSPD", "AR_with_VSD", "objects", "targets",
                "training_data", "boxes", "train_steps", "train_wall_s", "ms_per_image", "source"])
    for r in ours + pub:
        w.writerow([r["method"], _f(r["ar_mssd"], 4), _f(r["ar_mspd"], 4), _f(r["mean"], 4), _f(r["ar"], 4),
                    r["objects"], r["targets"], r["training"], r["boxes"],
                    r["steps"] if r["steps"] is not None else "",
                    "" if r["train_wall"] == "-" else f"{train_wall_s:.1f}",
                    _f(r["ms_image"], 2) if r["ms_image"] is not None else "", r["source"]])
    return "\n".join(md), buf.getvalue()


# --------------------------------------------------------------------------- command line
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="lmo.py", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, required=True, help="experiment folder (created; rerun to resume)")
    p.add_argument("--budget", choices=sorted(BUDGETS), default="tiny")
    p.add_argument("--steps", type=int, default=None, help="training steps (tiny: 12; full: the cpu preset's)")
    p.add_argument("--workers", type=int, default=1,
                   help="renderer worker processes (the LM-O meshes, 12k-50k faces, render ~5x slower than "
                        "the built-in objects: 2 keeps a 2-core machine busy)")
    p.add_argument("--data", type=Path, default=DEFAULT_DATA, help="LM-O BOP folder (default ../shared/data/lmo)")
    p.add_argument("--run", default=None, help="skip training: a training run directory or a shipped name (lmo)")
    p.add_argument("--reference", type=Path, default=DEFAULT_REFERENCE,
                   help="Markdown file with the published LM-O numbers (default ../shared/REFERENCE.md)")
    return p


def experiment(args: argparse.Namespace) -> int:
    from sc6d_jax._io import atomic_write_text
    from sc6d_jax.bop import BopDataset

    data, out = args.data, args.out
    check_data(data)
    if args.steps is not None and args.steps <= 0:
        raise ValueError(f"--steps must be a positive integer, got {args.steps}")
    if args.run is not None and args.steps is not None:
        raise ValueError("--steps trains; it cannot be combined with --run (which skips training)")
    all_obj_ids = sorted(BopDataset(data).models_info)
    out.mkdir(parents=True, exist_ok=True)
    t_all = time.perf_counter()
    budget = BUDGETS[args.budget]
    if args.run is not None:
        run = run_info(args.run)
        _say(f"[1/4] train: skipped (--run {args.run}: {run.steps} steps)")
        wall = loop_seconds(run.path) if run.is_training_run else None
        wall_note = ("the training loop's elapsed_s in the run's metrics.jsonl, summed over resumed segments"
                     if wall is not None else "")
        budget_label = None
    else:
        run_dir, wall = train_stage(out, data, args.budget, args.steps, args.workers)
        run = run_info(run_dir)
        budget_label = args.budget
        wall_note = "the `sc6d train` processes of this experiment, start-up and compilation included"
    results = predict_stage(out, data, run, budget.library_size)
    scores = eval_stage(out, data, results, run)
    ms = ms_per_image(results)
    published, note = load_published(args.reference)
    commands = [f"python experiments/lmo.py {shlex.join(sys.argv[1:])}"] if sys.argv[1:] else []
    for stage in ("train", "predict", "eval"):
        log = out / "logs" / f"{stage}.log"
        if log.is_file() and (stage != "train" or args.run is None):
            commands.append(log.read_text(encoding="utf-8").splitlines()[0].removeprefix("$ "))
    md, csv_text = build_report(scores, run, all_obj_ids, published, note, wall, ms, budget_label, commands,
                               wall_note)
    atomic_write_text(out / "lmo.md", md)
    atomic_write_text(out / "lmo.csv", csv_text)
    _say("[4/4] report: " + str(out / "lmo.md") + ", " + str(out / "lmo.csv"))
    _say(md)
    _say(f"LM-O experiment finished in {time.perf_counter() - t_all:.0f} s")
    return 0


def main(argv: list[str]) -> int:
    args = build_parser().parse_args(argv)
    return experiment_main("lmo.py", lambda: experiment(args))

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
