"""experiments/lmo.py: the tiny budget end to end on the real LM-O test images (real sc6d train /
predict / eval subprocesses), the report beside published rows, and input errors."""

from __future__ import annotations

import csv
import importlib.util
import json
import subprocess
import sys
from collections import Counter
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
LMO_SCRIPT = REPO / "experiments" / "lmo.py"


def _load_lmo():
    spec = importlib.util.spec_from_file_location("lmo_experiment", LMO_SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses resolve their module through sys.modules
    spec.loader.exec_module(mod)
    return mod


lmo = _load_lmo()


def _run(*args: str, timeout: float = 400) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(LMO_SCRIPT), *args], capture_output=True, text=True, timeout=timeout)


def _read_csv(path: Path) -> list[dict[str, str]]:
    with open(path, newline="", encoding="utf-8") as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def tiny_run(shared_data, tmp_path_factory) -> tuple[Path, Path, str]:
    data = shared_data / "lmo"
    if not (data / "test_targets_bop19.json").is_file():
        pytest.skip(f"LM-O data not found at {data}")
    out = tmp_path_factory.mktemp("lmo") / "exp"
    res = _run("--out", str(out), "--budget", "tiny", "--data", str(data), "--workers", "0")
    assert res.returncode == 0, res.stdout + res.stderr
    return data, out, res.stdout


def test_tiny_stages_and_predictions_cover_the_trained_objects(tiny_run):
    from sc6d_jax.bop import BopDataset

    data, out, log = tiny_run
    for stage in ("[1/4] train: preset tiny, 12 steps, objects 8,10", "[2/4] predict:", "[3/4] eval:",
                  "[4/4] report:"):
        assert stage in log
    cfg = json.loads((out / "run" / "config.json").read_text())
    assert cfg["stream"]["obj_ids"] == [8, 10] and cfg["preset"] == "tiny" and cfg["steps"] == 12
    # the models trained on are the LM-O models, never the test images
    train_cmd = (out / "logs" / "train.log").read_text().splitlines()[0]
    assert f"--models {data / 'models'}" in train_cmd and "rgb" not in train_cmd
    # one estimate per target instance of the trained objects, none for the others
    want = Counter()
    for t in BopDataset(data).targets():
        if t.obj_id in (8, 10):
            want[(t.scene_id, t.im_id, t.obj_id)] += t.inst_count
    rows = _read_csv(out / "sc6d_lmo-test.csv")
    got = Counter((int(r["scene_id"]), int(r["im_id"]), int(r["obj_id"])) for r in rows)
    assert got == want and sum(want.values()) > 50
    # BOP: one time per image
    per_image: dict[tuple[str, str], set[str]] = {}
    for r in rows:
        per_image.setdefault((r["scene_id"], r["im_id"]), set()).add(r["time"])
    assert all(len(v) == 1 for v in per_image.values())


def test_tiny_scores_have_mssd_mspd_and_no_vsd(tiny_run):
    _, out, _ = tiny_run
    sc = json.loads((out / "scores.json").read_text())
    for k in ("bop19_average_recall_mssd", "bop19_average_recall_mspd", "bop19_average_recall"):
        assert 0.0 <= sc[k] <= 1.0
    assert sc["bop19_average_recall_vsd"] is None and sc["vsd_available"] is False
    assert sc["recalls"]["vsd"] is None and "depth" in sc["vsd_skipped_reason"]
    assert sc["bop19_average_recall"] == pytest.approx(
        0.5 * (sc["bop19_average_recall_mssd"] + sc["bop19_average_recall_mspd"]), abs=1e-12)
    assert "VSD skipped" in (out / "logs" / "eval.log").read_text()
    assert sorted(int(k) for k in sc["per_object"]) == [1, 5, 6, 8, 9, 10, 11, 12]
    figs = list((out / "figures").glob("*.png"))
    assert figs and all(p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for p in figs)


