"""Atomic training checkpoints: a re-export of :mod:`sc6d_jax.checkpoint`.

The checkpoint IO lives in the top-level module :mod:`sc6d_jax.checkpoint` (inference and
shipped models read checkpoints without the training package); this name is kept so that
``from sc6d_jax.train.checkpoint import ...`` keeps working.
"""

from __future__ import annotations

from sc6d_jax.checkpoint import *  # noqa: F401,F403
from sc6d_jax.checkpoint import __all__  # noqa: F401
