"""The built-in object set: 14 objects generated with trimesh from a seed (no download).

Every object is 4-20 cm (largest extent), in millimetres, centred (symmetric objects on their
symmetry centre, so every symmetry has t = 0; the others on their bounding-box centre), and coloured so
that its intended symmetry holds visually (symmetric objects in one colour, asymmetric
composites with one colour per part). ``models_info.json`` carries the diameter, extents and
the exact symmetries in BOP's format (for evaluation only: training never reads them).

| id | name | symmetry |
|---|---|---|
| 1 | L-bracket with knob | none |
| 2 | cylinder | continuous about z, 180 deg flip about x |
| 3 | cone | continuous about z |
| 4 | torus | continuous about z, 180 deg flip about x |
| 5 | box (3 different extents) | 180 deg about x, y, z |
| 6 | cube | the 24 rotations of the cube |
| 7 | hexagonal prism | 6-fold about z, 6 flips |
| 8 | mug (cylinder + handle) | none |
| 9 | hammer (handle + head + claw) | none |
| 10 | triangular prism | 3-fold about z, 3 flips |
| 11 | square pyramid | 4-fold about z |
| 12 | T-piece with cap | none |
| 13 | dumbbell (unequal ends) | none |
| 14 | staircase block | none |
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import trimesh

from sc6d_jax._io import atomic_directory, atomic_write_bytes
from sc6d_jax.bop import ModelInfo, write_models_info
from sc6d_jax.render._mesh import mesh_diameter

DEFAULT_SEED = 0


@dataclass(frozen=True)
class BuiltinObject:
    obj_id: int
    name: str
    mesh: trimesh.Trimesh  # mm, vertex colours set
    symmetries_discrete: tuple[np.ndarray, ...]  # (4, 4) each, identity excluded
    symmetries_continuous: tuple[dict, ...]  # {"axis": (3,), "offset": (3,)}

    @property
    def symmetric(self) -> bool:
        return bool(self.symmetries_discrete or self.symmetries_continuous)


def _rot(axis, angle) -> np.ndarray:
    return trimesh.transformations.rotation_matrix(angle, axis)[:3, :3]


def _sym(R: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = np.round(R, 12) + 0.0
    return T


def _colour(mesh: trimesh.Trimesh, rgb) -> trimesh.Trimesh:
    mesh = mesh.copy()
    mesh.visual = trimesh.visual.ColorVisuals(mesh, vertex_colors=np.tile([*rgb, 255], (len(mesh.vertices), 1)).astype(np.uint8))
    return mesh


def _parts(*parts) -> trimesh.Trimesh:
    return trimesh.util.concatenate([_colour(m, c) for m, c in parts])


def _placed(mesh: trimesh.Trimesh, xyz=(0, 0, 0), R=None) -> trimesh.Trimesh:
    mesh = mesh.copy()
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R
    T[:3, 3] = xyz
    mesh.apply_transform(T)
    return mesh


def _cube_group() -> list[np.ndarray]:
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1, -1), repeat=3):
            R = np.zeros((3, 3))
            for i, (p, s) in enumerate(zip(perm, signs)):
                R[i, p] = s
            if np.isclose(np.linalg.det(R), 1) and not np.allclose(R, np.eye(3)):
                out.append(R)
    return out


def _dihedral(n: int, flips: bool) -> list[np.ndarray]:
    out = [_rot([0, 0, 1], 2 * np.pi * k / n) for k in range(1, n)]
    if flips:
        out += [_rot([np.cos(np.pi * k / n), np.sin(np.pi * k / n), 0], np.pi) for k in range(n)]
    return out


def _make(rng: np.random.Generator) -> list[tuple[str, trimesh.Trimesh, list[np.ndarray], list[dict]]]:
    u = lambda lo, hi: float(rng.uniform(lo, hi))  # noqa: E731
    palette = rng.permutation(
        np.array(
            [[220, 60, 50], [40, 120, 220], [240, 190, 40], [60, 170, 80], [160, 80, 190], [240, 130, 40],
             [30, 170, 170], [200, 60, 140], [120, 120, 120], [140, 90, 50], [90, 200, 230], [230, 230, 220]],
            np.uint8,
        )
    )
    col = lambda i: tuple(int(v) for v in palette[i % len(palette)])  # noqa: E731
    z_axis = {"axis": np.array([0.0, 0.0, 1.0]), "offset": np.zeros(3)}
    flip_x = _rot([1, 0, 0], np.pi)
    objs = []

    # 1 L-bracket with knob (asymmetric)
    a, b, th = u(90, 130), u(50, 80), u(16, 24)
    objs.append(("l_bracket", _parts(
        (_placed(trimesh.creation.box((a, th, th)), (0, 0, 0)), col(0)),
        (_placed(trimesh.creation.box((th, b, th)), (a / 2 - th / 2, b / 2 + th / 2, 0)), col(1)),
        (_placed(trimesh.creation.icosphere(2, th * 0.8), (-a / 2 + th, 0, th * 0.9)), col(2)),
    ), [], []))
    # 2 cylinder
    r, h = u(25, 40), u(80, 140)
    objs.append(("cylinder", _colour(trimesh.creation.cylinder(r, h, sections=64), col(3)), [flip_x], [z_axis]))
    # 3 cone
    r, h = u(30, 45), u(70, 120)
    cone = _placed(trimesh.creation.cone(r, h, sections=64), (0, 0, -h / 2))
    objs.append(("cone", _colour(cone, col(4)), [], [z_axis]))
    # 4 torus
    R_, r_ = u(40, 55), u(10, 16)
    objs.append(("torus", _colour(trimesh.creation.torus(R_, r_, major_sections=64, minor_sections=24), col(5)), [flip_x], [z_axis]))
    # 5 box with three different extents
    ex = sorted([u(40, 60), u(70, 90), u(110, 150)])
    box_syms = [_rot([1, 0, 0], np.pi), _rot([0, 1, 0], np.pi), _rot([0, 0, 1], np.pi)]
    objs.append(("box", _colour(trimesh.creation.box((ex[2], ex[1], ex[0])), col(6)), box_syms, []))
    # 6 cube
    s = u(60, 90)
    objs.append(("cube", _colour(trimesh.creation.box((s, s, s)), col(7)), _cube_group(), []))
    # 7 hexagonal prism
    r, h = u(35, 50), u(60, 110)
    hexa = trimesh.creation.cylinder(r, h, sections=6)
    objs.append(("hex_prism", _colour(hexa, col(8)), _dihedral(6, True), []))
    # 8 mug: cylinder body + box handle (asymmetric in pose; mirror symmetry is not a rotation)
    r, h = u(30, 40), u(80, 110)
    body = trimesh.creation.cylinder(r, h, sections=48)
    handle = _placed(trimesh.creation.box((r * 0.7, 10, h * 0.6)), (r + r * 0.3, 0, 0))
    cap = _placed(trimesh.creation.cylinder(r * 0.9, 4, sections=48), (0, 0, h / 2 + 2))
    objs.append(("mug", _parts((body, col(9)), (handle, col(10)), (cap, col(11))), [], []))
    # 9 hammer
    L = u(130, 170)
    objs.append(("hammer", _parts(
        (_placed(trimesh.creation.cylinder(9, L, sections=24), (0, 0, 0)), col(0)),
        (_placed(trimesh.creation.box((70, 24, 24)), (10, 0, L / 2)), col(7)),
        (_placed(trimesh.creation.box((24, 14, 30)), (-35, 0, L / 2 - 16)), col(3)),
    ), [], []))
    # 10 triangular prism (equilateral cross-section)
    r, h = u(35, 50), u(70, 120)
    objs.append(("tri_prism", _colour(trimesh.creation.cylinder(r, h, sections=3), col(2)), _dihedral(3, True), []))
    # 11 square pyramid
    b2, h = u(35, 50), u(60, 100)
    pyr = trimesh.creation.cone(b2 * np.sqrt(2), h, sections=4)
    pyr = _placed(pyr, (0, 0, -h / 2))
    objs.append(("pyramid", _colour(pyr, col(5)), _dihedral(4, False), []))
    # 12 T-piece with cap
    a, th = u(100, 140), u(18, 26)
    objs.append(("t_piece", _parts(
        (trimesh.creation.box((a, th, th)), col(1)),
        (_placed(trimesh.creation.box((th, th, a * 0.7)), (0, 0, -a * 0.35 - th / 2)), col(4)),
        (_placed(trimesh.creation.box((th * 1.4, th * 1.4, th * 0.6)), (a / 2, 0, 0)), col(8)),
    ), [], []))
    # 13 dumbbell with unequal ends and a coloured band
    L = u(110, 150)
    objs.append(("dumbbell", _parts(
        (_placed(trimesh.creation.cylinder(8, L, sections=24), (0, 0, 0)), col(9)),
        (_placed(trimesh.creation.icosphere(2, 26), (0, 0, L / 2)), col(6)),
        (_placed(trimesh.creation.box((40, 40, 40)), (0, 0, -L / 2)), col(0)),
        (_placed(trimesh.creation.box((20, 20, 20)), (14, 0, 0)), col(2)),
    ), [], []))
    # 14 staircase block
    w = u(40, 60)
    steps = [(_placed(trimesh.creation.box((30, w, 25 * (k + 1))), (30 * k, 0, 12.5 * (k + 1))), col(3 + 2 * k)) for k in range(3)]
    objs.append(("staircase", _parts(*steps), [], []))
    return objs


def builtin_objects(seed: int = DEFAULT_SEED) -> list[BuiltinObject]:
    """The 14 built-in objects for ``seed`` (sizes and colours are drawn from it)."""
    rng = np.random.default_rng(seed)
    out = []
    for i, (name, mesh, disc, cont) in enumerate(_make(rng), start=1):
        mesh = trimesh.Trimesh(mesh.vertices, mesh.faces, vertex_colors=mesh.visual.vertex_colors, process=False)
        if not (disc or cont):  # symmetric shapes are built around their symmetry centre (t = 0)
            lo, hi = mesh.bounds
            mesh.apply_translation(-(lo + hi) / 2)  # asymmetric ones: origin at the box centre
        out.append(BuiltinObject(i, name, mesh, tuple(_sym(R) for R in disc), tuple(cont)))
    return out


def model_info(obj: BuiltinObject) -> ModelInfo:
    lo, hi = obj.mesh.bounds
    return ModelInfo(
        obj.obj_id,
        mesh_diameter(obj.mesh),
        tuple(float(v) for v in lo),  # type: ignore[arg-type]
        tuple(float(v) for v in hi - lo),  # type: ignore[arg-type]
        [np.asarray(s) for s in obj.symmetries_discrete],
        [dict(s) for s in obj.symmetries_continuous],
    )


def write_models(out_dir: str | Path, seed: int = DEFAULT_SEED, overwrite: bool = False) -> Path:
    """Write the built-in set as a BOP ``models/`` folder (PLY in mm with vertex colours + models_info.json).

    Written into a temporary folder and renamed, so a failure leaves nothing behind.
    """
    out_dir = Path(out_dir)
    objs = builtin_objects(seed)
    with atomic_directory(out_dir, overwrite=overwrite) as tmp:
        for o in objs:
            data = trimesh.exchange.ply.export_ply(o.mesh, encoding="binary", vertex_normal=False)
            atomic_write_bytes(tmp / f"obj_{o.obj_id:06d}.ply", data)
        write_models_info(tmp / "models_info.json", {o.obj_id: model_info(o) for o in objs})
    return out_dir


SYMMETRIC_IDS = tuple(o.obj_id for o in builtin_objects() if o.symmetric)
ASYMMETRIC_IDS = tuple(o.obj_id for o in builtin_objects() if not o.symmetric)
