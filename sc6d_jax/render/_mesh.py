"""Mesh loading (OBJ / STL / PLY through trimesh) with explicit units and colour handling.

Conventions: the returned mesh is in millimetres, in the file's own frame (no re-centring),
and always carries per-face colours (uint8 RGBA) in ``mesh.visual.face_colors``: vertex
colours are averaged per face, textures are sampled at the vertices first. The renderer
bakes those face colours into a texture (MuJoCo has no per-vertex colour).
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

_UNIT_TO_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0}
_EXTENSIONS = (".ply", ".obj", ".stl")

#: Default colour of meshes without colour information (light grey).
DEFAULT_RGBA = (180, 180, 180, 255)


def load_mesh(path: str | os.PathLike, units: str = "mm") -> trimesh.Trimesh:
    """Load a triangle mesh and return it in millimetres with per-face colours.

    Args:
        path: an OBJ, STL or PLY file (BOP models are PLY in mm, often vertex-coloured).
        units: the unit of the file's coordinates: "mm" (default, BOP), "cm" or "m".

    Returns:
        A ``trimesh.Trimesh`` in mm, origin as in the file, ``visual.face_colors`` set.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: unknown units or extension, unparsable file, or a mesh with no faces.

    Warns:
        UserWarning when the diameter is implausible for the declared units (below 1 mm
        suggests metres passed as mm; above 10 m suggests the opposite).
    """
    path = Path(path)
    if units not in _UNIT_TO_MM:
        raise ValueError(f"units must be one of {sorted(_UNIT_TO_MM)}, got {units!r}")
    if not path.is_file():
        raise FileNotFoundError(f"mesh file not found: {path}")
    if path.suffix.lower() not in _EXTENSIONS:
        raise ValueError(f"unsupported mesh format {path.suffix!r} for {path} (use PLY, OBJ or STL)")
    try:
        loaded = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types on malformed files
        raise ValueError(f"cannot parse mesh file {path}: {exc}") from exc
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0 or len(loaded.vertices) == 0:
        raise ValueError(f"mesh file {path} contains no triangles")
    return prepare_mesh(loaded, units=units, name=str(path))


def prepare_mesh(mesh: trimesh.Trimesh, units: str = "mm", name: str = "mesh") -> trimesh.Trimesh:
    """Validate an in-memory mesh, scale it to mm and normalise its colours to face colours."""
    if units not in _UNIT_TO_MM:
        raise ValueError(f"units must be one of {sorted(_UNIT_TO_MM)}, got {units!r}")
    if not isinstance(mesh, trimesh.Trimesh):
        raise ValueError(f"{name}: expected a trimesh.Trimesh, got {type(mesh).__name__}")
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    if faces.ndim != 2 or len(faces) == 0 or len(vertices) == 0:
        raise ValueError(f"{name}: mesh has no triangles")
    if not np.all(np.isfinite(vertices)):
        raise ValueError(f"{name}: mesh has non-finite vertex coordinates")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise ValueError(f"{name}: face indices out of range")
    face_rgba = _face_colors(mesh)
    out = trimesh.Trimesh(vertices * _UNIT_TO_MM[units], faces, process=False)
    out.visual.face_colors = face_rgba
    diameter = mesh_diameter(out)
    if diameter <= 0:
        raise ValueError(f"{name}: mesh is degenerate (zero diameter)")
    if diameter < 1.0:
        warnings.warn(
            f"{name}: diameter {diameter:.4g} mm is implausibly small; were metres passed as "
            f"{units}? (use units='m')",
            UserWarning,
            stacklevel=3,
        )
    elif diameter > 10_000.0:
        warnings.warn(
            f"{name}: diameter {diameter:.4g} mm is implausibly large; check the units",
            UserWarning,
            stacklevel=3,
        )
    return out


def mesh_diameter(mesh: trimesh.Trimesh) -> float:
    """Largest distance between two vertices (computed on the convex hull), in mesh units."""
    v = np.asarray(mesh.vertices, dtype=np.float64)
    try:
        hull = np.asarray(mesh.convex_hull.vertices) if len(v) > 4 else v
    except Exception:  # degenerate (flat) meshes have no 3D hull
        hull = v
    if len(hull) > 4000:
        hull = hull[:: int(np.ceil(len(hull) / 4000))]
    d2 = ((hull[:, None, :] - hull[None, :, :]) ** 2).sum(-1)
    return float(np.sqrt(d2.max()))


def _face_colors(mesh: trimesh.Trimesh) -> np.ndarray:
    """Per-face RGBA uint8 (F, 4) from whatever colour information the mesh carries."""
    n_faces = len(mesh.faces)
    visual = mesh.visual
    if visual is None:
        return np.tile(np.array(DEFAULT_RGBA, np.uint8), (n_faces, 1))
    if visual.kind == "texture":
        try:
            visual = visual.to_color()
        except Exception:
            return np.tile(np.array(DEFAULT_RGBA, np.uint8), (n_faces, 1))
    if visual.kind == "vertex":
        vc = np.asarray(visual.vertex_colors, dtype=np.float64)
        fc = vc[np.asarray(mesh.faces)].mean(axis=1)
        return np.clip(np.round(fc), 0, 255).astype(np.uint8)
    if visual.kind == "face":
        return np.asarray(visual.face_colors, dtype=np.uint8).copy()
    return np.tile(np.array(DEFAULT_RGBA, np.uint8), (n_faces, 1))


@dataclass(frozen=True)
class BakedMesh:
    """A mesh prepared for MuJoCo: vertices (V,3) mm, faces (F,3), and either one RGBA colour
    (``texture is None``) or a per-face texture with one texcoord per face."""

    vertices: np.ndarray
    faces: np.ndarray
    rgba: tuple[float, float, float, float]
    texture: np.ndarray | None  # (Ht, Wt, 3) uint8
    texcoords: np.ndarray | None  # (F, 2) float, one per face (texel centre)
    normals: np.ndarray | None = None  # (V, 3) per-vertex normals (sharp edges split)


def _split_sharp_edges(mesh: trimesh.Trimesh, angle_deg: float = 30.0):
    """Vertices, faces and vertex normals with vertices split along edges sharper than
    ``angle_deg`` (flat faces look flat, curved surfaces stay smooth). Face order is kept."""
    try:
        sm = trimesh.graph.smooth_shade(mesh, angle=np.radians(angle_deg))
        if len(sm.faces) == len(mesh.faces) and np.allclose(
            sm.triangles_center, mesh.triangles_center, atol=1e-6
        ):
            return (np.asarray(sm.vertices, np.float64), np.asarray(sm.faces, np.int64),
                    np.asarray(sm.vertex_normals, np.float64))
    except Exception:  # pragma: no cover - fall back to fully flat shading
        pass
    faces = np.asarray(mesh.faces, np.int64)
    v = np.asarray(mesh.vertices, np.float64)[faces].reshape(-1, 3)
    n = np.repeat(np.asarray(mesh.face_normals, np.float64), 3, axis=0)
    return v, np.arange(len(v), dtype=np.int64).reshape(-1, 3), n


def bake_mesh(mesh: trimesh.Trimesh) -> BakedMesh:
    """Bake per-face colours into a texture atlas with one texel per face.

    Every corner of face k gets the texcoord of texel k's centre, so the colour is constant
    over the face and exact at any distance (zero UV derivatives: no mip-map bleeding).
    Uniformly coloured meshes use a plain RGBA instead.
    """
    fc = np.asarray(mesh.visual.face_colors, dtype=np.uint8)[:, :3]
    vertices, faces, normals = _split_sharp_edges(mesh)
    if len(fc) and np.all(fc == fc[0]):
        rgba = tuple(float(c) / 255.0 for c in fc[0]) + (1.0,)
        return BakedMesh(vertices, faces, rgba, None, None, normals)  # type: ignore[arg-type]
    n = len(faces)
    w = int(np.ceil(np.sqrt(n)))
    h = int(np.ceil(n / w))
    tex = np.zeros((h * w, 3), np.uint8)
    tex[:n] = fc
    k = np.arange(n)
    uv = np.stack([(k % w + 0.5) / w, (k // w + 0.5) / h], axis=1)
    return BakedMesh(vertices, faces, (1.0, 1.0, 1.0, 1.0), tex.reshape(h, w, 3), uv, normals)


def simplify_mesh(mesh: trimesh.Trimesh, max_faces: int) -> trimesh.Trimesh:
    """The mesh with at most ``max_faces`` faces, by vertex clustering on a cubic grid.

    The vertices in a grid cell merge into their mean; faces whose corners fall into fewer than
    three cells vanish; the others keep their orientation and face colour. The grid is the
    finest (cells of ``extent / k``, k found by bisection) that leaves at most ``max_faces``
    faces, so every vertex moves by less than a cell's diagonal. Meant for the training stream:
    a 64-pixel crop cannot show the detail of the 12k-50k-face LM-O models, which render about
    5x slower than a few thousand faces. A mesh already within the limit is returned as is.
    """
    max_faces = int(max_faces)
    if max_faces < 4:
        raise ValueError(f"max_faces must be >= 4, got {max_faces}")
    faces = np.asarray(mesh.faces, np.int64)
    if len(faces) <= max_faces:
        return mesh
    v = np.asarray(mesh.vertices, np.float64)
    fc = np.asarray(mesh.visual.face_colors, np.uint8)
    lo = v.min(axis=0)
    extent = float(np.ptp(v, axis=0).max()) or 1.0

    def cluster(k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        cell = np.minimum(np.floor((v - lo) / (extent / k)).astype(np.int64), k - 1)
        key = (cell[:, 0] * (k + 1) + cell[:, 1]) * (k + 1) + cell[:, 2]
        _, inv = np.unique(key, return_inverse=True)
        f = inv.reshape(-1)[faces]
        keep = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
        return inv.reshape(-1), f[keep], keep

    lo_k, hi_k = 1, 4096
    while lo_k < hi_k:  # the largest k whose mesh has at most max_faces faces
        k = (lo_k + hi_k + 1) // 2
        if len(cluster(k)[1]) <= max_faces:
            lo_k = k
        else:
            hi_k = k - 1
    inv, f, keep = cluster(lo_k)
    n = int(inv.max()) + 1
    count = np.bincount(inv, minlength=n).astype(np.float64)
    nv = np.stack([np.bincount(inv, weights=v[:, i], minlength=n) for i in range(3)], axis=1) / count[:, None]
    used = np.unique(f)  # drop vertices left without a face
    remap = np.full(n, -1, np.int64)
    remap[used] = np.arange(len(used))
    out = trimesh.Trimesh(nv[used], remap[f], process=False)
    out.visual.face_colors = fc[keep]
    return out
