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

#: The primitive shapes drawn as clutter and occluders (the stream's and these scenes').
DISTRACTOR_SHAPES = ("box", "sphere", "cylinder", "ellipsoid")
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
                prims.append(Primitive(str(rng.choice(DISTRACTOR_SHAPES)), s,
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


#: The target's table (``StreamConfig.tabletop``): models and primitive shapes standing around it.
TABLE_MODELS = (1, 4)
TABLE_PRIMITIVES = (0, 2)
#: The table's half extent, in target diameters, and its thickness in median diameters.
TABLE_HALF = 8.0
TABLE_THICKNESS = 0.02
#: The table's colour: grey, its rendered shade (lights, shadows) to multiply a texture with
#: (``textured_table``).
TABLE_GREY = 0.75
#: Neighbours stand this many target diameters apart from the target's bounding sphere, at most.
TABLE_SPREAD = 1.5


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def table_under(rng: np.random.Generator, R: np.ndarray, t: np.ndarray,
                vertices: np.ndarray) -> tuple[np.ndarray, float]:
    """A table plane under an object posed (R, t) in the camera frame: ``(n, h)``, the plane's
    unit normal (towards the camera side) and offset, the plane being {x: n.x = h}.

    The normal is tilted TABLE_TILT_DEG from the direction from the object to the camera, turned
    about it at random; the plane touches the object's lowest point along n (min of n.(R v + t)
    over ``vertices`` equals h), so the object stands on it and the camera (the origin, n.0 = 0 >
    h) sees its top side."""
    d = -_unit(np.asarray(t, np.float64))
    a = np.cross(d, [1.0, 0.0, 0.0] if abs(d[0]) < 0.9 else [0.0, 1.0, 0.0])
    a = _unit(a)
    b = np.cross(d, a)
    phi = rng.uniform(0, 2 * np.pi)
    e = np.cos(phi) * a + np.sin(phi) * b
    tilt = np.radians(rng.uniform(*TABLE_TILT_DEG))
    n = np.cos(tilt) * d + np.sin(tilt) * e
    h = float(np.min((vertices @ R.T + t) @ n))
    return n, h


def support(shape: str, size, R: np.ndarray, n: np.ndarray) -> float:
    """How far a MuJoCo primitive (``shape``, ``size`` as :class:`~sc6d_jax.render.Primitive`
    takes it, rotation R) reaches from its centre along the unit direction n: centred that far
    above a plane of normal n, it rests on the plane."""
    s = np.asarray(size, np.float64)
    m = np.asarray(R, np.float64).T @ np.asarray(n, np.float64)  # n in the shape's frame
    if shape == "box":
        return float(np.abs(m) @ s)
    if shape == "sphere":
        return float(s[0])
    if shape == "ellipsoid":
        return float(np.linalg.norm(s * m))
    if shape in ("cylinder", "capsule"):  # radius s[0], half length s[1] along the shape's z
        c = abs(float(m[2]))
        if shape == "capsule":
            return float(c * s[1] + s[0])
        return float(c * s[1] + s[0] * np.sqrt(max(0.0, 1.0 - c * c)))
    raise ValueError(f"unknown primitive shape {shape!r}")


def tabletop_around(
    rng: np.random.Generator,
    obj_id: int,
    R: np.ndarray,
    t: np.ndarray,
    vertices: Mapping[int, np.ndarray],
    radii: Mapping[int, float],
    diameters: Mapping[int, float],
    ids: list[int],
    max_instances: int = 2,
    near: float = 10.0,
    spacing: tuple[float, float] | None = None,
):
    """The target ``obj_id`` at (R, t) standing on a table, with 1-4 other models and 0-2
    primitive shapes standing on the same table around it: ``(table, objects, primitives)``, the
    table a flat grey box :class:`~sc6d_jax.render.Primitive` (``textured_table`` gives its
    rendered pixels a texture), ``objects`` a list of (obj_id, R, t) of
    the neighbours (the target not included; at most ``max_instances`` of each id, the target's
    own counting one), ``primitives`` the shapes. A pure function of ``rng``.

    ``vertices``: obj_id -> points of the model (its hull's vertices will do); ``radii``: obj_id
    -> the largest distance of a model point from the model's origin. Every neighbour rests on
    the table (its lowest point on the plane) and its bounding sphere (about its origin) does not
    meet the target's, so nothing intersects the target; a neighbour that would reach the near
    plane is left out. Neighbours in front of the target may occlude it, as in a real scene.

    ``spacing``: ``(low, high)`` in target diameters: each neighbour stands instead that far (uniform)
    from the target along its direction in the table's plane, measured between the two shapes'
    extents along that direction (their support functions over ``vertices``), so that the
    plane perpendicular to it separates them: touching at 0, never intersecting. Photographed
    clutter touches and hides the target; bounding spheres keep every neighbour apart by the
    target's largest radius or more (None, the default). The same draws either way.
    """
    from sc6d_jax.render import Primitive

    R = np.asarray(R, np.float64)
    t = np.asarray(t, np.float64)
    n, h = table_under(rng, R, t, vertices[obj_id])
    # the table's frame: z along -n (the box's top face at the plane), x and y in it
    e1 = _unit(np.cross(n, [0.0, 0.0, 1.0] if abs(n[2]) < 0.9 else [1.0, 0.0, 0.0]))
    e2 = np.cross(n, e1)
    foot = t - (float(t @ n) - h) * n  # the target's centre dropped onto the plane
    d_t = float(diameters[obj_id])
    d_med = float(np.median([diameters[i] for i in ids]))
    thick = TABLE_THICKNESS * d_med
    R_tab = np.stack([e1, -e2, -n], axis=1)  # columns: the box's axes (right-handed)
    table = Primitive("box", (TABLE_HALF * d_t, TABLE_HALF * d_t, thick), (TABLE_GREY,) * 3, R_tab, foot - thick * n)
    r_t = float(radii[obj_id])
    target_v = vertices[obj_id] @ R.T  # the target's points about its centre, camera axes
    objects, used = [], {obj_id: 1}
    for _ in range(int(rng.integers(TABLE_MODELS[0], TABLE_MODELS[1] + 1))):
        oid = int(ids[rng.integers(len(ids))])
        R_o = random_rotation(rng)
        ang = rng.uniform(0, 2 * np.pi)
        u = np.cos(ang) * e1 + np.sin(ang) * e2
        v_o = vertices[oid] @ R_o.T  # its points about its centre, camera axes
        if spacing is None:
            dist = r_t + float(radii[oid]) + rng.uniform(0.0, TABLE_SPREAD) * d_t
        else:  # separated along u: the target's extent along u, the neighbour's along -u, the spacing
            dist = float(np.max(target_v @ u)) + float(np.max(-(v_o @ u))) + rng.uniform(*spacing) * d_t
        lift = -float(np.min(v_o @ n))  # its lowest point onto the plane
        c = foot + dist * u + lift * n
        apart = spacing is not None or np.linalg.norm(c - t) >= r_t + radii[oid]
        if used.get(oid, 0) >= max_instances or not apart or c[2] - radii[oid] < near:
            continue
        used[oid] = used.get(oid, 0) + 1
        objects.append((oid, R_o, c))
    prims = []
    for _ in range(int(rng.integers(TABLE_PRIMITIVES[0], TABLE_PRIMITIVES[1] + 1))):
        s = rng.uniform(0.1, 0.4, 3) * d_med
        shape = str(rng.choice(DISTRACTOR_SHAPES))
        R_p = random_rotation(rng)
        r_p = float(np.linalg.norm(s))  # a sphere about the shape's centre that holds it
        ang = rng.uniform(0, 2 * np.pi)
        u = np.cos(ang) * e1 + np.sin(ang) * e2
        if spacing is None:
            dist = r_t + r_p + rng.uniform(0.0, TABLE_SPREAD) * d_t
        else:
            dist = float(np.max(target_v @ u)) + support(shape, s, R_p, u) + rng.uniform(*spacing) * d_t
        c = foot + dist * u + support(shape, s, R_p, n) * n
        if c[2] - r_p < near:
            continue
        prims.append(Primitive(shape, s, rng.uniform(0, 1, 3), R_p, c))
    return table, objects, prims


def textured_table(rgb: np.ndarray, table_px: np.ndarray, texture: np.ndarray) -> np.ndarray:
    """``rgb`` with the pixels of a rendered TABLE_GREY table (``table_px``, bool (H, W)) replaced
    by ``texture`` (uint8 (H, W, 3)) times the table's rendered shade (its pixel over TABLE_GREY
    in [0, 255]): a textured table lit by the scene's lights, shadows included."""
    out = rgb.copy()
    shade = rgb[table_px].astype(np.float32) / np.float32(255.0 * TABLE_GREY)
    out[table_px] = np.clip(texture[table_px].astype(np.float32) * shade + 0.5, 0, 255).astype(np.uint8)
    return out
