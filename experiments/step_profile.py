"""Where a training step's time goes: XLA's own timings of one compiled step, by kind of work.

    python experiments/step_profile.py [--preset cpu] [--obj-ids 1] [--set KEY=VALUE ...] \\
        [--steps 10] [--models DIR] [--json OUT.json]

The step of ``--preset`` (with ``--set`` overrides, as ``sc6d train``) is compiled and run on a
few batches rendered beforehand by the crop stream (so the stream costs nothing here), timed
(median over ``--steps`` x 4 steps), then run ``--steps`` more times under ``jax.profiler``.
Every operation of the compiled program in the trace is put into one kind by what it computes
(the operation's source in the optimised HLO: a convolution in the forward pass or in the
gradient, a matrix product, a reduction, a layout copy) and the kinds' time per step is
printed, with XLA's count of the step's floating-point operations and the rate they run at.
Summed over threads, the kinds' times can exceed the step's wall time where operations
overlap. ``step_flops.py`` counts operations per configuration; this says where the time is.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import glob
import gzip
import json
import os
import re
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

from sc6d_jax._subprocess import experiment_main  # noqa: E402

#: kinds of work, in the order printed
KINDS = (
    "convolution, forward",
    "convolution, gradient",
    "matrix product, forward",
    "matrix product, gradient",
    "reduction (sums, means: GroupNorm statistics, bias gradients)",
    "layout copy (transpose)",
    "element-wise and other fusions",
)
_RUNTIME = ("ThunkExecutor", "$", "PjitFunction", "Common", "SlinkyThreadPool", "ParseArguments")


def op_kinds(hlo_text: str) -> dict[str, str]:
    """{instruction name: kind} of the optimised HLO's instructions (fusions named by what they
    wrap: the source op in their metadata, or their own name)."""
    kinds = {}
    for line in hlo_text.splitlines():
        m = re.match(r"\s*(?:ROOT )?%?([\w.\-]+) = ", line)
        if not m:
            continue
        name = m.group(1)
        src = re.search(r'op_name="([^"]*)"', line)
        src = src.group(1) if src else ""
        grad = "transpose(" in src
        if "conv_general_dilated" in src or name.startswith("conv"):
            kinds[name] = KINDS[1] if grad else KINDS[0]
        elif "dot_general" in src or name.startswith("dot") or re.search(r"\bdot\(", line):
            kinds[name] = KINDS[3] if grad else KINDS[2]
        elif "reduce_sum" in src or "reduce_max" in src or name.startswith("reduce"):
            kinds[name] = KINDS[4]
        elif name.startswith("transpose"):
            kinds[name] = KINDS[5]
        else:
            kinds[name] = KINDS[6]
    return kinds


def trace_times(trace_dir: str) -> dict[str, float]:
    """{operation name: total microseconds} of the newest perfetto trace under ``trace_dir``."""
    files = sorted(glob.glob(os.path.join(trace_dir, "**", "*perfetto_trace.json.gz"), recursive=True))
    if not files:
        raise RuntimeError(f"jax.profiler wrote no perfetto trace under {trace_dir}")
    with gzip.open(files[-1]) as f:
        tr = json.load(f)
    events = tr["traceEvents"] if isinstance(tr, dict) else tr
    out: collections.Counter = collections.Counter()
    for e in events:
        if e.get("ph") == "X" and "dur" in e and not e["name"].startswith(_RUNTIME):
            out[e["name"]] += float(e["dur"])
    return dict(out)


def full_stream_config(cfg, models: Path, batch_size: int, seed: int):
    """The crop stream of ``cfg``'s objects and options as after its curriculum, rendered in
    this process (no workers)."""
    from sc6d_jax.data import StreamConfig
    from sc6d_jax.train.loop import stream_fields

    kw = stream_fields(cfg, models, workers=0)
    kw.pop("curriculum", None)  # the full stream, as after the curriculum
    kw["models_dir"] = str(kw["models_dir"])
    return StreamConfig(batch_size=batch_size, seed=seed, **kw)


def _setup(a: argparse.Namespace, models: Path):
    import jax

    from sc6d_jax.data import CropStream, delta_z_range
    from sc6d_jax.model import init, loss_fn
    from sc6d_jax.train import preset
    from sc6d_jax.train.cli import apply_overrides
    from sc6d_jax.train.loop import make_optimizer, make_train_step, resolve_z_range

    cfg = preset(a.preset)
    if a.set:
        cfg = apply_overrides(cfg, a.set)
    cfg = cfg.replace(stream=dataclasses.replace(cfg.stream, obj_ids=tuple(a.obj_ids)),
                      model=dataclasses.replace(cfg.model, n_objects=len(a.obj_ids)))
    scfg = full_stream_config(cfg, models, cfg.stream.batch_size, seed=0)
    z_range = resolve_z_range(cfg, scfg, delta_z_range)
    cfg = cfg.replace(z_range=z_range)
    with CropStream(scfg) as s:
        batches = [jax.device_put(dict(s.batch(i))) for i in range(4)]
    tx, _ = make_optimizer(cfg)
    step = make_train_step(loss_fn, cfg, tx, z_range)
    params = init(jax.random.PRNGKey(0), cfg.model)
    return step, params, tx.init(params), jax.random.PRNGKey(1), batches


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--preset", default="cpu")
    p.add_argument("--obj-ids", type=int, nargs="+", default=[1])
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config override (repeatable)")
    p.add_argument("--steps", type=int, default=10, help="profiled steps (4x as many are timed)")
    p.add_argument("--models", type=Path, default=None, help="models folder (default: the built-in objects)")
    p.add_argument("--json", type=Path, default=None, help="also write the figures here")
    a = p.parse_args(argv)

    def body() -> int:
        import jax
        import jax.numpy as jnp

        if a.steps < 1:
            raise ValueError("--steps must be positive")
        with tempfile.TemporaryDirectory() as tmp:
            models = a.models
            if models is None:
                from sc6d_jax import objects

                models = Path(tmp) / "models"
                objects.write_models(models)
            if not models.is_dir():
                raise FileNotFoundError(f"models folder {models} does not exist")
            step, params, opt, key, batches = _setup(a, models)
            t0 = time.perf_counter()
            params, opt, m = step(params, opt, batches[0], jnp.int32(0), key)
            jax.block_until_ready(m)
            compile_s = time.perf_counter() - t0
            walls = []
            for i in range(4 * a.steps):
                t = time.perf_counter()
                params, opt, m = step(params, opt, batches[i % 4], jnp.int32(i), key)
                jax.block_until_ready(m)
                walls.append(time.perf_counter() - t)
            compiled = step.lower(params, opt, batches[0], jnp.int32(0), key).compile()
            cost = compiled.cost_analysis()
            cost = cost[0] if isinstance(cost, list) else cost
            flops = float((cost or {}).get("flops", float("nan")))
            kinds = op_kinds(compiled.as_text())
            trace_dir = os.path.join(tmp, "trace")
            with jax.profiler.trace(trace_dir, create_perfetto_trace=True):
                for i in range(a.steps):
                    params, opt, m = step(params, opt, batches[i % 4], jnp.int32(i), key)
                    jax.block_until_ready(m)
            times = trace_times(trace_dir)
        per_kind = collections.Counter()
        unmatched = 0.0
        for name, us in times.items():
            kind = kinds.get(name) or kinds.get(re.sub(r"\.\d+$", "", name))
            if kind is None:
                unmatched += us
                continue
            per_kind[kind] += us / a.steps / 1000.0
        wall_ms = float(np.median(walls)) * 1000.0
        total = sum(per_kind.values())
        print(f"{a.preset} preset, objects {a.obj_ids}{' ' + ' '.join(a.set) if a.set else ''}: "
              f"median step {wall_ms:.1f} ms ({1000.0 / wall_ms:.2f} steps/s; compile {compile_s:.1f} s); "
              f"{flops / 1e9:.2f} GFLOP per step, {flops / 1e9 / (wall_ms / 1000.0):.0f} GFLOP/s")
        print(f"{'ms per step':>11}  {'share':>5}  kind of work (summed over the program's operations)")
        for k in KINDS:
            print(f"{per_kind[k]:11.2f}  {per_kind[k] / max(total, 1e-9):5.0%}  {k}")
        print(f"{total:11.2f}         all operations ({unmatched / a.steps / 1000.0:.2f} ms per step in "
              "trace events not found in the program)")
        if a.json:
            from sc6d_jax._io import atomic_write_text

            atomic_write_text(a.json, json.dumps({
                "preset": a.preset, "obj_ids": a.obj_ids, "set": a.set, "step_ms_median": wall_ms,
                "compile_s": compile_s, "gflop_per_step": flops / 1e9, "ms_per_step_by_kind": dict(per_kind),
                "device": str(jax.devices()[0]), "jax_version": jax.__version__,
            }, indent=1) + "\n")
            print(f"wrote {a.json}")
        return 0

    return experiment_main("step_profile", body)


if __name__ == "__main__":
    raise SystemExit(main())
