"""experiments/sweep.py end to end (real sc6d train / predict / eval subprocesses on the tiny budget),
interruption and resume, so3-samples, ``sc6d eval --figures`` and ``sc6d train --set``."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
SWEEP = REPO / "experiments" / "sweep.py"
PNG = b"\x89PNG\r\n\x1a\n"


def _sweep(*args: str, timeout: float = 400) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SWEEP), *args], capture_output=True, text=True, timeout=timeout)


def _read_csv(path: Path) -> list[dict[str, str]]:
    with open(path, newline="", encoding="utf-8") as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def ablation_dir(tmp_path_factory) -> tuple[Path, str]:
    """Tiny ablation with rows A4 and TTA (two rows, one training: TTA evaluates A4's model with
    --tta): killed (whole process group) once A4 is finished, then rerun to completion. Returns
    the sweep folder and the rerun's output."""
    out = tmp_path_factory.mktemp("sweep") / "ablation"
    cmd = [sys.executable, str(SWEEP), "ablation", "--out", str(out), "--budget", "tiny", "--rows", "A4,TTA"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    first = out / "scores" / "A4_s0.json"
    deadline = time.monotonic() + 300
    try:
        while not first.is_file():
            if proc.poll() is not None:
                pytest.fail(f"sweep ended before A4 finished:\n{proc.stdout.read()}")
            if time.monotonic() > deadline:
                pytest.fail("A4 did not finish within 300 s")
            time.sleep(0.2)
        time.sleep(1.0)  # let the next row's prediction start, so that the kill interrupts it
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
    killed_out = proc.stdout.read()
    assert "A4 (+ PE map) seed 0: done" in killed_out
    assert not (out / "scores" / "TTA_s0.json").exists()
    mtime = first.stat().st_mtime_ns
    res = _sweep("ablation", "--out", str(out), "--budget", "tiny", "--rows", "A4,TTA")
    assert res.returncode == 0, res.stdout + res.stderr
    assert first.stat().st_mtime_ns == mtime  # the finished run was not redone
    return out, res.stdout


def test_ablation_resumes_and_writes_tables(ablation_dir):
    out, log = ablation_dir
    assert "[ablation 1/2] A4 (+ PE map) seed 0: skipped (finished earlier" in log
    assert "[ablation 2/2] TTA (+ TTA (ours)) seed 0: training A4_s0 finished earlier" in log  # shared, trained once
    assert "[ablation 2/2] TTA (+ TTA (ours)) seed 0: done" in log
    assert sorted(p.name for p in (out / "runs").iterdir()) == ["A4_s0"]
    # committed, the folder keeps its results and tables, not the runs, data and logs
    ignored = (out / ".gitignore").read_text().split()
    assert {"/runs/", "/models/", "/dataset/", "/logs/", "/figures/"} <= set(ignored)
    assert not {"/scores/", "/results/"} & set(ignored)
    # TTA evaluates the A4 training with --tta
    a4 = json.loads((out / "runs" / "A4_s0" / "config.json").read_text())
    assert (a4["loss"]["z_mode"], a4["loss"]["z_loss"], a4["model"]["use_pe"], a4["model"]["rot_head"]) == (
        "expectation", "focal", True, "so3")
    assert a4["seed"] == 0 and a4["stream"]["obj_ids"] == [1, 2] and a4["steps"] == 12
    assert "--tta --tta-mode best" in (out / "logs" / "TTA_s0.predict.log").read_text().splitlines()[0]  # the paper's
    assert "--tta" not in (out / "logs" / "A4_s0.predict.log").read_text().splitlines()[0]
    # tables agree with the scores JSONs
    runs = _read_csv(out / "runs.csv")
    assert [r["row"] for r in runs] == ["A4", "TTA"]
    agg = {r["row"]: r for r in _read_csv(out / "ablation.csv")}
    for r in runs:
        sc = json.loads((out / "scores" / f"{r['row']}_s0.json").read_text())
        assert float(r["AR"]) == pytest.approx(sc["bop19_average_recall"], abs=1e-4)
        assert float(agg[r["row"]]["AR_mean"]) == pytest.approx(sc["bop19_average_recall"], abs=1e-4)
        assert float(agg[r["row"]]["AR_std"]) == 0.0 and agg[r["row"]]["n_seeds"] == "1"
        assert 0.0 <= sc["bop19_average_recall"] <= 1.0
    for r in runs:  # the pose-error breakdown beside the recalls
        sc = json.loads((out / "scores" / f"{r['row']}_s0.json").read_text())
        assert float(r["rot_deg"]) == pytest.approx(sc["breakdown"]["overall"]["rot_median_deg"], abs=1e-3)
        assert float(r["depth_pct"]) == pytest.approx(100 * sc["breakdown"]["overall"]["depth_rel_median"], abs=1e-3)
    md = (out / "ablation.md").read_text()
    assert "| A4 | + PE map | 0 |" in md and "| TTA | + TTA (ours) | 0 |" in md
    assert "| A1 - A0 | z classification over regression | 0 | +0.049 | - | - | - |" in md
    diff = float(runs[1]["AR"]) - float(runs[0]["AR"])
    assert f"| TTA - A4 | TTA | 1 | +0.010 | {diff:+.3f} ± 0.000 | - |" in md  # one seed: no spread yet
    assert [d["delta"] for d in _read_csv(out / "deltas.csv")][-1] == "TTA - IPDF"
    assert (out / "ablation.png").read_bytes()[:8] == PNG
    figs = sorted((out / "figures" / "A4_s0").glob("*.png"))
    assert figs and all(p.read_bytes()[:8] == PNG for p in figs)


def test_ablation_rerun_of_a_finished_sweep_redoes_nothing(ablation_dir):
    out, _ = ablation_dir
    before = {p: p.stat().st_mtime_ns for p in (out / "scores").glob("*.json")}
    res = _sweep("ablation", "--out", str(out), "--budget", "tiny", "--rows", "A4,TTA", timeout=120)
    assert res.returncode == 0, res.stderr
    assert res.stdout.count("skipped (finished earlier") == 2
    assert {p: p.stat().st_mtime_ns for p in (out / "scores").glob("*.json")} == before


def test_so3_samples_two_sizes(ablation_dir, tmp_path):
    out, _ = ablation_dir
    res = _sweep("so3-samples", "--run", str(out / "runs" / "A4_s0"), "--out", str(tmp_path / "so3"),
                 "--sizes", "20000,60000", "--no-refine", "--no-figures", "--dataset", str(out / "dataset"))
    assert res.returncode == 0, res.stdout + res.stderr
    rows = _read_csv(tmp_path / "so3" / "so3_samples.csv")
    assert [(r["library_size"], r["refine"]) for r in rows] == [("20000", "0"), ("60000", "0")]
    for r in rows:
        assert 0.0 <= float(r["AR"]) <= 1.0 and float(r["ms_per_crop"]) > 0
    assert "| 60,000 | no |" in (tmp_path / "so3" / "so3_samples.md").read_text()
    assert (tmp_path / "so3" / "so3_samples_ms.png").read_bytes()[:8] == PNG
    # the library-size option reached the predictor
    assert "--library-size 60000" in (tmp_path / "so3" / "logs" / "lib60000.predict.log").read_text()


def test_eval_figures_writes_pngs(ablation_dir, tmp_path):
    from sc6d_jax.metrics.cli import main

    out, _ = ablation_dir
    figs = tmp_path / "figs"
    assert main(["--dataset", str(out / "dataset"), "--results", str(out / "results" / "A4_s0.csv"),
                 "--out", str(tmp_path / "s.json"), "--no-progress", "--figures", str(figs),
                 "--run", str(out / "runs" / "A4_s0")]) == 0
    names = sorted(p.name for p in figs.iterdir())
    assert "ar_per_object.png" in names and "worst_targets.png" in names
    assert any(n.startswith("poses_") for n in names) and any(n.startswith("rotdist_") for n in names)
    for p in figs.iterdir():
        assert p.read_bytes()[:8] == PNG and p.stat().st_size > 1000
    with pytest.raises(ValueError, match="only used with --figures"):
        main(["--dataset", str(out / "dataset"), "--results", str(out / "results" / "A4_s0.csv"),
              "--out", str(tmp_path / "s2.json"), "--run", str(out / "runs" / "A4_s0")])


def test_ablation_oracle_rescores_each_run_with_one_head_from_the_ground_truth(ablation_dir):
    import importlib.util

    from sc6d_jax.bop import BopDataset, read_results_csv
    from sc6d_jax.metrics import evaluate_bop19

    out, _ = ablation_dir
    script = REPO / "experiments" / "ablation_oracle.py"
    res = subprocess.run([sys.executable, str(script), "--out", str(out), "--seeds", "0"], capture_output=True,
                         text=True, timeout=300)
    assert res.returncode == 0, res.stdout + res.stderr
    for name in ("A4_s0", "TTA_s0"):
        for v in ("gtR", "gtt"):
            sc = json.loads((out / "oracle" / f"{name}.{v}.json").read_text())
            assert 0.0 <= sc["bop19_average_recall"] <= 1.0
    rows = {r["row"]: r for r in _read_csv(out / "oracle.csv")}
    assert set(rows) == {"A4", "TTA"} and rows["A4"]["n_seeds"] == "1"
    assert float(rows["A4"]["AR_mean"]) == pytest.approx(json.loads((out / "scores" / "A4_s0.json").read_text())
                                                         ["bop19_average_recall"], abs=1e-4)
    assert (out / "oracle.png").read_bytes()[:8] == PNG
    md = (out / "oracle.md").read_text()
    assert "| A4 | 0 |" in md and "| TTA - A4 | TTA | 1 |" in md
    # a rerun reads the stored scores back instead of scoring again
    before = {p: p.stat().st_mtime_ns for p in (out / "oracle").iterdir()}
    res = subprocess.run([sys.executable, str(script), "--out", str(out), "--seeds", "0"], capture_output=True,
                         text=True, timeout=120)
    assert res.returncode == 0 and {p: p.stat().st_mtime_ns for p in (out / "oracle").iterdir()} == before

    spec = importlib.util.spec_from_file_location("ablation_oracle", script)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    ds = BopDataset(out / "dataset")
    ests = read_results_csv(out / "results" / "A4_s0.csv")
    gt_r = mod.oracle_estimates(ds, ests, "gtR")
    assert [e.t.tolist() for e in gt_r] == [e.t.tolist() for e in ests]  # only the rotation changes
    e = gt_r[0]
    g = [g for g in ds.scene_gt(e.scene_id)[e.im_id] if g.obj_id == e.obj_id]
    assert any(np.allclose(e.R, np.asarray(x.R).reshape(3, 3)) for x in g)
    # both heads from the ground truth: every target is found, by all three errors
    both = mod.oracle_estimates(ds, gt_r, "gtt")
    assert evaluate_bop19(ds, both)["bop19_average_recall"] == pytest.approx(1.0)
    with pytest.raises(ValueError, match="variant must be one of"):
        mod.oracle_estimates(ds, ests, "gtX")
    res = subprocess.run([sys.executable, str(script), "--out", str(out.parent / "nothing")], capture_output=True,
                         text=True, timeout=60)
    assert res.returncode == 2 and "does not exist: run experiments/sweep.py ablation" in res.stderr


def test_sweep_argument_errors(tmp_path):
    res = _sweep("ablation", "--out", str(tmp_path / "a"), "--rows", "A0,B7", timeout=60)
    assert res.returncode == 2 and "unknown row(s) ['B7']" in res.stderr
    res = _sweep("ablation", "--out", str(tmp_path / "a"), "--seeds", "0,x", timeout=60)
    assert res.returncode == 2 and "--seeds must be comma-separated integers" in res.stderr
    res = _sweep("so3-samples", "--run", str(tmp_path), "--out", str(tmp_path / "b"), timeout=60)
    assert res.returncode == 2 and "not a training run directory" in res.stderr
    (tmp_path / "c").mkdir()
    (tmp_path / "c" / "sweep.json").write_text(json.dumps({"kind": "ablation", "budget": "full"}))
    res = _sweep("ablation", "--out", str(tmp_path / "c"), "--budget", "tiny", timeout=60)
    assert res.returncode == 2 and "budget='full'" in res.stderr


# --------------------------------------------------------------------------- sc6d train --set
def test_train_set_overrides_parse_with_field_types():
    from sc6d_jax.train.cli import apply_overrides
    from sc6d_jax.train.config import preset

    cfg = apply_overrides(preset("tiny"), [
        "loss.z_mode=regression", "model.use_pe=false", "model.rot_head=ipdf", "stream.occlusion=none",
        "optim.lr=1e-3", "z_range=0.5,3", "steps=7", "stream.obj_ids=3,4,5",
    ])
    assert cfg.loss.z_mode == "regression" and cfg.model.use_pe is False and cfg.model.rot_head == "ipdf"
    assert cfg.stream.occlusion is None and cfg.optim.lr == 1e-3 and cfg.z_range == (0.5, 3.0)
    assert cfg.steps == 7 and cfg.stream.obj_ids == (3, 4, 5) and cfg.model.n_objects == 3
    assert apply_overrides(cfg, []) is cfg


@pytest.mark.parametrize(
    "item, match",
    [
        ("loss.z_mod=regression", "unknown config key 'loss.z_mod'"),
        ("lr=1", "unknown config key 'lr'"),
        ("model=3", "unknown config key 'model'"),
        ("loss.z_mode", "expects KEY=VALUE"),
        ("model.use_pe=maybe", "model.use_pe=maybe: expected a boolean"),
        ("steps=ten", "steps=ten: expected an integer"),
        ("optim.lr=fast", "optim.lr=fast: expected a number"),
        ("loss.z_mode=linear", "z_mode must be one of"),
        ("z_range=1", "expected 2 comma-separated values"),
        ("steps=0", "steps must be a positive integer"),
    ],
)
def test_train_set_errors_name_the_problem(item, match, tmp_path):
    from sc6d_jax.train.cli import main

    with pytest.raises(ValueError, match=match):
        main(["--models", str(tmp_path), "--out", str(tmp_path / "run"), "--preset", "tiny", "--set", item])
    assert not (tmp_path / "run").exists()


def test_every_budget_and_row_builds_a_valid_training_config(tmp_path):
    """What each ablation row would train, for every budget: the config parses, the rows' depth
    settings reach it, and budgets above tiny leave out the recipe's L1 on the decoded depth."""
    from sc6d_jax.train.cli import build_config, build_parser

    sweep = _sweep_module()
    for name, budget in sweep.BUDGETS.items():
        for row in sweep.ROWS:
            args = sweep._train_args(budget, tmp_path / "models", tmp_path / "run", 0, row.sets)
            cfg = build_config(build_parser().parse_args([str(a) for a in args[1:]]))
            assert cfg.preset == budget.preset
            for item in row.sets:
                key, value = sweep._resolve_set(budget.preset, item).split("=")
                section, field_ = key.split(".")
                assert str(getattr(getattr(cfg, section), field_)).lower() == value.lower(), (name, row.name, item)
            if name != "tiny":
                assert cfg.loss.w_z_l1 == 0.0, (name, row.name)
            if budget.obj_ids:
                assert cfg.stream.obj_ids == budget.obj_ids
            if name == "medium":  # the committed sweep's batch, pinned as the cpu preset moved on to 48
                assert cfg.stream.batch_size == 32, row.name
    medium = sweep.BUDGETS["medium"]
    assert medium.steps == 4000 and len(medium.obj_ids) == 4 and medium.seeds == (0, 1, 2)


def _sweep_module():
    import importlib.util

    spec = importlib.util.spec_from_file_location("sweep_module", SWEEP)
    mod = importlib.util.module_from_spec(spec)
    sys.modules["sweep_module"] = mod  # dataclasses look their module up while the class is made
    try:
        spec.loader.exec_module(mod)
    finally:
        del sys.modules["sweep_module"]
    return mod


def test_ablation_deltas_pair_seeds_and_compare_signs_with_the_paper():
    sw = _sweep_module()
    per_seed = {"A0": {0: {"AR": 0.20}, 1: {"AR": 0.22}, 2: {"AR": 0.30}},
                "A1": {0: {"AR": 0.26}, 1: {"AR": 0.24}},  # seed 2 unfinished: paired over 0 and 1
                "TTA": {0: {"AR": 0.30}, 1: {"AR": 0.31}}, "IPDF": {0: {"AR": 0.33}, 1: {"AR": 0.35}}}
    d = {x["delta"]: x for x in sw.ablation_deltas(per_seed)}
    a = d["A1 - A0"]
    assert a["n_seeds"] == 2 and a["mean"] == pytest.approx(0.04) and a["paper"] == pytest.approx(0.049)
    assert a["std"] == pytest.approx(0.0283, abs=1e-4)  # differences 0.06 and 0.02
    assert a["spread"] == pytest.approx(0.0141, abs=1e-4) and a["separation"] == pytest.approx(2.83, abs=0.01)
    assert a["sign_reproduced"] == "yes"
    assert d["TTA - IPDF"]["mean"] == pytest.approx(-0.035) and d["TTA - IPDF"]["sign_reproduced"] == "no"
    assert d["A2 - A1"]["n_seeds"] == 0 and d["A2 - A1"]["sign_reproduced"] == "-"
    # the IPDF row trains an Implicit-PDF head as wide as the preset's SO(3) encoder, and predicts with TTA
    row = sw.ROW_BY_NAME["IPDF"]
    args = [str(x) for x in sw._train_args(sw.BUDGETS["medium"], Path("m"), Path("r"), 0, row.sets)]
    assert "model.rot_head=ipdf" in args and "model.ipdf_hidden=128" in args and row.predict == ("--tta", "--tta-mode", "best")
