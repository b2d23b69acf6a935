"""sc6d-jax: SC6D 6D object pose estimation in JAX.

From one RGB image, a camera matrix K and a 2D box, estimate an object's 6D pose without the
object's CAD model at inference and without prior knowledge of its symmetries.
"""

from sc6d_jax._version import __version__
from sc6d_jax.inference import Estimator

__all__ = ["Estimator", "__version__"]
