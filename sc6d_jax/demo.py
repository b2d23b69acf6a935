"""``sc6d demo``: the main job on the built-in objects, end to end.

1. writes the built-in object set (BOP ``models/``),
2. renders a BOP test set with clutter and occlusion,
3. runs the render-and-check (renderer vs geometry; a picture),
4. with a model (the shipped ``builtin`` model by default, ``--run RUN_DIR`` for another, or
   ``--train`` to train one with the ``cpu`` preset first): predicts every target from the
   ground-truth visible boxes (with fused 4-fold test-time augmentation; ``--no-tta`` without),
   evaluates with the BOP19 metrics, prints the AR table (overall, symmetric, asymmetric
   objects) and the pose-error breakdown (median rotation, depth and centre errors) and writes
   pictures: overlays of the estimated poses, rotation distributions on the sphere and AR per
   object.

Everything goes under ``--out`` (default ``sc6d-demo/``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path



def _step(msg: str) -> None:
    print(f"\n== {msg}", flush=True)


def _ar_groups(scores: dict, symmetric: set[int]) -> dict[str, float]:
    """Mean AR over the symmetric and the asymmetric objects (per-object ARs weighted by targets)."""
    groups: dict[str, list[tuple[float, int]]] = {"symmetric": [], "asymmetric": []}
    for obj_id, d in scores["per_object"].items():
        groups["symmetric" if int(obj_id) in symmetric else "asymmetric"].append((d["ar"], d["targets"]))
    out = {}
    for name, vals in groups.items():
        n = sum(t for _, t in vals)
        out[name] = sum(a * t for a, t in vals) / n if n else float("nan")
    return out




def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="sc6d demo", description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("sc6d-demo"), help="output folder (default sc6d-demo/)")
    ap.add_argument("--run", type=Path, default=None,
                    help="run directory or shipped model name to evaluate (default: the shipped builtin model)")
    ap.add_argument("--no-model", action="store_true", help="stop after rendering and the render-and-check")
    ap.add_argument("--train", action="store_true", help="train the cpu preset first (about an hour on 2 cores)")
    ap.add_argument("--steps", type=int, default=None, help="training steps with --train (preset's by default)")
    ap.add_argument("--scenes", type=int, default=2)
    ap.add_argument("--images-per-scene", type=int, default=6)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--tta", action=argparse.BooleanOptionalAction, default=True,
                    help="4-fold test-time augmentation, fused (default on; --no-tta: one look per crop)")
    ap.add_argument("--library-size", type=int, default=480_000, help="rotation library size (20000..1440000)")
    a = ap.parse_args(argv)
    if a.run is not None and a.train:
        raise ValueError("give either --run (an existing model) or --train (train one), not both")
    from sc6d_jax import pretrained

    if a.run is None and not a.train and not a.no_model and "builtin" in pretrained.available():
        a.run = Path("builtin")
    if a.run is not None:
        pretrained.check_run(a.run)  # a shipped name, or a path
    from sc6d_jax.check import main as check_main
    from sc6d_jax.objects import SYMMETRIC_IDS, write_models
    from sc6d_jax.render._dataset import DatasetSpec, render_dataset

    t0 = time.perf_counter()
    out = a.out
    out.mkdir(parents=True, exist_ok=True)
    models = out / "models"
    _step(f"built-in objects -> {models}")
    write_models(models, seed=a.seed, overwrite=True)
    dataset = out / "dataset"
    _step(f"rendering a BOP test set ({a.scenes} scenes x {a.images_per_scene} images) -> {dataset}")
    render_dataset(models, dataset, DatasetSpec(scenes=a.scenes, images_per_scene=a.images_per_scene, seed=a.seed),
                   overwrite=True)
    _step("render-and-check: renderer vs geometry")
    rc = check_main(["--out", str(out / "check.png"), "--seed", str(a.seed)])
    if rc:
        print("render-and-check FAILED", file=sys.stderr)
        return rc
    run = a.run
    if a.train:
        from sc6d_jax.train import preset, train

        run = out / "run"
        _step(f"training the cpu preset -> {run}")
        overrides = {} if a.steps is None else {"steps": a.steps}
        train(preset("cpu", **overrides), models, run, resume=(run / "checkpoints").is_dir())
    if run is None:
        _step("no model")
        print("Pass --run RUN_DIR to evaluate a trained model, or --train to train the cpu preset here.\n"
              f"Pictures: {out / 'check.png'}; dataset: {dataset}")
        print(f"\ndone in {time.perf_counter() - t0:.0f} s")
        return 0
    from sc6d_jax.inference.cli import main as predict_main
    from sc6d_jax.metrics.cli import main as eval_main

    results = out / "sc6d_builtin-test.csv"
    how = "4-fold test-time augmentation, fused" if a.tta else "no test-time augmentation"
    _step(f"predicting every target (ground-truth visible boxes, {how}) -> {results}")
    predict_main(["--run", str(run), "--dataset", str(dataset), "--out", str(results),
                  "--library-size", str(a.library_size)] + (["--tta"] if a.tta else []))
    _step("BOP19 evaluation")
    eval_main(["--dataset", str(dataset), "--results", str(results), "--out", str(out / "scores.json")])
    scores = json.loads((out / "scores.json").read_text())
    groups = _ar_groups(scores, set(SYMMETRIC_IDS))
    print(f"\nAR symmetric objects: {groups['symmetric']:.3f}   AR asymmetric objects: {groups['asymmetric']:.3f}")
    if scores.get("breakdown"):
        from sc6d_jax.metrics import format_breakdown_line

        print(format_breakdown_line(scores["breakdown"]["overall"]))
    from sc6d_jax.viz import write_eval_figures

    _step(f"pictures -> {out / 'figures'}")
    pics = write_eval_figures(dataset, results, out / "figures", run=run, scores=scores)
    print("\n".join(f"  {p}" for p in pics))
    print(f"\ndone in {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main(sys.argv[1:]))