def test_tiny_report_has_our_row_and_the_published_rows(tiny_run):
    _, out, log = tiny_run
    sc = json.loads((out / "scores.json").read_text())
    md = (out / "lmo.md").read_text()
    assert md in log  # the table is printed
    mssd, mspd = sc["bop19_average_recall_mssd"], sc["bop19_average_recall_mspd"]
    ours = f"| sc6d-jax (ours), tiny budget | {mssd:.3f} | {mspd:.3f} | {0.5 * (mssd + mspd):.3f} | - | 2 of 8 |"
    assert ours in md
    assert "trained objects' targets only" in md and "ground-truth visible boxes" in md
    rows = _read_csv(out / "lmo.csv")
    assert rows[0]["method"] == "sc6d-jax (ours), tiny budget"
    assert float(rows[0]["AR_MSSD"]) == pytest.approx(mssd, abs=1e-4)
    assert float(rows[0]["AR_MSPD"]) == pytest.approx(mspd, abs=1e-4)
    assert float(rows[0]["AR_mean_MSSD_MSPD"]) == pytest.approx(sc["bop19_average_recall"], abs=1e-4)
    assert rows[0]["train_steps"] == "12" and float(rows[0]["train_wall_s"]) > 0
    assert float(rows[0]["ms_per_image"]) > 0
    # trained-objects row: recall pooled over the targets of objects 8 and 10
    po = sc["per_object"]
    n = po["8"]["targets"] + po["10"]["targets"]
    sub = (po["8"]["ar_mssd"] * po["8"]["targets"] + po["10"]["ar_mssd"] * po["10"]["targets"]) / n
    assert float(rows[1]["AR_MSSD"]) == pytest.approx(sub, abs=1e-4) and rows[1]["targets"] == str(n)
    # the published rows of the reference file, or the statement that it has none
    published, note = lmo.load_published(lmo.DEFAULT_REFERENCE)
    assert note in md
    for p in published:
        assert f"| {p['method']} |" in md
    assert [r["method"] for r in rows[2:]] == [p["method"] for p in published]


REFERENCE_MD = """# Reference
## 3. Something else
| method | AR |
|---|---|
| Not LM-O | 0.9 |

## 5. Published LM-O numbers (BOP19 test set)

| Method | AR | AR_VSD | AR_MSSD | AR_MSPD | training data | boxes | source |
|---|---|---|---|---|---|---|---|
| Method A (RGB) | 63.3 | 48.0 | 60.6 | 81.2 | PBR + real | Mask R-CNN detections | Paper A, Table 2 |
| Method B | 0.547 | | | | PBR | detections | Paper B |

## 6. Next section
| method | AR |
|---|---|
| Also not LM-O | 0.1 |
"""


def test_parse_published_reads_only_lm_o_tables():
    rows = lmo.parse_published(REFERENCE_MD)
    assert [r["method"] for r in rows] == ["Method A (RGB)", "Method B"]
    a, b = rows
    assert a["ar"] == pytest.approx(0.633) and a["ar_mssd"] == pytest.approx(0.606)
    assert a["ar_mspd"] == pytest.approx(0.812) and a["ar_vsd"] == pytest.approx(0.48)
    assert a["training"] == "PBR + real" and a["boxes"] == "Mask R-CNN detections" and a["source"] == "Paper A, Table 2"
    assert b["ar"] == pytest.approx(0.547) and b["ar_mssd"] is None and b["ar_mspd"] is None
    assert lmo.parse_published("# LM-O\n\nno table here\n") == []


def test_report_puts_published_rows_beside_ours(tmp_path):
    ref = tmp_path / "REF.md"
    ref.write_text(REFERENCE_MD)
    published, note = lmo.load_published(ref)
    assert len(published) == 2 and "REF.md" in note
    scores = {
        "bop19_average_recall_mssd": 0.2, "bop19_average_recall_mspd": 0.4, "bop19_average_recall": 0.3,
        "counts": {"targets": 30, "images": 5},
        "per_object": {"1": {"targets": 10, "ar_mssd": 0.6, "ar_mspd": 0.9, "ar": 0.75},
                       "5": {"targets": 20, "ar_mssd": 0.0, "ar_mspd": 0.15, "ar": 0.075}},
    }
    run = lmo.RunInfo(path=tmp_path, name="r", steps=7, obj_ids=(1,), preset="tiny", is_training_run=True)
    md, text = lmo.build_report(scores, run, [1, 5], published, note, 12.5, 3.25, "tiny", ["cmd one"])
    assert "| sc6d-jax (ours), tiny budget | 0.200 | 0.400 | 0.300 | - | 1 of 2 | 30 |" in md
    assert "| sc6d-jax (ours), tiny budget, trained objects' targets only | 0.600 | 0.900 | 0.750 |" in md
    assert "| Method A (RGB) | 0.606 | 0.812 | 0.709 | 0.633 |" in md and "Mask R-CNN detections" in md
    assert "| Method B | - | - | - | 0.547 |" in md and "| PBR | detections |" in md
    assert "their AR includes VSD" in md and "cmd one" in md
    rows = list(csv.DictReader(text.splitlines()))
    assert [r["method"] for r in rows] == ["sc6d-jax (ours), tiny budget",
                                           "sc6d-jax (ours), tiny budget, trained objects' targets only",
                                           "Method A (RGB)", "Method B"]
    assert rows[0]["train_wall_s"] == "12.5" and rows[0]["ms_per_image"] == "3.25"
    assert rows[2]["source"] == "Paper A, Table 2" and rows[2]["train_steps"] == ""
    missing, why = lmo.load_published(tmp_path / "nope.md")
    assert missing == [] and "not found" in why


