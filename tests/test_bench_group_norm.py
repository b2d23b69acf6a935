"""experiments/bench_group_norm.py: the textbook form it times against is the same function as the
library's GroupNorm, the benchmark runs a real compiled step, and the shipped model's groups are
far from where the one-pass variance loses precision."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "experiments"))

import bench_group_norm  # noqa: E402

from sc6d_jax.model import group_norm  # noqa: E402


def test_textbook_form_is_the_library_function():
    rng = np.random.default_rng(0)
    with jax.enable_x64(True):
        for shape, per_sample in (((2, 6, 5, 8), False), ((3, 4, 4, 16), True), ((5, 12), False)):
            x = jnp.asarray(rng.normal(size=shape) * 1.5 + 0.7)
            c = shape[-1]
            sshape = (shape[0], c) if per_sample else (c,)
            s, b = jnp.asarray(rng.normal(size=sshape)), jnp.asarray(rng.normal(size=sshape))
            np.testing.assert_allclose(group_norm(x, s, b, 4), bench_group_norm.textbook_group_norm(x, s, b, 4),
                                       rtol=1e-10, atol=1e-10)


def test_benchmark_times_both_forms_of_each_layer_shape():
    rows = bench_group_norm.bench_layers(rounds=1, n=1)
    assert [r["what"] for r in rows] == [f"GroupNorm {s}" for s in bench_group_norm.SHAPES]
    assert all(r["textbook_ms"] > 0 and r["library_ms"] > 0 and r["ratio"] > 0 for r in rows)


@pytest.mark.slow  # about a minute: two compiles of the tiny step in a subprocess
def test_benchmark_times_both_forms_on_the_tiny_step(tmp_path, models):
    out = tmp_path / "b.json"
    r = subprocess.run([sys.executable, str(REPO / "experiments" / "bench_group_norm.py"), "--preset", "tiny",
                        "--models", str(models), "--rounds", "1", "--steps", "2", "--json", str(out)],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    rows = json.loads(out.read_text())["rows"]
    assert len(rows) == len(bench_group_norm.SHAPES) + 1 and rows[-1]["what"].startswith("training step, tiny")
    assert all(row["textbook_ms"] > 0 and row["library_ms"] > 0 for row in rows)


def test_stats_of_the_shipped_model(models):
    r = subprocess.run([sys.executable, str(REPO / "experiments" / "bench_group_norm.py"), "--stats", "builtin",
                        "--models", str(models)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    m = re.search(r"builtin: (\d+) GroupNorm layers, largest mean\^2/var of a group ([\d.]+)", r.stdout)
    assert m, r.stdout
    assert int(m.group(1)) > 10 and 0 < float(m.group(2)) < 100  # float32's one-pass form needs << 1e7


def test_stats_needs_the_models_folder(tmp_path):
    r = subprocess.run([sys.executable, str(REPO / "experiments" / "bench_group_norm.py"), "--stats", "builtin",
                        "--models", str(tmp_path / "none")], capture_output=True, text=True, timeout=300)
    assert r.returncode != 0 and "--models" in r.stderr
