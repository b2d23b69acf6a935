"""GroupNorm's cost: the library's one-pass form against the textbook two-pass form.

    python experiments/bench_group_norm.py [--rounds 5] [--steps 20] [--obj-ids 1 ...] [--set KEY=VALUE ...] [--json OUT.json]
    python experiments/bench_group_norm.py --stats RUN [RUN ...] --models DIR

``sc6d_jax.model.group_norm`` reads the activations once for its statistics (mean and mean
square) and folds the normalisation and the learned scale and bias into one affine per sample
and channel. The textbook form (kept here as ``textbook_group_norm``) subtracts the mean, takes
the variance of the difference and then applies scale and bias, which XLA's gradient turns
into more passes over the activations. Two measurements, in alternating rounds on the same
inputs so that the shared machine's load falls on both alike:

1. GroupNorm alone, forward and backward (``jax.grad`` of a ReLU'd weighted sum), at the
   shapes of the ``cpu`` preset's layers (batch 32);
2. the whole compiled training step of ``--preset`` (``step_profile.py``'s setup: batches
   rendered beforehand) built once with each form.

Prints the medians of the rounds' medians and their ratio (textbook / library). The numbers
differ only by float32 rounding: the one-pass variance loses precision when a group's squared
mean is many times its variance (about 1e7 for float32; ``tests/test_model.py`` checks the form
against numpy at 900). ``--stats RUN ...`` prints, for trained models (run directories or
shipped names) on a batch of the stream's crops of their objects, the largest squared mean
over variance of any group in each GroupNorm layer.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "experiments"))
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

from sc6d_jax._subprocess import experiment_main  # noqa: E402

#: (B, H, W, C) of the cpu preset's GroupNorm layers at 64x64 crops (backbone, decoder, pose decoder)
SHAPES = ((32, 32, 32, 16), (32, 16, 16, 16), (32, 8, 8, 32), (32, 4, 4, 32), (32, 128))


def textbook_group_norm(x, scale, bias, groups: int, eps: float = 1e-5):
    """GroupNorm as written before: two passes for the statistics, then scale and bias."""
    import jax.numpy as jnp
    from jax import lax

    c = x.shape[-1]
    shape = x.shape
    xg = x.reshape(shape[0], -1, groups, c // groups)
    mean = jnp.mean(xg, axis=(1, 3), keepdims=True)
    var = jnp.mean(jnp.square(xg - mean), axis=(1, 3), keepdims=True)
    y = ((xg - mean) * lax.rsqrt(var + eps)).reshape(shape)
    if scale.ndim == 2 and x.ndim > 2:
        extra = (1,) * (x.ndim - 2)
        scale = scale.reshape(scale.shape[0], *extra, c)
        bias = bias.reshape(bias.shape[0], *extra, c)
    return y * scale + bias


@contextlib.contextmanager
def _group_norm_as(fn):
    """Models built or applied inside use ``fn`` as their GroupNorm (the encoder's and the pose
    decoder's); the library's form is back afterwards."""
    import sc6d_jax.model._encoder as enc
    import sc6d_jax.model._pose_decoder as pdec

    saved = enc.group_norm, pdec.group_norm
    enc.group_norm = pdec.group_norm = fn
    try:
        yield
    finally:
        enc.group_norm, pdec.group_norm = saved


def _timed(fn, n: int) -> float:
    import jax

    ts = []
    for _ in range(n):
        t = time.perf_counter()
        jax.block_until_ready(fn())
        ts.append(time.perf_counter() - t)
    return float(np.median(ts)) * 1e3


def bench_layers(rounds: int, n: int) -> list[dict]:
    import jax
    import jax.numpy as jnp

    from sc6d_jax.model import group_norm

    rows = []
    for shape in SHAPES:
        k1, k2 = jax.random.split(jax.random.PRNGKey(0))
        x = jax.random.normal(k1, shape) * 2.0 + 1.0
        w = jax.random.normal(k2, shape)
        c = shape[-1]
        s, b = jnp.full((c,), 1.1), jnp.full((c,), 0.1)
        fns = {}
        for name, gn in (("textbook", textbook_group_norm), ("library", group_norm)):
            g = jax.jit(jax.grad(lambda x, s, b, gn=gn: jnp.sum(jax.nn.relu(gn(x, s, b, 4)) * w), argnums=(0, 1, 2)))
            jax.block_until_ready(g(x, s, b))
            fns[name] = lambda g=g: g(x, s, b)
        per = {name: [] for name in fns}
        for _ in range(rounds):
            for name, f in fns.items():
                per[name].append(_timed(f, n))
        t, lib = float(np.median(per["textbook"])), float(np.median(per["library"]))
        rows.append({"what": f"GroupNorm {shape}", "textbook_ms": t, "library_ms": lib, "ratio": t / lib})
    return rows


def bench_step(a: argparse.Namespace, rounds: int, n: int) -> dict:
    import jax
    import jax.numpy as jnp

    import step_profile

    from sc6d_jax.model import group_norm

    forms = {"textbook": textbook_group_norm, "library": group_norm}
    with tempfile.TemporaryDirectory() as tmp:
        models = a.models
        if models is None:
            from sc6d_jax import objects

            models = Path(tmp) / "models"
            objects.write_models(models)
        sp_args = argparse.Namespace(preset=a.preset, obj_ids=a.obj_ids, set=a.set)
        steps, state = {}, {}
        for name, form in forms.items():
            with _group_norm_as(form):  # traced (at the first call) with this form
                step, params, opt, key, batches = step_profile._setup(sp_args, models)
                params, opt, m = step(params, opt, batches[0], jnp.int32(0), key)
                jax.block_until_ready(m)
            steps[name] = (step, key, batches)
            state[name] = [params, opt]  # the step donates its parameters and optimiser state: carry them
        per = {name: [] for name in steps}
        for _ in range(rounds):
            for name, (step, key, batches) in steps.items():
                st = state[name]

                def one(step=step, st=st, key=key, batches=batches, i=iter(range(10**9))):
                    k = next(i)
                    st[0], st[1], m = step(st[0], st[1], batches[k % 4], jnp.int32(k), key)
                    return m

                per[name].append(_timed(one, n))
    t, lib = float(np.median(per["textbook"])), float(np.median(per["library"]))
    sets = "".join(f" {x}" for x in a.set)
    return {"what": f"training step, {a.preset} preset, objects {a.obj_ids}{sets}", "textbook_ms": t,
            "library_ms": lib, "ratio": t / lib}


def group_stats(run: str, models: Path) -> list[float]:
    """Largest mean^2 / var of any group, per GroupNorm layer of ``run``'s model, over a batch of
    32 stream crops of its objects (seed 5, the full stream), in float64."""
    import jax
    import jax.numpy as jnp

    import step_profile

    from sc6d_jax.checkpoint import load_checkpoint
    from sc6d_jax.data import CropStream
    from sc6d_jax.model import apply, group_norm
    from sc6d_jax.pretrained import resolve

    params, cfg = load_checkpoint(resolve(run)[0])
    with CropStream(step_profile.full_stream_config(cfg, models, 32, seed=5)) as s:
        b = s.batch(0)
    worst: list[float] = []

    def recording(x, scale, bias, groups, eps=1e-5):
        xg = np.asarray(x, np.float64)
        xg = xg.reshape(xg.shape[0], -1, groups, xg.shape[-1] // groups)
        worst.append(float(np.max(xg.mean(axis=(1, 3)) ** 2 / (xg.var(axis=(1, 3)) + eps))))
        return group_norm(x, scale, bias, groups, eps)

    with _group_norm_as(recording), jax.disable_jit():
        apply(params, cfg.model, jnp.asarray(b["rgb"]), jnp.asarray(b["pe"]) if cfg.model.use_pe else None,
              jnp.asarray(b["obj_idx"]))
    return worst


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--rounds", type=int, default=5, help="alternating rounds (medians over them)")
    p.add_argument("--steps", type=int, default=20, help="timed calls per round")
    p.add_argument("--preset", default="cpu")
    p.add_argument("--obj-ids", type=int, nargs="+", default=[1])
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config override (repeatable)")
    p.add_argument("--models", type=Path, default=None, help="models folder (default: the built-in objects)")
    p.add_argument("--skip-step", action="store_true", help="GroupNorm alone, not the training step")
    p.add_argument("--stats", nargs="+", default=None, metavar="RUN",
                   help="instead: the largest mean^2/var of a group per GroupNorm layer of these trained models")
    p.add_argument("--json", type=Path, default=None, help="also write the figures here")
    a = p.parse_args(argv)

    def body() -> int:
        import jax

        if a.rounds < 1 or a.steps < 1:
            raise ValueError("--rounds and --steps must be positive")
        if a.stats:
            if a.models is None or not a.models.is_dir():
                raise FileNotFoundError("--stats needs --models DIR, the models folder the runs trained on")
            for run in a.stats:
                w = group_stats(run, a.models)
                print(f"{run}: {len(w)} GroupNorm layers, largest mean^2/var of a group {max(w):.1f} "
                      f"(per layer: {' '.join(f'{v:.1f}' for v in w)})")
            return 0
        rows = bench_layers(a.rounds, a.steps)
        if not a.skip_step:
            rows.append(bench_step(a, a.rounds, a.steps))
        print(f"{'textbook ms':>11}  {'library ms':>10}  {'ratio':>5}  what (medians of {a.rounds} alternating rounds)")
        for r in rows:
            print(f"{r['textbook_ms']:11.2f}  {r['library_ms']:10.2f}  {r['ratio']:5.2f}  {r['what']}")
        if a.json:
            from sc6d_jax._io import atomic_write_text

            atomic_write_text(a.json, json.dumps({"rows": rows, "rounds": a.rounds, "steps": a.steps,
                                                  "device": str(jax.devices()[0]), "cpu_count": os.cpu_count(),
                                                  "jax_version": jax.__version__}, indent=1) + "\n")
            print(f"wrote {a.json}")
        return 0

    return experiment_main("bench_group_norm", body)


if __name__ == "__main__":
    sys.exit(main())