def test_check_scores_and_loop_seconds(tmp_path):
    ok = {"bop19_average_recall_mssd": 0.2, "bop19_average_recall_mspd": 0.4, "bop19_average_recall": 0.3,
          "bop19_average_recall_vsd": None, "vsd_available": False}
    lmo.check_scores(ok)
    with pytest.raises(ValueError, match="computed VSD"):
        lmo.check_scores({**ok, "bop19_average_recall_vsd": 0.1, "vsd_available": True})
    with pytest.raises(ValueError, match="not the mean of AR_MSSD"):
        lmo.check_scores({**ok, "bop19_average_recall": 0.25})
    # elapsed_s restarts at every resume: the segments' last values are summed
    lines = [{"step": 20, "elapsed_s": 5.0}, {"step": 40, "elapsed_s": 10.0}, {"step": 60, "elapsed_s": 4.0},
             {"step": 80, "elapsed_s": 9.0}]
    (tmp_path / "metrics.jsonl").write_text("\n".join(json.dumps(x) for x in lines) + "\n")
    assert lmo.loop_seconds(tmp_path) == pytest.approx(19.0)
    assert lmo.loop_seconds(tmp_path / "absent") is None


def _main_err(capsys, *args: str) -> tuple[int, str, str]:
    rc = lmo.main(list(args))
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


def test_bad_inputs_error_cleanly(tmp_path, capsys):
    out = tmp_path / "exp"
    res = _run("--out", str(out), "--data", str(tmp_path / "no_such_lmo"), timeout=60)  # as a user runs it
    assert res.returncode == 2 and res.stdout == ""
    assert "LM-O data folder not found" in res.stderr and str(tmp_path / "no_such_lmo") in res.stderr
    assert not out.exists()
    (tmp_path / "half").mkdir()
    rc, _, err = _main_err(capsys, "--out", str(out), "--data", str(tmp_path / "half"))
    assert rc == 2 and "missing models/models_info.json, test_targets_bop19.json, test" in err
    with pytest.raises(SystemExit) as exc:
        lmo.main(["--out", str(out), "--budget", "huge"])
    assert exc.value.code == 2 and "invalid choice: 'huge'" in capsys.readouterr().err


def test_bad_run_and_steps_error_cleanly(shared_data, tmp_path, capsys):
    data = shared_data / "lmo"
    if not (data / "test_targets_bop19.json").is_file():
        pytest.skip(f"LM-O data not found at {data}")
    rc, _, err = _main_err(capsys, "--out", str(tmp_path / "a"), "--data", str(data), "--run", str(tmp_path / "nope"))
    assert rc == 2 and "neither a training run" in err
    rc, _, err = _main_err(capsys, "--out", str(tmp_path / "b"), "--data", str(data), "--steps", "0")
    assert rc == 2 and "--steps must be a positive integer" in err
    rc, _, err = _main_err(capsys, "--out", str(tmp_path / "c"), "--data", str(data), "--run", "lmo", "--steps", "5")
    assert rc == 2 and "cannot be combined with --run" in err
    from sc6d_jax import pretrained

    if "lmo" not in pretrained.available():
        rc, _, err = _main_err(capsys, "--out", str(tmp_path / "d"), "--data", str(data), "--run", "lmo")
        assert rc == 2 and "no shipped model 'lmo'" in err
