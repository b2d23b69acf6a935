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


@pytest.fixture(scope="session")
def gt_estimates():
    """``make(dataset, change)``: the ground truth of a BOP dataset's targets as
    ``PoseEstimate`` (score 1, time 0.1), each target's instance (visible fraction >= 0.1) passed
    with its index k in its image to ``change(k, gt)``, which returns the estimate's ``(R, t)``
    or None to leave the target without one. Returns the estimates and the k of each."""
    def make(ds, change):
        from sc6d_jax.bop import PoseEstimate

        ests, ks = [], []
        for scene_id, im_id in sorted({(t.scene_id, t.im_id) for t in ds.targets()}):
            targets = {t.obj_id for t in ds.targets() if (t.scene_id, t.im_id) == (scene_id, im_id)}
            k = 0
            for g, inf in zip(ds.scene_gt(scene_id)[im_id], ds.scene_gt_info(scene_id)[im_id]):
                if g.obj_id not in targets or inf.visib_fract < 0.1:
                    continue
                pose = change(k, g)
                if pose is not None:
                    ests.append(PoseEstimate(scene_id, im_id, g.obj_id, 1.0, pose[0], pose[1], 0.1))
                    ks.append(k)
                k += 1
        return ests, ks

    return make


@pytest.fixture(scope="session")
def micro_model():
    """``make(**fields)``: a ModelConfig of one object small enough to compile in seconds (32-pixel
    crops, width 8), with the given fields set on top."""
    def make(**fields):
        from sc6d_jax import model

        base = dict(n_objects=1, crop_size=32, backbone="tiny", width=8, decoder_width=8, feat_dim=8, pose_width=8,
                    head_hidden=16, so3_hidden=16, n_z_bins=8, conv_impl="lax", gn_groups=4)
        return model.ModelConfig(**{**base, **fields})

    return make
