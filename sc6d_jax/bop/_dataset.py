"""Reading BOP datasets written by anyone (BOP toolkit layout).

    root/
      models/ (obj_XXXXXX.ply, models_info.json)   models_eval/ (optional)
      camera.json (optional)   test_targets_bop19.json (optional)
      <split>/<scene:06d>/ scene_camera.json scene_gt.json scene_gt_info.json
                            rgb/ (or gray/) depth/ mask/ mask_visib/
"""

from __future__ import annotations

import functools
from pathlib import Path

import cv2
import numpy as np

from sc6d_jax.bop._formats import (
    BopFormatError,
    Camera,
    GtInfo,
    GtPose,
    ModelInfo,
    Target,
    parse_models_info,
    parse_scene_camera,
    parse_scene_gt,
    parse_scene_gt_info,
    parse_targets,
)

_IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".tif")


def model_path(models_dir: str | Path, obj_id: int) -> Path:
    """``models_dir/obj_{obj_id:06d}.ply``; FileNotFoundError naming it when absent."""
    p = Path(models_dir) / f"obj_{int(obj_id):06d}.ply"
    if not p.is_file():
        raise FileNotFoundError(f"{p}: model of object {obj_id} not found")
    return p


def load_models_info(path: str | Path) -> dict[int, ModelInfo]:
    """Parse ``models_info.json`` (a file, or a models folder that holds one)."""
    path = Path(path)
    if path.is_dir():
        path = path / "models_info.json"
    return parse_models_info(path)


def _ascii_ply_vertices(path: Path) -> np.ndarray | None:
    """x, y, z of an ASCII PLY parsed as float64 (as the BOP toolkit does); None if not ASCII PLY.

    trimesh keeps vertices as float32, which moves MSSD by ~1e-8 relative against the toolkit.
    """
    with path.open("rb") as f:
        head = f.read(4096)
    if not head.startswith(b"ply") or b"format ascii" not in head.split(b"end_header")[0]:
        return None
    lines = path.read_text(errors="replace").splitlines()
    n_vert, props, in_vertex, start = 0, [], False, None
    for i, line in enumerate(lines):
        tok = line.split()
        if not tok:
            continue
        if tok[0] == "element":
            in_vertex = tok[1] == "vertex"
            if in_vertex:
                n_vert = int(tok[2])
        elif tok[0] == "property" and in_vertex:
            props.append(tok[-1])
        elif tok[0] == "end_header":
            start = i + 1
            break
    if start is None or not {"x", "y", "z"} <= set(props) or n_vert <= 0:
        return None
    cols = [props.index(c) for c in ("x", "y", "z")]
    try:
        rows = [lines[start + k].split() for k in range(n_vert)]
        return np.array([[float(r[c]) for c in cols] for r in rows], dtype=np.float64)
    except (IndexError, ValueError) as exc:
        raise BopFormatError(f"{path}: malformed ASCII PLY vertex list ({exc})") from exc


