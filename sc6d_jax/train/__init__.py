"""Training: typed configs with presets, the training loop, atomic checkpoints, ``sc6d train``."""

from sc6d_jax.checkpoint import load_checkpoint, save_checkpoint
from sc6d_jax.train.config import PRESETS, OptimConfig, StreamSettings, TrainConfig, preset
from sc6d_jax.train.loop import (
    DataFns,
    ModelFns,
    NonFiniteLossError,
    initialize_distributed,
    make_optimizer,
    make_train_step,
    train,
)

__all__ = [
    "PRESETS",
    "DataFns",
    "ModelFns",
    "NonFiniteLossError",
    "OptimConfig",
    "StreamSettings",
    "TrainConfig",
    "initialize_distributed",
    "load_checkpoint",
    "make_optimizer",
    "make_train_step",
    "preset",
    "save_checkpoint",
    "train",
]
