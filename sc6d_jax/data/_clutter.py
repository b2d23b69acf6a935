"""Rendered tabletop clutter: backgrounds made of objects, not of procedural patterns.

A real test crop is full of real things around the target: other objects, standing on a table,
lit like the target and at its scale. :func:`clutter_scenes` renders such surroundings once,
as a bank of images the crop stream draws its backgrounds from (``StreamConfig.scene_backgrounds``):
a table top (a flat box of one colour, tilted 20-70 degrees away from facing the camera) with
6-14 of the models and 2-5 primitive shapes resting on it at random rotations, under the
stream's kind of random lights. The models appear at about the size the target has in its crop
(the bank image is cut into windows of half its side).
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

from sc6d_jax.backgrounds import random_background
from sc6d_jax.data._scene import random_rotation

__all__ = ["clutter_scenes"]

#: Models and primitives per scene.
N_MODELS = (6, 14)
N_PRIMITIVES = (2, 5)
#: Tilt of the table's normal from the viewing direction, degrees.
TABLE_TILT_DEG = (20.0, 70.0)


def _rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def clutter_scenes(
    meshes: Mapping[int, object], diameters: Mapping[int, float], n: int, size: int, rng: np.random.Generator,
) -> np.ndarray:
    """``n`` rendered clutter scenes, ``(n, size, size, 3)`` uint8, a pure function of ``rng``.

    ``meshes``: obj_id -> mesh in mm (the stream's, possibly simplified); ``diameters``: obj_id
    -> diameter in mm. The camera has f = ``size`` pixels; the table's centre lies at two median
    diameters, so a median model's diameter spans half the image (its silhouette about a third:
    in a window of half the image, about the size of the target in its crop).
    """
    from sc6d_jax.render import Light, Primitive, Renderer

    if n < 1 or size < 8:
        raise ValueError(f"clutter_scenes needs n >= 1 and size >= 8, got n={n}, size={size}")
    ids = sorted(int(i) for i in meshes)
    d_med = float(np.median([diameters[i] for i in ids]))
    K = np.array([[size, 0.0, (size - 1) / 2], [0.0, size, (size - 1) / 2], [0.0, 0.0, 1.0]])
    z0 = 2.0 * d_med
    max_inst = 2
    ren = Renderer(dict(meshes), size, size, max_instances=max_inst, n_primitives=1 + N_PRIMITIVES[1], n_lights=2,
                   near=0.05 * d_med, far=50.0 * d_med)
    out = np.empty((n, size, size, 3), np.uint8)
    try:
        for k in range(n):
            # the table: its normal tilted away from the camera's -z, turned about the view axis
            R_tab = _rot_z(rng.uniform(0, 2 * np.pi)) @ _rot_x(np.radians(rng.uniform(*TABLE_TILT_DEG)))
            e1, e2, nrm = R_tab[:, 0], R_tab[:, 1], -R_tab[:, 2]  # nrm points towards the camera
            centre = np.array([0.0, 0.0, z0])
            half = 3.0 * z0
            prims = [Primitive("box", (half, half, 0.02 * d_med), rng.uniform(0.05, 0.95, 3), R_tab,
                               centre - 0.02 * d_med * nrm)]
            spread = 0.55 * z0  # a little more than the half-width of the view at the table's centre
            objects, used = [], {}
            for _ in range(int(rng.integers(N_MODELS[0], N_MODELS[1] + 1))):
                oid = ids[int(rng.integers(len(ids)))]
                if used.get(oid, 0) >= max_inst:
                    continue
                used[oid] = used.get(oid, 0) + 1
                u, v = rng.uniform(-spread, spread, 2)
                objects.append((oid, random_rotation(rng), centre + u * e1 + v * e2 + 0.3 * diameters[oid] * nrm))
            for _ in range(int(rng.integers(N_PRIMITIVES[0], N_PRIMITIVES[1] + 1))):
                s = rng.uniform(0.1, 0.4, 3) * d_med
                u, v = rng.uniform(-spread, spread, 2)
                prims.append(Primitive(str(rng.choice(["box", "sphere", "cylinder", "ellipsoid"])), s,
                                       rng.uniform(0, 1, 3), random_rotation(rng),
                                       centre + u * e1 + v * e2 + 0.5 * float(s.max()) * nrm))
            lights = [Light(direction=rng.normal(size=3) + np.array([0, 0, 1.5]), diffuse=rng.uniform(0.2, 0.7),
                            specular=rng.uniform(0.0, 0.4)) for _ in range(int(rng.integers(1, 3)))]
            ren.set_lights(lights, headlight=(rng.uniform(0.1, 0.4), rng.uniform(0.1, 0.5)))
            # beyond the table's far edge (steep tilts show the horizon): a procedural background
            bg = random_background(rng, size)
            out[k] = ren.render(objects, K, primitives=prims, background=bg, depth=False).rgb
    finally:
        ren.close()
    return out
