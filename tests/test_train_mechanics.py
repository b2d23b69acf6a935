"""Mechanics of the training program with a small stand-in model and random batches.

The stand-in model and data live only here: they make checkpoints, SIGKILL + resume,
determinism, data parallelism, multi-process runs and NaN handling cheap to test.  The real
model and crop stream are exercised in tests/test_train_real.py.

This file doubles as a script (``python tests/test_train_mechanics.py run ...``) so that the
tests can train the stand-in in subprocesses (killed with SIGKILL, with 2 host devices, or as
two jax.distributed processes).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve()
REPO = HERE.parents[1]


# -- stand-in model and data (test-only) ------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class StandinModelConfig:
    n_objects: int = 1
    crop_size: int = 16
    hidden: int = 32


@dataclasses.dataclass(frozen=True)
class StandinLossConfig:
    noise: float = 0.1


def standin_init(key, cfg):
    import jax

    k1, k2, k3 = jax.random.split(key, 3)
    d = 3 * 4 * 4
    return {
        "fc1": {"w": jax.random.normal(k1, (d, cfg.hidden)) / np.sqrt(d), "b": jax.numpy.zeros((cfg.hidden,))},
        "fc2": {"w": jax.random.normal(k2, (cfg.hidden, 10)) / np.sqrt(cfg.hidden), "b": jax.numpy.zeros((10,))},
        "obj": jax.random.normal(k3, (cfg.n_objects, cfg.hidden)) * 0.1,
    }


def standin_loss(params, mcfg, lcfg, batch, key, z_range):
    import jax
    import jax.numpy as jnp

    x = batch["rgb"].astype(jnp.float32) / 255.0
    b, s = x.shape[0], x.shape[1]
    x = x.reshape(b, 4, s // 4, 4, s // 4, 3).mean(axis=(2, 4)).reshape(b, -1)
    x = x + lcfg.noise * jax.random.normal(key, x.shape)  # the step key matters
    h = jnp.tanh(x @ params["fc1"]["w"] + params["fc1"]["b"] + params["obj"][batch["obj_idx"]])
    y = h @ params["fc2"]["w"] + params["fc2"]["b"]
    rot = jnp.mean((y[:, :9] - batch["R_allo"].reshape(b, 9)) ** 2)
    z = (batch["delta_z"] - z_range[0]) / (z_range[1] - z_range[0])
    zl = jnp.mean((y[:, 9] - z) ** 2)
    return rot + zl, {"rot": rot, "z": zl, "vector_ignored": y[:, 0]}


@dataclasses.dataclass(frozen=True)
class StandinStreamConfig:
    models_dir: Path
    crop_size: int
    batch_size: int
    seed: int
    workers: int | None = None
    obj_ids: tuple[int, ...] | None = None
    augment: bool = True
    delay: float = 0.0
    nan_batch: int = -1


class StandinStream:
    """Batch b is a pure function of (seed, b); rgb is correlated with R_allo so it can learn."""

    def __init__(self, cfg: StandinStreamConfig, start_batch: int = 0):
        self.cfg, self.b = cfg, start_batch
        self.obj_ids = list(cfg.obj_ids or (1, 5))
        self.closed = False

    def __iter__(self):
        return self

    def __next__(self):
        c = self.cfg
        rng = np.random.default_rng([c.seed, self.b])
        q = rng.normal(size=(c.batch_size, 4))
        q /= np.linalg.norm(q, axis=1, keepdims=True)
        w, x, y, z = q.T
        R = np.stack([
            1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
            2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
            2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
        ], axis=1).reshape(-1, 3, 3).astype(np.float32)
        base = (R.reshape(-1, 9)[:, :3] * 100 + 128).astype(np.float32)
        rgb = np.clip(base[:, None, None, :] + rng.normal(0, 20, (c.batch_size, c.crop_size, c.crop_size, 3)), 0, 255)
        dz = rng.uniform(0.2, 0.8, c.batch_size).astype(np.float32)
        if self.b == c.nan_batch:
            dz[0] = np.nan
        batch = {
            "rgb": rgb.astype(np.uint8),
            "R_allo": R,
            "delta_z": dz,
            "obj_idx": rng.integers(0, len(self.obj_ids), c.batch_size).astype(np.int32),
            "note": "non-array entries are dropped",
        }
        self.b += 1
        if c.delay:
            time.sleep(c.delay)
        return batch

    def close(self):
        self.closed = True


def standin_load_weights(params, cfg, path):
    with np.load(path) as z:
        w = z["fc1.weight"].T
    if w.shape != params["fc1"]["w"].shape:
        raise ValueError(f"{path}: fc1.weight has the wrong shape")
    return {**params, "fc1": {**params["fc1"], "w": w}}


def standin_fns(delay: float = 0.0, nan_batch: int = -1):
    from sc6d_jax.train import DataFns, ModelFns

    def stream_config(**kw):
        return StandinStreamConfig(**kw, delay=delay, nan_batch=nan_batch)

    return (
        ModelFns(standin_init, standin_loss, standin_load_weights),
        DataFns(stream_config, StandinStream, lambda cfg: (0.1, 1.0)),
    )


def standin_config(steps: int = 20, **kw):
    from sc6d_jax.train import OptimConfig, StreamSettings, TrainConfig

    base = dict(
        model=StandinModelConfig(), loss=StandinLossConfig(), stream=StreamSettings(batch_size=8),
        optim=OptimConfig(lr=1e-2, lr_end=1e-4), steps=steps, seed=3, checkpoint_every=5, log_every=1,
    )
    base.update(kw)
    return TrainConfig(**base)


def _run_standin(out: Path, steps: int, delay: float = 0.0, nan_batch: int = -1, resume: bool = False,
                 init_weights: Path | None = None, **kw):
    from sc6d_jax.train import train

    mf, df = standin_fns(delay, nan_batch)
    out.parent.mkdir(parents=True, exist_ok=True)
    models = out.parent / "models"
    models.mkdir(exist_ok=True)
    return train(standin_config(steps, **kw), models, out, resume=resume, progress=False, verbose=False,
                 model_fns=mf, data_fns=df, init_weights=init_weights)


def _save_params(params, path: Path) -> None:
    from sc6d_jax.train.checkpoint import flatten_with_paths

    np.savez(path, **flatten_with_paths(params, "params"))


def _script_main(argv: list[str]) -> int:
    p = argparse.ArgumentParser()
    p.add_argument("what", choices=["run"])
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--steps", type=int, default=20)
    p.add_argument("--delay", type=float, default=0.0)
    p.add_argument("--resume", action="store_true")
    p.add_argument("--params-out", type=Path)
    p.add_argument("--coordinator")
    p.add_argument("--num-processes", type=int)
    p.add_argument("--process-id", type=int)
    a = p.parse_args(argv)
    sys.path.insert(0, str(REPO))
    if a.coordinator:
        from sc6d_jax.train import initialize_distributed

        initialize_distributed(a.coordinator, a.num_processes, a.process_id)
    params = _run_standin(a.out, a.steps, delay=a.delay, resume=a.resume)
    if a.params_out:
        _save_params(params, a.params_out)
    return 0


def _script(*args: str, env: dict | None = None) -> list[str]:
    return [sys.executable, str(HERE), *args]


def _env(**extra: str) -> dict:
    env = dict(os.environ)
    env.pop("XLA_FLAGS", None)
    env.update(extra)
    return env


# -- tests ---------------------------------------------------------------------------------------
if __name__ != "__main__":
    import pytest


def _metrics(run: Path) -> list[dict]:
    return [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]


def _assert_same_params(a, b) -> None:
    import jax

    la, lb = jax.tree.leaves(a), jax.tree.leaves(b)
    assert len(la) == len(lb)
    for x, y in zip(la, lb):
        assert np.asarray(x).dtype == np.asarray(y).dtype
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_run_writes_config_metrics_checkpoints_and_is_deterministic(tmp_path):
    from sc6d_jax.train.checkpoint import checkpoint_dirs, read_meta

    p1 = _run_standin(tmp_path / "a" / "run", 12)
    p2 = _run_standin(tmp_path / "b" / "run", 12)
    _assert_same_params(p1, p2)  # same seed -> same params bit for bit
    run = tmp_path / "a" / "run"
    cfg = json.loads((run / "config.json").read_text())
    assert cfg["model"]["n_objects"] == 2 and cfg["stream"]["obj_ids"] == [1, 5]
    assert cfg["z_range"] == [0.1, 1.0] and cfg["steps"] == 12
    m = _metrics(run)
    assert [r["step"] for r in m] == list(range(1, 13))
    assert {"loss", "rot", "z", "grad_norm", "lr", "crops_per_s"} <= set(m[0])
    assert "vector_ignored" not in m[0]
    assert m[-1]["loss"] < m[0]["loss"]
    assert m[0]["lr"] == pytest.approx(1e-2) and m[-1]["lr"] < m[0]["lr"]
    # checkpoints at 5, 10 and the end (12); keep_checkpoints=3
    assert [s for s, _ in checkpoint_dirs(run)] == [5, 10, 12]
    meta = read_meta(checkpoint_dirs(run)[-1][1])
    assert meta["step"] == 12 and meta["config"] == cfg
    # a different seed gives different parameters
    p3 = _run_standin(tmp_path / "c" / "run", 12, seed=4)
    assert not np.array_equal(np.asarray(p3["fc1"]["w"]), np.asarray(p1["fc1"]["w"]))


def test_init_weights_are_loaded_on_fresh_runs_only(tmp_path):
    import jax

    from sc6d_jax.train import OptimConfig
    from sc6d_jax.train.checkpoint import checkpoint_dirs, read_meta

    w = np.full((StandinModelConfig().hidden, 48), 0.5, np.float32)  # torch-like (out, in)
    np.savez(tmp_path / "w.npz", **{"fc1.weight": w})
    run = tmp_path / "w" / "run"
    p = _run_standin(run, 1, init_weights=tmp_path / "w.npz", optim=OptimConfig(lr=1e-9, lr_end=0.0))
    np.testing.assert_allclose(np.asarray(p["fc1"]["w"]), w.T, atol=1e-6)  # loaded, barely moved
    assert read_meta(checkpoint_dirs(run)[-1][1])["init_weights"] == str(tmp_path / "w.npz")
    fresh = standin_init(jax.random.split(jax.random.PRNGKey(3))[0], StandinModelConfig(n_objects=2))
    assert not np.allclose(np.asarray(fresh["fc1"]["w"]), w.T)
    with pytest.raises(FileNotFoundError, match="initial weights"):
        _run_standin(tmp_path / "w2" / "run", 1, init_weights=tmp_path / "nope.npz")
    np.savez(tmp_path / "bad.npz", **{"fc1.weight": w[:3]})
    with pytest.raises(ValueError, match="wrong shape"):
        _run_standin(tmp_path / "w3" / "run", 1, init_weights=tmp_path / "bad.npz")
    assert not checkpoint_dirs(tmp_path / "w3" / "run")


def test_checkpoint_roundtrip_and_corruption(tmp_path):
    import jax
    import optax

    from sc6d_jax.train.checkpoint import read_checkpoint, save_checkpoint

    params = standin_init(jax.random.PRNGKey(0), StandinModelConfig(n_objects=2))
    opt = optax.adamw(1e-3).init(params)
    key = jax.random.PRNGKey(7)
    d = save_checkpoint(tmp_path, 40, params, opt, key, {"x": 1})
    p_t = jax.eval_shape(lambda: params)
    o_t = jax.eval_shape(lambda: opt)
    p2, o2, k2, meta = read_checkpoint(d, p_t, o_t)
    _assert_same_params(params, p2)
    _assert_same_params(opt, o2)
    np.testing.assert_array_equal(k2, np.asarray(key))
    assert meta["step"] == 40 and meta["config"] == {"x": 1}
    # incompatible template -> ValueError naming the entry
    bad_t = jax.eval_shape(lambda: standin_init(jax.random.PRNGKey(0), StandinModelConfig(n_objects=3)))
    with pytest.raises(ValueError, match="incompatible.*params/obj"):
        read_checkpoint(d, bad_t, None)
    # flipped byte -> ValueError naming the file, file left as it was
    state = d / "state.npz"
    raw = bytearray(state.read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    state.write_bytes(bytes(raw))
    with pytest.raises(ValueError, match="corrupt"):
        read_checkpoint(d, p_t, o_t)
    assert state.read_bytes() == bytes(raw)
    (d / "meta.json").write_text("{not json")
    with pytest.raises(ValueError, match="corrupt"):
        read_checkpoint(d, p_t, o_t)


def test_bad_run_directories_are_refused_and_left_untouched(tmp_path):
    from sc6d_jax.train.checkpoint import checkpoint_dirs

    run = tmp_path / "x" / "run"
    _run_standin(run, 6)
    snapshot = {p: p.read_bytes() for p in run.rglob("*") if p.is_file()}
    with pytest.raises(ValueError, match="already holds checkpoints"):
        _run_standin(run, 6)
    with pytest.raises(ValueError, match="belongs to another config.*seed"):
        _run_standin(run, 6, seed=9, resume=True)
    # corrupt newest checkpoint on resume
    newest = checkpoint_dirs(run)[-1][1] / "state.npz"
    raw = newest.read_bytes()
    newest.write_bytes(raw[:-10])
    snapshot[newest] = newest.read_bytes()
    with pytest.raises(ValueError, match=f"checkpoint .*{newest.parent.name}.* corrupt"):
        _run_standin(run, 6, resume=True)
    assert {p: p.read_bytes() for p in run.rglob("*") if p.is_file()} == snapshot
    with pytest.raises(FileNotFoundError, match="models folder"):
        from sc6d_jax.train import train

        mf, df = standin_fns()
        train(standin_config(), tmp_path / "nope", tmp_path / "r2", model_fns=mf, data_fns=df, progress=False)


def test_nan_loss_stops_with_step_and_keeps_last_good_checkpoint(tmp_path):
    from sc6d_jax.train import NonFiniteLossError
    from sc6d_jax.train.checkpoint import checkpoint_dirs

    run = tmp_path / "n" / "run"
    with pytest.raises(NonFiniteLossError, match="not finite at step 8") as info:
        _run_standin(run, 20, nan_batch=7)  # batch index 7 is the 8th step
    assert info.value.step == 8
    assert [s for s, _ in checkpoint_dirs(run)] == [5]
    assert info.value.last_checkpoint == checkpoint_dirs(run)[0][1]
    assert max(r["step"] for r in _metrics(run)) == 7


def test_resume_after_sigkill_is_bit_exact(tmp_path):
    """Kill a training subprocess with SIGKILL mid-run, resume it, compare with an uninterrupted run."""
    from sc6d_jax.train.checkpoint import checkpoint_dirs

    steps = 40
    ref = _run_standin(tmp_path / "ref" / "run", steps)
    run = tmp_path / "k" / "run"
    proc = subprocess.Popen(_script("run", "--out", str(run), "--steps", str(steps), "--delay", "0.05"),
                            env=_env(), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.time() + 120
        while time.time() < deadline and not any(s >= 10 for s, _ in checkpoint_dirs(run)):
            assert proc.poll() is None, proc.stderr.read().decode()
            time.sleep(0.02)
        time.sleep(0.17)  # somewhere between checkpoints (may be mid-write of one)
        assert proc.poll() is None, "run finished before it could be killed"
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == -signal.SIGKILL
    killed_at = max(r["step"] for r in _metrics(run))
    assert 10 <= killed_at < steps
    out = tmp_path / "resumed.npz"
    r = subprocess.run(_script("run", "--out", str(run), "--steps", str(steps), "--resume", "--params-out", str(out)),
                       env=_env(), capture_output=True, text=True, timeout=180)
    assert r.returncode == 0, r.stderr
    with np.load(out) as z:
        resumed = {k: z[k] for k in z.files}
    from sc6d_jax.train.checkpoint import flatten_with_paths

    expected = flatten_with_paths(ref, "params")
    assert resumed.keys() == expected.keys()
    for k in expected:
        np.testing.assert_array_equal(resumed[k], expected[k], err_msg=k)
    # the metrics file has one line per step, no duplicates from the killed part
    assert [m["step"] for m in _metrics(run)] == list(range(1, steps + 1))
    ref_loss = [m["loss"] for m in _metrics(tmp_path / "ref" / "run")]
    assert [m["loss"] for m in _metrics(run)] == ref_loss
    # the run's clock goes on across the legs (learning curves plot against it)
    for key in ("train_s", "elapsed_s"):
        ts = [m[key] for m in _metrics(run)]
        assert all(b >= a for a, b in zip(ts, ts[1:])), key


def test_two_host_devices_give_the_same_loss_curve(tmp_path):
    """Data parallel over 2 forced host devices == 1 device, within float tolerance."""
    _run_standin(tmp_path / "one" / "run", 15)
    two = tmp_path / "two" / "run"
    r = subprocess.run(_script("run", "--out", str(two), "--steps", "15"),
                       env=_env(XLA_FLAGS="--xla_force_host_platform_device_count=2"),
                       capture_output=True, text=True, timeout=180)
    assert r.returncode == 0, r.stderr
    meta = json.loads(sorted((two / "checkpoints").glob("ckpt_*/meta.json"))[-1].read_text())
    assert meta["device_count"] == 2
    l1 = np.array([m["loss"] for m in _metrics(tmp_path / "one" / "run")])
    l2 = np.array([m["loss"] for m in _metrics(two)])
    np.testing.assert_allclose(l2, l1, rtol=2e-5, atol=1e-6)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_two_processes_with_jax_distributed(tmp_path):
    """Two local processes joined by jax.distributed (gloo CPU collectives) train one model."""
    addr = f"127.0.0.1:{_free_port()}"
    run = tmp_path / "d" / "run"
    procs = [
        subprocess.Popen(
            _script("run", "--out", str(run), "--steps", "10", "--params-out", str(tmp_path / f"p{i}.npz"),
                    "--coordinator", addr, "--num-processes", "2", "--process-id", str(i)),
            env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        for i in range(2)
    ]
    try:
        outs = [p.communicate(timeout=240) for p in procs]
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    for p, (_, err) in zip(procs, outs):
        assert p.returncode == 0, err[-3000:]
    with np.load(tmp_path / "p0.npz") as a, np.load(tmp_path / "p1.npz") as b:
        for k in a.files:
            np.testing.assert_array_equal(a[k], b[k])  # replicated params agree
    meta = json.loads(sorted((run / "checkpoints").glob("ckpt_*/meta.json"))[-1].read_text())
    assert meta["process_count"] == 2 and meta["device_count"] == 2 and meta["step"] == 10
    m = _metrics(run)
    assert [r["step"] for r in m] == list(range(1, 11))


if __name__ == "__main__":
    sys.exit(_script_main(sys.argv[1:]))


def test_stream_settings_reach_the_stream(tmp_path):
    """occlusion, curriculum, distance, placement, image_border and colour_p of StreamSettings are
    passed to the crop stream's config."""
    from sc6d_jax.train import DataFns, StreamSettings, train

    seen = {}

    class Stop(Exception):
        pass

    def stream_config(**kw):
        seen.update(kw)
        raise Stop

    mf, _ = standin_fns()
    stream = StreamSettings(batch_size=8, occlusion=0.25, curriculum=7, distance=(3, 12), placement=[0.1, 0.9],
                            image_border=True, colour_p=0.0)
    assert stream.distance == (3.0, 12.0) and stream.placement == (0.1, 0.9)
    with pytest.raises(Stop):
        train(standin_config(2, stream=stream), tmp_path, tmp_path / "run", progress=False, verbose=False,
              model_fns=mf, data_fns=DataFns(stream_config, StandinStream, lambda cfg: (0.1, 1.0)))
    assert (seen["occlusion"], seen["curriculum"], seen["distance"]) == (0.25, 7, (3.0, 12.0))
    assert seen["placement"] == (0.1, 0.9) and seen["image_border"] is True and seen["colour_p"] == 0.0
    with pytest.raises(ValueError, match="stream.distance"):
        StreamSettings(distance=(5, 2))
    with pytest.raises(ValueError, match="stream.placement"):
        StreamSettings(placement=(0.2, 1.2))
    with pytest.raises(ValueError, match="stream.colour_p"):
        StreamSettings(colour_p=-0.1)


