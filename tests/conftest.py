"""Shared test set-up: headless rendering, small thread pools, the shared data folder."""

from __future__ import annotations

import os
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

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
