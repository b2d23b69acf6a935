"""Shared test set-up: headless rendering, small thread pools, the shared data folder."""

from __future__ import annotations

import os
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")


def _share_compiled_programs() -> None:
    """One persistent XLA compilation cache for the whole test session: the controller creates it
    before the xdist workers start, and workers and every ``sc6d`` subprocess inherit it through
    the environment, so that the same program (the tiny preset's train step, the predictor) is
    compiled once per session instead of once per process (a 12-step tiny training: 63 -> 36 s).
    A cached executable is the one a compile gives: runs stay bit for bit the same. Removed at
    the end of the session; a cache directory set by the user is used as it is."""
    import atexit
    import shutil
    import tempfile

    if os.environ.get("JAX_COMPILATION_CACHE_DIR"):
        return
    path = tempfile.mkdtemp(prefix="sc6d-jax-test-xla-")
    os.environ["JAX_COMPILATION_CACHE_DIR"] = path
    atexit.register(shutil.rmtree, path, True)


_share_compiled_programs()

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """``../shared/data`` beside the checkout; tests using it skip cleanly when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data folder not found at ../shared/data (expected {SHARED_DATA})")
    return SHARED_DATA


@pytest.fixture(scope="session")
def models(tmp_path_factory) -> Path:
    """The built-in objects as a BOP models/ folder, written once per test session (read-only use)."""
    from sc6d_jax.objects import write_models

    out = tmp_path_factory.mktemp("builtin") / "models"
    write_models(out)
    return out
