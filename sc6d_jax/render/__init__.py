"""MuJoCo rendering: mesh loading, an exact pinhole renderer, depth for VSD.

Public surface: ``load_mesh``, ``Renderer`` (+ ``RenderOutput``, ``Primitive``, ``Light``),
``render_depth``, ``mesh_diameter``, ``simplify_mesh``. ``MUJOCO_GL`` defaults to "egl" (headless).
"""

import os

os.environ.setdefault("MUJOCO_GL", "egl")

from sc6d_jax.render._mesh import DEFAULT_RGBA, load_mesh, mesh_diameter, prepare_mesh, simplify_mesh
from sc6d_jax.render._renderer import (
    PRIMITIVE_SHAPES,
    Light,
    Primitive,
    Renderer,
    RenderOutput,
    render_depth,
    validate_intrinsics,
)

__all__ = [
    "DEFAULT_RGBA",
    "PRIMITIVE_SHAPES",
    "Light",
    "Primitive",
    "RenderOutput",
    "Renderer",
    "load_mesh",
    "mesh_diameter",
    "prepare_mesh",
    "render_depth",
    "simplify_mesh",
    "validate_intrinsics",
]
