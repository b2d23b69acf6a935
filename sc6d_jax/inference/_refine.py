"""Continuous rotation refinement beyond the paper.

Starting from the library's best rotation R0, maximise the cosine between the crop embedding f
and the SO(3) encoder's embedding g(R) over the rotation manifold. The rotation is parameterised
in the tangent space at R0, R(w) = R0 exp([w]x), so the problem is an unconstrained minimisation
of 1 - <f, g(R0 exp([w]x))> over w in R^3, solved by optimistix's BFGS, jit-compiled and
vmapped over the batch (``throw=False``; a failed solve keeps R0).
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
import optimistix as optx

from sc6d_jax.geometry import axis_angle_to_matrix


def refine_rotation(
    embed: Callable[[jax.Array], jax.Array],
    query: jax.Array,
    R0: jax.Array,
    max_steps: int = 32,
    tol: float = 1e-6,
) -> tuple[jax.Array, jax.Array]:
    """Refine one rotation. ``embed(R (3,3)) -> (E,)`` unit embedding; ``query`` (E,) unit.

    Returns (R, cosine). Never worse than R0: the result falls back to R0 when the solver's
    answer scores lower or the solve failed.
    """

    def loss(w, _):
        return 1.0 - jnp.dot(query, embed(R0 @ axis_angle_to_matrix(w)))

    sol = optx.minimise(
        loss, optx.BFGS(rtol=tol, atol=tol), jnp.zeros(3, R0.dtype), max_steps=max_steps, throw=False
    )
    R = R0 @ axis_angle_to_matrix(sol.value)
    c_new = jnp.dot(query, embed(R))
    c_old = jnp.dot(query, embed(R0))
    keep = (c_new >= c_old) & jnp.all(jnp.isfinite(R))
    return jnp.where(keep, R, R0), jnp.where(keep, c_new, c_old)


def refine_rotations(
    embed: Callable[[jax.Array, jax.Array], jax.Array],
    queries: jax.Array,
    R0: jax.Array,
    obj_idx: jax.Array,
    max_steps: int = 32,
) -> tuple[jax.Array, jax.Array]:
    """Batched :func:`refine_rotation`: ``embed(R (3,3), obj_idx ()) -> (E,)``; vmapped over B."""

    def one(q, r, o):
        return refine_rotation(lambda R: embed(R, o), q, r, max_steps=max_steps)

    return jax.vmap(one)(queries, R0, obj_idx)
