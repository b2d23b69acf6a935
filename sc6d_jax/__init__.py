"""sc6d-jax: SC6D 6D object pose estimation in JAX.

From one RGB image, a camera matrix K and a 2D box, estimate an object's 6D pose without the
object's CAD model at inference and without prior knowledge of its symmetries.

    from sc6d_jax import Estimator
    est = Estimator.load(run_dir)
    poses = est.predict(image, K, boxes, obj_ids)
"""

from typing import Any

from sc6d_jax._version import __version__

__all__ = ["Estimator", "__version__"]


def __getattr__(name: str) -> Any:  # lazy: `import sc6d_jax` and `sc6d --help` stay fast
    if name == "Estimator":
        from sc6d_jax.inference import Estimator

        return Estimator
    raise AttributeError(f"module 'sc6d_jax' has no attribute {name!r}")
