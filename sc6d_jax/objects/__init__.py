"""The built-in object set (14 generated objects with exact symmetries) and ``sc6d objects``."""

from sc6d_jax.objects._builtin import (
    ASYMMETRIC_IDS,
    DEFAULT_SEED,
    SYMMETRIC_IDS,
    BuiltinObject,
    builtin_objects,
    model_info,
    write_models,
)

__all__ = ["ASYMMETRIC_IDS", "DEFAULT_SEED", "SYMMETRIC_IDS", "BuiltinObject", "builtin_objects", "model_info", "write_models"]
