"""experiments/compare_runs.py: finished models scored on one test set, paired against the first."""

from __future__ import annotations

import csv
import dataclasses
import importlib.util
from pathlib import Path

import jax
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


def _module():
    spec = importlib.util.spec_from_file_location("compare_runs", ROOT / "experiments" / "compare_runs.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _run(d: Path, seed: int) -> Path:
    """A run folder with one checkpoint of a freshly initialised tiny model of the 14 built-in objects."""
    from sc6d_jax.model import init
    from sc6d_jax.train import StreamSettings, preset, save_checkpoint

    cfg = preset("tiny")
    cfg = cfg.replace(model=dataclasses.replace(cfg.model, n_objects=14),
                      stream=StreamSettings(batch_size=16, obj_ids=tuple(range(1, 15))), z_range=(20.0, 400.0))
    params = init(jax.random.PRNGKey(seed), cfg.model)
    save_checkpoint(d, 1, params, {}, np.zeros(2, np.uint32), cfg.to_dict(), extra_meta={"models_dir": None})
    return d


def test_compare_runs_pairs_each_run_with_the_first_and_reuses_scores(models, tmp_path, capsys):
    from sc6d_jax.render._dataset import DatasetSpec, render_dataset

    mod = _module()
    ds = render_dataset(models, tmp_path / "ds", DatasetSpec(scenes=1, images_per_scene=2, objects_per_image=3,
                                                             width=160, height=120, seed=5), progress=False)
    a, b = _run(tmp_path / "a", 0), _run(tmp_path / "b", 1)
    out, table = tmp_path / "cmp", tmp_path / "cmp.csv"
    argv = ["--dataset", str(ds), "--out", str(out), "--run", f"a={a}", "--run", f"same={a}", "--run", f"b={b}",
            "--library-size", "20000", "--csv", str(table)]
    assert mod.main(argv) == 0
    rows = list(csv.DictReader(open(table)))
    assert [(r["run"], r["tta"]) for r in rows] == [(n, t) for t in ("none", "fuse") for n in ("a", "same", "b")]
    for r in rows:
        assert 0.0 <= float(r["ar"]) <= 1.0 and int(r["targets"]) >= 3
        assert float(r["rot_median_deg"]) >= 0.0 and r["depth_bias_median"] != ""
    same = [r for r in rows if r["run"] == "same"]
    assert all(float(r["ar_diff_vs_first"]) == 0.0 and float(r["ar_diff_se"]) == 0.0 for r in same)
    assert all(r["ar_diff_vs_first"] == "" for r in rows if r["run"] == "a")
    printed = capsys.readouterr().out
    assert "paired" in printed and "bias" in printed
    # every model's results and scores are kept, and a rerun reuses them
    kept = sorted(p.name for p in out.iterdir())
    assert kept == sorted(f"{n}_{t}_{k}" for n in ("a", "same", "b") for t in ("none", "tta")
                          for k in ("results.csv", "scores.json"))
    stamp = {p.name: p.stat().st_mtime_ns for p in out.iterdir()}
    assert mod.main(argv[:-2]) == 0
    assert {p.name: p.stat().st_mtime_ns for p in out.iterdir()} == stamp


@pytest.mark.parametrize("runs, match", [
    (["a"], "NAME=RUN"),
    (["a=x", "a=y"], "given twice"),
    (["a b=x"], "letters, digits"),
    (["a=no/such/run"], "neither a run folder"),
])
def test_compare_runs_bad_input(tmp_path, capsys, runs, match):
    mod = _module()
    ds = tmp_path / "ds"
    (ds / "models").mkdir(parents=True)
    argv = ["--dataset", str(ds), "--out", str(tmp_path / "o")]
    for r in runs:
        argv += ["--run", r]
    assert mod.main(argv) == 2
    assert match in capsys.readouterr().err
    assert not (tmp_path / "o").exists()  # nothing half-written


def test_compare_runs_needs_a_bop_dataset(tmp_path, capsys):
    assert _module().main(["--dataset", str(tmp_path), "--out", str(tmp_path / "o"), "--run", "a=builtin"]) == 2
    assert "not a BOP dataset" in capsys.readouterr().err