def load_model_points(models_dir: str | Path, obj_id: int) -> np.ndarray:
    """Vertices (N, 3) float64 in mm of ``obj_{id:06d}.ply`` (as the BOP toolkit's metrics use them)."""
    import trimesh

    p = model_path(models_dir, obj_id)
    ascii_pts = _ascii_ply_vertices(p)
    if ascii_pts is not None:
        return ascii_pts
    try:
        geom = trimesh.load(p, process=False)
    except Exception as exc:  # trimesh raises many types on bad files
        raise BopFormatError(f"{p}: cannot parse model ({exc})") from exc
    pts = np.asarray(getattr(geom, "vertices", np.zeros((0, 3))), dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
        raise BopFormatError(f"{p}: model has no vertices")
    return pts


class BopDataset:
    """A BOP dataset folder. Files are read lazily and cached; errors name the file."""

    def __init__(self, root: str | Path, split: str = "test") -> None:
        self.root = Path(root)
        if not self.root.is_dir():
            raise FileNotFoundError(f"{self.root}: dataset folder not found")
        self.split = split
        self.split_dir = self.root / split
        if not self.split_dir.is_dir():
            raise FileNotFoundError(f"{self.split_dir}: split folder {split!r} not found in dataset {self.root}")
        self.models_dir = self.root / "models"

    def __repr__(self) -> str:
        return f"BopDataset({str(self.root)!r}, split={self.split!r})"

    # ------------------------------------------------------------------ models
    @functools.cached_property
    def models_info(self) -> dict[int, ModelInfo]:
        return load_models_info(self.models_dir / "models_info.json")

    @property
    def obj_ids(self) -> list[int]:
        return sorted(self.models_info)

    def models_eval_dir(self) -> Path:
        d = self.root / "models_eval"
        return d if d.is_dir() else self.models_dir

    def model_points(self, obj_id: int, eval_models: bool = True) -> np.ndarray:
        return load_model_points(self.models_eval_dir() if eval_models else self.models_dir, obj_id)

    # ------------------------------------------------------------------ scenes
    def scene_ids(self) -> list[int]:
        ids = []
        for p in sorted(self.split_dir.iterdir()):
            if p.is_dir() and p.name.isdigit():
                ids.append(int(p.name))
        return ids

    def scene_dir(self, scene_id: int) -> Path:
        d = self.split_dir / f"{int(scene_id):06d}"
        if not d.is_dir():
            raise FileNotFoundError(f"{d}: scene {scene_id} not found")
        return d

    @functools.lru_cache(maxsize=None)
    def scene_camera(self, scene_id: int) -> dict[int, Camera]:
        return parse_scene_camera(self.scene_dir(scene_id) / "scene_camera.json")

    @functools.lru_cache(maxsize=None)
    def scene_gt(self, scene_id: int) -> dict[int, list[GtPose]]:
        return parse_scene_gt(self.scene_dir(scene_id) / "scene_gt.json")

    @functools.lru_cache(maxsize=None)
    def scene_gt_info(self, scene_id: int) -> dict[int, list[GtInfo]]:
        return parse_scene_gt_info(self.scene_dir(scene_id) / "scene_gt_info.json")

    def im_ids(self, scene_id: int) -> list[int]:
        return sorted(self.scene_camera(scene_id))

    # ----------------------------------------------------------------- targets
    def targets(self, filename: str = "test_targets_bop19.json") -> list[Target]:
        """BOP19 targets; when the file is absent, every GT instance of every image is a target."""
        path = self.root / filename
        if path.is_file():
            return parse_targets(path)
        out = []
        for scene_id in self.scene_ids():
            for im_id, gts in self.scene_gt(scene_id).items():
                counts: dict[int, int] = {}
                for g in gts:
                    counts[g.obj_id] = counts.get(g.obj_id, 0) + 1
                out += [Target(scene_id, im_id, o, n) for o, n in sorted(counts.items())]
        return out

    # ------------------------------------------------------------------ images
    def _find_image(self, folder: Path, stem: str, what: str) -> Path:
        for ext in _IMAGE_EXTS:
            p = folder / f"{stem}{ext}"
            if p.is_file():
                return p
        raise FileNotFoundError(f"{folder / stem}.*: {what} image not found")

    def rgb_path(self, scene_id: int, im_id: int) -> Path:
        d = self.scene_dir(scene_id)
        folder = d / "rgb" if (d / "rgb").is_dir() else d / "gray"
        return self._find_image(folder, f"{int(im_id):06d}", "rgb")

    def depth_path(self, scene_id: int, im_id: int) -> Path:
        return self._find_image(self.scene_dir(scene_id) / "depth", f"{int(im_id):06d}", "depth")

    def has_depth(self) -> bool:
        return any((self.split_dir / f"{s:06d}" / "depth").is_dir() for s in self.scene_ids())

    def mask_visib_path(self, scene_id: int, im_id: int, gt_idx: int) -> Path:
        return self._find_image(
            self.scene_dir(scene_id) / "mask_visib", f"{int(im_id):06d}_{int(gt_idx):06d}", "mask_visib"
        )

    def mask_path(self, scene_id: int, im_id: int, gt_idx: int) -> Path:
        return self._find_image(self.scene_dir(scene_id) / "mask", f"{int(im_id):06d}_{int(gt_idx):06d}", "mask")

    def load_rgb(self, scene_id: int, im_id: int) -> np.ndarray:
        """uint8 H x W x 3 (RGB order; grayscale images are repeated to 3 channels)."""
        p = self.rgb_path(scene_id, im_id)
        im = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        if im is None:
            raise BopFormatError(f"{p}: cannot decode image")
        if im.ndim == 2:
            im = np.repeat(im[..., None], 3, axis=2)
        elif im.shape[2] == 4:
            im = im[..., :3]
        if im.dtype != np.uint8:
            im = (im / 256).astype(np.uint8) if im.dtype == np.uint16 else im.astype(np.uint8)
        return np.ascontiguousarray(im[..., ::-1])

    def load_depth(self, scene_id: int, im_id: int) -> np.ndarray:
        """float32 H x W depth in mm (the camera's depth_scale applied; 0 = no measurement)."""
        p = self.depth_path(scene_id, im_id)
        d = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        if d is None:
            raise BopFormatError(f"{p}: cannot decode depth image")
        scale = self.scene_camera(scene_id)[int(im_id)].depth_scale
        return d.astype(np.float32) * np.float32(scale)

    def load_mask_visib(self, scene_id: int, im_id: int, gt_idx: int) -> np.ndarray:
        p = self.mask_visib_path(scene_id, im_id, gt_idx)
        m = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        if m is None:
            raise BopFormatError(f"{p}: cannot decode mask")
        return m > 0

    def image_size(self, scene_id: int, im_id: int) -> tuple[int, int]:
        """(width, height) of an image (read from the rgb file header via cv2)."""
        im = cv2.imread(str(self.rgb_path(scene_id, im_id)), cv2.IMREAD_UNCHANGED)
        if im is None:
            raise BopFormatError(f"{self.rgb_path(scene_id, im_id)}: cannot decode image")
        return int(im.shape[1]), int(im.shape[0])


def check_scene_files(scene_dir: str | Path) -> None:
    """Raise FileNotFoundError naming the first BOP scene file that is missing."""
    scene_dir = Path(scene_dir)
    for name in ("scene_camera.json", "scene_gt.json", "scene_gt_info.json"):
        if not (scene_dir / name).is_file():
            raise FileNotFoundError(f"{scene_dir / name}: required BOP file missing")