def _state(ckpt: Path, template):
    from sc6d_jax.checkpoint import read_checkpoint, read_ema

    params, _, _, _ = read_checkpoint(ckpt, template, None)
    return params, read_ema(ckpt, template)


def test_moving_average_of_parameters(tmp_path):
    """``ema``: the recursion with its ramp, checkpointed beside the raw parameters, resumed bit
    for bit, switched on at a resume, and never fed back into training."""
    import jax

    from sc6d_jax.train.checkpoint import checkpoint_dirs
    from sc6d_jax.train.loop import _ema_decay

    cfg = standin_config(ema=0.9)
    assert [float(_ema_decay(cfg, n)) for n in (0, 1, 80, 10_000)] == pytest.approx([0.1, 2 / 11, 0.9, 0.9])
    assert float(_ema_decay(cfg, 0, start=5)) == pytest.approx(0.9)  # switched on at a resume: no ramp
    plain = _run_standin(tmp_path / "plain" / "run", 12)
    run = tmp_path / "ema" / "run"
    returned = _run_standin(run, 12, ema=0.9, checkpoint_every=1, keep_checkpoints=20)
    template = jax.eval_shape(lambda p: p, plain)
    states = {s: _state(d, template) for s, d in checkpoint_dirs(run)}
    assert sorted(states) == list(range(1, 13))
    _assert_same_params(states[12][0], plain)  # the average never feeds back
    _assert_same_params(states[12][1][0], returned)  # train() returns the average
    assert all(states[s][1][1] == 0 for s in states)  # begun at step 0
    for s in range(2, 13):  # ema_s = d ema_{s-1} + (1 - d) p_s, d after s - 1 updates
        d = float(_ema_decay(cfg, s - 1))
        for e0, e1, p in zip(jax.tree.leaves(states[s - 1][1][0]), jax.tree.leaves(states[s][1][0]),
                             jax.tree.leaves(states[s][0])):
            np.testing.assert_allclose(e1, d * e0 + (1 - d) * p, rtol=1e-5, atol=1e-7)
    assert not np.array_equal(np.asarray(states[12][1][0]["fc1"]["w"]), np.asarray(plain["fc1"]["w"]))
    # resumed from step 6 (the later checkpoints removed): the same average and parameters
    legs = tmp_path / "legs" / "run"
    _run_standin(legs, 12, ema=0.9, checkpoint_every=3)
    for s, d in checkpoint_dirs(legs):
        if s > 6:
            shutil.rmtree(d)
    resumed = _run_standin(legs, 12, ema=0.9, checkpoint_every=3, resume=True)
    _assert_same_params(resumed, returned)
    _assert_same_params(_state(checkpoint_dirs(legs)[-1][1], template)[0], plain)
    # switched on when a plain run is resumed at step 5: the average starts there
    late = tmp_path / "late" / "run"
    _run_standin(late, 12)
    for s, d in checkpoint_dirs(late):
        if s > 5:
            shutil.rmtree(d)
    _run_standin(late, 12, ema=0.9, resume=True)
    params, (ema, start) = _state(checkpoint_dirs(late)[-1][1], template)
    assert start == 5
    _assert_same_params(params, plain)
    # no ramp when switched on late: decay 0.9 from the first update (the raw parameters of every
    # step are those of the averaged run above, which the average never changed)
    expect = jax.tree.map(np.asarray, states[5][0])
    for s in range(6, 13):
        expect = jax.tree.map(lambda e, p: 0.9 * e + 0.1 * p, expect, states[s][0])
    for x, y in zip(jax.tree.leaves(ema), jax.tree.leaves(expect)):
        np.testing.assert_allclose(x, y, rtol=1e-5, atol=1e-7)
