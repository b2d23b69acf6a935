"""``sc6d carry``: a run stopped after its checkpoint of step 3, carried to a fresh folder and
resumed there with ``sc6d train --resume``, ends bit for bit like an uninterrupted 6-step run;
bad input is refused with one error line (exit status 2), touching nothing."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from sc6d_jax.checkpoint import checkpoint_dirs
from sc6d_jax.cli import main

#: An asymmetric built-in object (as in test_train_real.py).
ASYM_OBJ = 1
STEPS = 6


class _Stop(Exception):
    """Raised by the stream in place of batch ``stop_at``: the run ends as if killed there."""


def _stopping_data_fns(stop_at: int):
    """The real crop stream, raising :class:`_Stop` when asked for batch ``stop_at`` (0-based),
    i.e. right after the checkpoint of step ``stop_at`` was written."""
    from sc6d_jax.train import DataFns
    from sc6d_jax.train.loop import _default_data_fns

    real = _default_data_fns()

    class Stream:
        def __init__(self, inner, start):
            self.inner, self.start = inner, start
            self.obj_ids = inner.obj_ids

        def __iter__(self):
            for i, batch in enumerate(self.inner, start=self.start):
                if i >= stop_at:
                    raise _Stop
                yield batch

        def close(self):
            self.inner.close()

    return DataFns(real.stream_config, lambda scfg, start: Stream(real.stream(scfg, start), start), real.z_range)


def _metrics(run: Path) -> list[dict]:
    return [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]


def _files(d: Path) -> dict[Path, bytes]:
    return {p: p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def runs(tmp_path_factory, models):
    """Run A (6 steps, uninterrupted) and run B (same config, stopped after step 3)."""
    from sc6d_jax.train import preset, train

    root = tmp_path_factory.mktemp("carry")
    cfg = preset("tiny", steps=STEPS, checkpoint_every=3, log_every=1).replace(val_crops=0)
    cfg = cfg.replace(stream=dataclasses.replace(cfg.stream, obj_ids=(ASYM_OBJ,)))
    # workers=0: six steps render faster in this process than through a pool (the data are the same)
    train(cfg, models, root / "a", progress=False, verbose=False, workers=0)
    with pytest.raises(_Stop):
        train(cfg, models, root / "b", progress=False, verbose=False, data_fns=_stopping_data_fns(3), workers=0)
    assert [s for s, _ in checkpoint_dirs(root / "b")] == [3]
    with open(root / "b" / "metrics.jsonl", "a") as f:
        f.write('{"step": 4, "lo')  # a torn line, as a kill in mid-write leaves
    return root, models


def test_carried_state_resumes_bit_exact(runs, capsys):
    root, models = runs
    a, b, state = root / "a", root / "b", root / "legs" / "state"
    before = _files(b)
    assert main(["carry", "--run", str(b), "--out", str(state)]) == 0
    out = capsys.readouterr().out
    assert "step 3" in out and " MB)" in out and f"--out {state} --resume" in out
    assert _files(b) == before  # the source run is untouched
    # exactly what a resume needs: config, the newest checkpoint, metrics up to it (+ the marker)
    assert sorted(str(p.relative_to(state)) for p in state.rglob("*") if p.is_file()) == [
        "carry.json", "checkpoints/ckpt_00000003/meta.json", "checkpoints/ckpt_00000003/state.npz",
        "config.json", "metrics.jsonl",
    ]
    assert [m["step"] for m in _metrics(state)] == [1, 2, 3]
    # it is meant to be committed: no absolute path of this machine (the runs used absolute ones)
    for p in state.rglob("*.json"):
        assert str(root) not in p.read_text() and str(models) not in p.read_text(), p
    assert sorted(p.name for p in state.parent.iterdir()) == ["state"]  # no temporary leftovers
    # the carried folder is a run directory as it is: resume it with the CLI (config read back)
    assert main(["train", "--models", str(models), "--out", str(state), "--resume",
                 "--no-progress", "--quiet", "--workers", "0"]) == 0
    capsys.readouterr()
    ref = a / "checkpoints" / "ckpt_00000006" / "state.npz"
    got = state / "checkpoints" / "ckpt_00000006" / "state.npz"
    with np.load(ref) as x, np.load(got) as y:
        assert x.files == y.files and any(k.startswith("params/") for k in x.files)
        for k in x.files:  # parameters, optimiser state and PRNG key
            np.testing.assert_array_equal(x[k], y[k], err_msg=k)
    # the curve continues: one line per step, the losses of the uninterrupted run
    assert [m["step"] for m in _metrics(state)] == list(range(1, STEPS + 1))
    assert [m["loss"] for m in _metrics(state)] == [m["loss"] for m in _metrics(a)]

    # carrying the state onto itself (after a leg trained in it) keeps only its newest checkpoint
    assert [s for s, _ in checkpoint_dirs(state)] == [3, 6]
    assert main(["carry", "--run", str(state), "--out", str(state)]) == 0
    assert "step 6" in capsys.readouterr().out
    assert [s for s, _ in checkpoint_dirs(state)] == [6]
    assert json.loads((state / "carry.json").read_text())["step"] == 6
    assert [m["step"] for m in _metrics(state)] == list(range(1, STEPS + 1))

    # an earlier carry of the same run is replaced; going back to an older step is refused
    again = root / "legs" / "again"
    assert main(["carry", "--run", str(b), "--out", str(again)]) == 0
    assert main(["carry", "--run", str(a), "--out", str(again)]) == 0
    assert [s for s, _ in checkpoint_dirs(again)] == [6]
    capsys.readouterr()
    snap = _files(state)
    assert main(["carry", "--run", str(b), "--out", str(state)]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "holds step 6, newer than step 3" in err
    assert _files(state) == snap


def test_amend_continues_a_run_under_a_changed_stream_and_resumes_bit_exact(runs, tmp_path, capsys):
    """``sc6d train --resume --amend --set stream...``: run B's step-3 state trained on under
    jittered boxes. Amended, stopped before its next checkpoint, carried and resumed, it ends bit for bit
    like the same amendment run uninterrupted, and not like the unamended run A; the change is
    recorded with its step; changes of the model or of the objects are refused."""
    from sc6d_jax.train import train
    from sc6d_jax.train.config import TrainConfig
    from sc6d_jax.train.loop import read_amendments

    root, models = runs
    sets = ["--set", "stream.box_shift=0.1", "--set", "stream.box_scale=0.9,1.1"]  # tiny's: 0 and (1, 1)
    straight, stopped = tmp_path / "straight", tmp_path / "stopped"
    for d in (straight, stopped):
        shutil.copytree(root / "b", d)
    assert main(["train", "--models", str(models), "--out", str(straight), "--resume", "--amend", *sets,
                 "--no-progress", "--quiet", "--workers", "0"]) == 0
    amends = read_amendments(straight)
    assert [a["step"] for a in amends] == [3]
    assert sorted(c.split(" ")[0] for c in amends[0]["changes"]) == ["stream.box_scale", "stream.box_shift"]
    cfg = json.loads((straight / "config.json").read_text())
    assert cfg["stream"]["box_shift"] == 0.1 and cfg["stream"]["box_scale"] == [0.9, 1.1]

    amended = TrainConfig.from_json((straight / "config.json").read_text())
    with pytest.raises(_Stop):  # amended at step 3, killed at step 4 before any new checkpoint
        train(amended, models, stopped, resume=True, amend=True, progress=False, verbose=False,
              data_fns=_stopping_data_fns(4), workers=0)
    state = tmp_path / "state"
    assert main(["carry", "--run", str(stopped), "--out", str(state)]) == 0
    assert read_amendments(state) == amends
    assert main(["train", "--models", str(models), "--out", str(state), "--resume", "--no-progress", "--quiet",
                 "--workers", "0"]) == 0
    ref = straight / "checkpoints" / "ckpt_00000006" / "state.npz"
    with np.load(ref) as x, np.load(state / "checkpoints" / "ckpt_00000006" / "state.npz") as y, \
            np.load(root / "a" / "checkpoints" / "ckpt_00000006" / "state.npz") as z:
        for k in x.files:
            np.testing.assert_array_equal(x[k], y[k], err_msg=k)
        assert any(not np.array_equal(x[k], z[k]) for k in x.files if k.startswith("params/"))
    assert [m["loss"] for m in _metrics(state)] == [m["loss"] for m in _metrics(straight)]
    assert [m["loss"] for m in _metrics(state)][:3] == [m["loss"] for m in _metrics(root / "a")][:3]

    capsys.readouterr()
    for bad, match in ((["--set", "model.width=8"], "refused: model.width"),
                       (["--obj-ids", "1,2"], "refused: model.n_objects")):
        assert main(["train", "--models", str(models), "--out", str(straight), "--resume", "--amend", *bad,
                     "--no-progress", "--quiet"]) == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and match in err, err
    assert main(["train", "--models", str(models), "--out", str(tmp_path / "new"), "--amend", *sets]) == 2
    assert "needs --resume" in capsys.readouterr().err
    assert read_amendments(straight) == amends  # refusals change nothing


def test_carry_refuses_bad_input_with_one_error_line(runs, tmp_path, capsys):
    root, _ = runs
    b = root / "b"

    def refused(run: Path, out: Path, match: str) -> None:
        assert main(["carry", "--run", str(run), "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and err.startswith("sc6d carry: error:"), err
        assert match in err, err

    # no checkpoint (a run killed before its first one), no run directory
    fresh = tmp_path / "fresh"
    fresh.mkdir()
    shutil.copy(b / "config.json", fresh / "config.json")
    refused(fresh, tmp_path / "s1", "has no checkpoint")
    refused(tmp_path / "missing", tmp_path / "s1", "does not exist")
    assert not (tmp_path / "s1").exists()
    # --out is a file, or a folder that is not a carry (here: another run's directory)
    (tmp_path / "file").write_text("x")
    refused(b, tmp_path / "file", "not a directory")
    assert (tmp_path / "file").read_text() == "x"
    snap = _files(root / "a")
    refused(b, root / "a", "not a carried state")
    assert _files(root / "a") == snap
    # --out is a carry of another run (another seed)
    other = tmp_path / "other"
    assert main(["carry", "--run", str(b), "--out", str(other)]) == 0
    cfg = json.loads((other / "config.json").read_text())
    (other / "config.json").write_text(json.dumps({**cfg, "seed": cfg["seed"] + 1}))
    snap = _files(other)
    capsys.readouterr()
    refused(b, other, "holds the state of another run; differing: seed")
    assert _files(other) == snap
    # a corrupt newest checkpoint is not carried
    bad = tmp_path / "bad"
    shutil.copytree(b, bad)
    state = bad / "checkpoints" / "ckpt_00000003" / "state.npz"
    state.write_bytes(state.read_bytes()[:-10])
    refused(bad, tmp_path / "s2", "corrupt")
    assert not (tmp_path / "s2").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad", "file", "fresh", "other"]


def test_anneal_probe_cools_a_checkpoint_down_and_validates(runs, tmp_path, capsys):
    """experiments/anneal_probe.py: from run A's step-3 checkpoint, a 4-step cool-down whose
    learning rate starts at the run's value there and ends at lr_end, validated at the end."""
    import importlib.util

    from sc6d_jax.checkpoint import load_checkpoint
    from sc6d_jax.train.loop import make_optimizer

    root, models = runs
    spec = importlib.util.spec_from_file_location("anneal_probe", Path(__file__).resolve().parents[1] / "experiments" / "anneal_probe.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    out = tmp_path / "probe"
    assert mod.main(["--run", str(root / "a"), "--models", str(models), "--out", str(out), "--step", "3",
                     "--steps", "10", "--workers", "0", "--val-crops", "16"]) == 0
    text = capsys.readouterr().out
    assert "after a 10-step cool-down: AR " in text
    cfg = json.loads((out / "config.json").read_text())
    _, run_cfg = load_checkpoint(root / "a", 3)
    assert cfg["steps"] == 10 and cfg["stream"]["curriculum_fraction"] == 0 and cfg["val_crops"] == 16
    assert cfg["optim"]["lr"] == pytest.approx(float(make_optimizer(run_cfg)[1](3)))
    recs = _metrics(out)
    assert recs[-1]["step"] == 10 and "val_ar" in recs[-1]
    # the probe starts from the checkpoint's parameters, not from fresh ones
    step, params, pcfg = mod.setup(root / "a", 3, 10)
    assert step == 3 and pcfg.val_crops == run_cfg.val_crops
    import jax

    for x, y in zip(jax.tree.leaves(params), jax.tree.leaves(load_checkpoint(root / "a", 3)[0])):
        np.testing.assert_array_equal(x, y)
    assert mod.main(["--run", str(tmp_path), "--models", str(models), "--out", str(out)]) == 2
    assert "not a training run" in capsys.readouterr().err
    # --set changes the probe's recipe, never its model
    _, _, tcfg = mod.setup(root / "a", 3, 10, sets=["loss.turn_negatives=true", "loss.tau=0.2"])
    assert tcfg.loss.turn_negatives and tcfg.loss.tau == 0.2 and tcfg.model == pcfg.model
    assert mod.main(["--run", str(root / "a"), "--models", str(models), "--out", str(tmp_path / "w"),
                     "--set", "model.width=8"]) == 2
    assert "cannot change the model" in capsys.readouterr().err and not (tmp_path / "w").exists()
