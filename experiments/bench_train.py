"""Benchmark of the training program: steps/s and crops/s per preset, stream vs pre-rendered.

For each preset, one subprocess (so that peak memory is per preset) runs the real training loop
(:func:`sc6d_jax.train.train`) twice with the same config, hence one compilation:

- ``prerendered``: batches rendered once by the crop stream beforehand and cycled;
- ``stream``: batches rendered on the fly by ``sc6d_jax.data.CropStream`` (worker processes).

Each run logs every ``--window`` steps; the first window (compilation) is dropped and the
median of the remaining windows is the run's figure.  The two modes alternate for ``--rounds``
rounds (the machine's load drifts), and the medians over rounds are reported, with the stream
overhead of each round.  The stream alone is also timed (batches/s with
the same workers).  Peak memory is ``resource.getrusage`` maxrss of the process and of its
largest child (the stream workers).

Usage::

    .venv/bin/python experiments/bench_train.py                      # cpu preset
    .venv/bin/python experiments/bench_train.py --presets cpu paper --paper-batch 8
    .venv/bin/python experiments/bench_train.py --models DIR --json out.json
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")


def _models_dir(arg: str | None, tmp: Path) -> Path:
    if arg:
        return Path(arg)
    from sc6d_jax import objects

    out = tmp / "models"
    objects.write_models(out)
    return out


def _one(preset_name: str, models: Path, windows: int, window: int, workers: int | None, batch: int | None,
         rounds: int = 1) -> dict:
    import numpy as np

    from sc6d_jax import data
    from sc6d_jax.train import DataFns, StreamSettings, preset, train
    from sc6d_jax.train.loop import _default_data_fns

    cfg = preset(preset_name)
    if batch is not None:
        cfg = cfg.replace(stream=StreamSettings(batch_size=batch, augment=cfg.stream.augment))
    steps = window * (windows + 1)
    cfg = cfg.replace(steps=steps, log_every=window, checkpoint_every=steps, keep_checkpoints=1)
    cfg = cfg.replace(optim=cfg.optim.__class__(**{**cfg.optim.__dict__, "warmup_steps": 0}))
    dfs = _default_data_fns()

    # the stream alone
    scfg = dfs.stream_config(models_dir=models, crop_size=cfg.model.crop_size, batch_size=cfg.stream.batch_size,
                             seed=0, workers=workers, obj_ids=None, augment=cfg.stream.augment)
    with data.CropStream(scfg, 0) as s:
        it = iter(s)
        next(it)
        t = time.perf_counter()
        n_stream = max(8, windows * window // 4)
        pre = [next(it) for _ in range(n_stream)]
        stream_bps = n_stream / (time.perf_counter() - t)

    class Cycle:
        def __init__(self, cfg_, start):
            self.obj_ids = s.obj_ids
            self.it = itertools.cycle(pre)

        def __iter__(self):
            return self

        def __next__(self):
            return next(self.it)

        def close(self):
            pass

    res: dict = {"preset": preset_name, "batch_size": cfg.stream.batch_size, "crop_size": cfg.model.crop_size,
                 "stream_batches_per_s": stream_bps, "workers": workers}
    per_round: dict[str, list[float]] = {"prerendered": [], "stream": []}
    walls: dict[str, list[float]] = {"prerendered": [], "stream": []}
    with tempfile.TemporaryDirectory() as tmp:
        # the two modes alternate, round after round, so that a change in the machine's load
        # hits both; each round's figure is the median of its windows (compile window dropped)
        for rnd in range(rounds):
            for mode, fns in (("prerendered", DataFns(dfs.stream_config, Cycle, dfs.z_range)), ("stream", dfs)):
                run = Path(tmp) / f"{mode}{rnd}"
                t0 = time.perf_counter()
                train(cfg, models, run, workers=workers, progress=False, verbose=False, data_fns=fns)
                walls[mode].append(time.perf_counter() - t0)
                recs = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
                per_round[mode].append(float(np.median([r["crops_per_s"] for r in recs[1:]])))
    for mode in per_round:
        crops = float(np.median(per_round[mode]))
        res[mode] = {"crops_per_s": crops, "steps_per_s": crops / cfg.stream.batch_size,
                     "rounds_crops_per_s": per_round[mode], "wall_s": walls[mode]}
    step_s = 1.0 / res["prerendered"]["steps_per_s"]
    overheads = [1.0 - s_ / p_ for s_, p_ in zip(per_round["stream"], per_round["prerendered"])]
    res["stream_overhead_frac"] = float(np.median(overheads))
    res["stream_overhead_rounds"] = overheads
    res["stream_time_frac_if_serial"] = (1.0 / stream_bps) / step_s
    ru_self = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    ru_child = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0
    res["peak_rss_mb"] = {"self": ru_self, "largest_child": ru_child}
    return res


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--presets", nargs="+", default=["cpu"])
    p.add_argument("--models", default=None, help="models folder (default: the built-in objects)")
    p.add_argument("--windows", type=int, default=5, help="timed windows after the compile window")
    p.add_argument("--window", type=int, default=10, help="steps per window")
    p.add_argument("--paper-windows", type=int, default=2)
    p.add_argument("--paper-window", type=int, default=1)
    p.add_argument("--paper-batch", type=int, default=None, help="batch size for the paper preset (default 64)")
    p.add_argument("--workers", type=int, default=None)
    p.add_argument("--rounds", type=int, default=3,
                   help="alternating prerendered/stream rounds; figures are medians over rounds")
    p.add_argument("--json", default=None, help="write the results here")
    p.add_argument("--_one", default=None, help=argparse.SUPPRESS)
    a = p.parse_args(argv)

    if a._one:
        name = a._one
        paper = name == "paper"
        r = _one(name, Path(a.models), a.paper_windows if paper else a.windows, a.paper_window if paper else a.window,
                 a.workers, a.paper_batch if paper else None, a.rounds)
        print("RESULT " + json.dumps(r), flush=True)
        return 0

    results = []
    with tempfile.TemporaryDirectory() as tmp:
        models = _models_dir(a.models, Path(tmp))
        for name in a.presets:
            cmd = [sys.executable, __file__, "--_one", name, "--models", str(models), "--windows", str(a.windows),
                   "--window", str(a.window), "--paper-windows", str(a.paper_windows),
                   "--paper-window", str(a.paper_window), "--rounds", str(a.rounds)]
            if a.paper_batch:
                cmd += ["--paper-batch", str(a.paper_batch)]
            if a.workers is not None:
                cmd += ["--workers", str(a.workers)]
            out = subprocess.run(cmd, capture_output=True, text=True)
            line = [x for x in out.stdout.splitlines() if x.startswith("RESULT ")]
            if out.returncode or not line:
                print(out.stderr[-3000:], file=sys.stderr)
                return 1
            r = json.loads(line[-1][7:])
            results.append(r)
            print(f"{name:6s} batch {r['batch_size']:3d} crop {r['crop_size']:3d}: "
                  f"prerendered {r['prerendered']['steps_per_s']:.2f} steps/s ({r['prerendered']['crops_per_s']:.0f} crops/s); "
                  f"stream {r['stream']['steps_per_s']:.2f} steps/s ({r['stream']['crops_per_s']:.0f} crops/s); "
                  f"stream overhead {100 * r['stream_overhead_frac']:.1f} % (median of rounds: "
                  f"{', '.join(f'{100 * x:.1f}' for x in r['stream_overhead_rounds'])}); stream alone {r['stream_batches_per_s']:.1f} batches/s "
                  f"({100 * r['stream_time_frac_if_serial']:.1f} % of a step if serial); "
                  f"peak RSS {r['peak_rss_mb']['self']:.0f} MB (+ largest child {r['peak_rss_mb']['largest_child']:.0f} MB)",
                  flush=True)
    if a.json:
        Path(a.json).write_text(json.dumps(results, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
