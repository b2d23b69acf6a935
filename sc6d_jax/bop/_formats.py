"""Typed records for the BOP file formats, and their JSON (de)serialisation.

BOP conventions: millimetres, row-major 3x3 R, x_cam = R x_model + t, boxes (x, y, w, h) in pixels.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from sc6d_jax._io import atomic_write_text


@dataclass(frozen=True)
class Camera:
    """One image's camera: intrinsics K (3x3) and the depth scale (depth_mm = png * depth_scale)."""

    K: np.ndarray
    depth_scale: float = 1.0
    R_w2c: np.ndarray | None = None
    t_w2c: np.ndarray | None = None


@dataclass(frozen=True)
class GtPose:
    obj_id: int
    R: np.ndarray  # (3, 3)
    t: np.ndarray  # (3,) mm


@dataclass(frozen=True)
class GtInfo:
    bbox_obj: tuple[int, int, int, int]
    bbox_visib: tuple[int, int, int, int]
    px_count_all: int
    px_count_visib: int
    px_count_valid: int
    visib_fract: float


def bbox_extent(bbox) -> np.ndarray:
    """The continuous extent ``(x, y, w, h)`` of a BOP pixel box, as the estimator takes boxes.

    BOP's ``bbox_visib`` (and the toolkit's ``calc_2d_bbox``) is ``(x_min, y_min, x_max - x_min,
    y_max - y_min)`` over the indices of the mask's pixels: it runs from the first pixel's centre
    to the last one's, about one pixel less than the silhouette it was measured on. The
    silhouette covers ``[x_min - 0.5, x_max + 0.5]`` (pixel centres at integers, the K
    convention), so its extent is ``(x - 0.5, y - 0.5, w + 1, h + 1)``. Crops cut from the
    extent show the object as the training crops do (cut from the projection's exact extent);
    cut from the pixel box, each object looks one pixel larger, and its depth came out about
    1 % too far at 100-pixel boxes. Works on ``(4,)`` or ``(N, 4)``.
    """
    b = np.asarray(bbox, np.float64)
    if b.shape[-1:] != (4,):
        raise ValueError(f"bbox must be (x, y, w, h), got shape {b.shape}")
    return b + np.array([-0.5, -0.5, 1.0, 1.0])



def most_visible_instances(gts: Sequence[GtPose], infos: Sequence[GtInfo], obj_id: int) -> list[int]:
    """Indices into ``scene_gt`` of one image of the instances of ``obj_id`` with a non-empty
    visible box, the most visible (``px_count_visib``) first, ties in file order: the instances
    ``sc6d predict`` cuts its ground-truth boxes from (the first ``inst_count`` of them)."""
    idx = [i for i, (g, gi) in enumerate(zip(gts, infos))
           if g.obj_id == obj_id and gi.bbox_visib[2] > 0 and gi.bbox_visib[3] > 0]
    return sorted(idx, key=lambda i: -infos[i].px_count_visib)

@dataclass(frozen=True)
class Target:
    scene_id: int
    im_id: int
    obj_id: int
    inst_count: int


@dataclass(frozen=True)
class ModelInfo:
    """models_info.json entry. Symmetries are kept as the toolkit reads them."""

    obj_id: int
    diameter: float
    min_xyz: tuple[float, float, float]
    size_xyz: tuple[float, float, float]
    symmetries_discrete: list[np.ndarray] = field(default_factory=list)  # (4, 4) each, t in mm
    symmetries_continuous: list[dict[str, np.ndarray]] = field(default_factory=list)  # axis, offset

    @property
    def is_symmetric(self) -> bool:
        return bool(self.symmetries_discrete or self.symmetries_continuous)

    def as_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {
            "diameter": float(self.diameter),
            "min_x": float(self.min_xyz[0]),
            "min_y": float(self.min_xyz[1]),
            "min_z": float(self.min_xyz[2]),
            "size_x": float(self.size_xyz[0]),
            "size_y": float(self.size_xyz[1]),
            "size_z": float(self.size_xyz[2]),
        }
        if self.symmetries_continuous:
            d["symmetries_continuous"] = [
                {"axis": [float(a) for a in s["axis"]], "offset": [float(o) for o in s["offset"]]}
                for s in self.symmetries_continuous
            ]
        if self.symmetries_discrete:
            d["symmetries_discrete"] = [[float(v) for v in np.asarray(s).reshape(16)] for s in self.symmetries_discrete]
        return d


class BopFormatError(ValueError):
    """A BOP file exists but its content is not what the format says."""


def read_json(path: str | Path) -> Any:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: file not found")
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise BopFormatError(f"{path}: not valid JSON ({exc})") from exc


def _num_array(path: Path, key: str, value: Any, n: int) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise BopFormatError(f"{path}: {key} is not a list of numbers") from exc
    if arr.size != n:
        raise BopFormatError(f"{path}: {key} has {arr.size} numbers, expected {n}")
    if not np.all(np.isfinite(arr)):
        raise BopFormatError(f"{path}: {key} contains NaN or infinity")
    return arr


def _int_keys(path: Path, data: Any) -> dict[int, Any]:
    if not isinstance(data, dict):
        raise BopFormatError(f"{path}: expected a JSON object keyed by id")
    out = {}
    for k, v in data.items():
        try:
            out[int(k)] = v
        except ValueError as exc:
            raise BopFormatError(f"{path}: key {k!r} is not an integer id") from exc
    return dict(sorted(out.items()))


def parse_models_info(path: str | Path) -> dict[int, ModelInfo]:
    path = Path(path)
    data = _int_keys(path, read_json(path))
    infos = {}
    for obj_id, d in data.items():
        try:
            diameter = float(d["diameter"])
            min_xyz = tuple(float(d[k]) for k in ("min_x", "min_y", "min_z"))
            size_xyz = tuple(float(d[k]) for k in ("size_x", "size_y", "size_z"))
        except (KeyError, TypeError, ValueError) as exc:
            raise BopFormatError(f"{path}: object {obj_id}: missing or bad field {exc}") from exc
        if not diameter > 0:
            raise BopFormatError(f"{path}: object {obj_id}: diameter must be positive, got {diameter}")
        disc = [
            _num_array(path, f"object {obj_id} symmetries_discrete", s, 16).reshape(4, 4)
            for s in d.get("symmetries_discrete", [])
        ]
        cont = [
            {
                "axis": _num_array(path, f"object {obj_id} symmetries_continuous axis", s.get("axis"), 3),
                "offset": _num_array(path, f"object {obj_id} symmetries_continuous offset", s.get("offset", [0, 0, 0]), 3),
            }
            for s in d.get("symmetries_continuous", [])
        ]
        infos[obj_id] = ModelInfo(obj_id, diameter, min_xyz, size_xyz, disc, cont)  # type: ignore[arg-type]
    return infos


def parse_scene_camera(path: str | Path) -> dict[int, Camera]:
    path = Path(path)
    data = _int_keys(path, read_json(path))
    cams = {}
    for im_id, d in data.items():
        if "cam_K" not in d:
            raise BopFormatError(f"{path}: image {im_id}: cam_K missing")
        K = _num_array(path, f"image {im_id} cam_K", d["cam_K"], 9).reshape(3, 3)
        R = t = None
        if "cam_R_w2c" in d and "cam_t_w2c" in d:
            R = _num_array(path, f"image {im_id} cam_R_w2c", d["cam_R_w2c"], 9).reshape(3, 3)
            t = _num_array(path, f"image {im_id} cam_t_w2c", d["cam_t_w2c"], 3)
        cams[im_id] = Camera(K=K, depth_scale=float(d.get("depth_scale", 1.0)), R_w2c=R, t_w2c=t)
    return cams


def parse_scene_gt(path: str | Path) -> dict[int, list[GtPose]]:
    path = Path(path)
    data = _int_keys(path, read_json(path))
    out = {}
    for im_id, lst in data.items():
        poses = []
        for i, d in enumerate(lst):
            try:
                obj_id = int(d["obj_id"])
                R = _num_array(path, f"image {im_id} gt {i} cam_R_m2c", d["cam_R_m2c"], 9).reshape(3, 3)
                t = _num_array(path, f"image {im_id} gt {i} cam_t_m2c", d["cam_t_m2c"], 3)
            except (KeyError, TypeError) as exc:
                raise BopFormatError(f"{path}: image {im_id} gt {i}: missing field {exc}") from exc
            poses.append(GtPose(obj_id, R, t))
        out[im_id] = poses
    return out


def parse_scene_gt_info(path: str | Path) -> dict[int, list[GtInfo]]:
    path = Path(path)
    data = _int_keys(path, read_json(path))
    out = {}
    for im_id, lst in data.items():
        infos = []
        for i, d in enumerate(lst):
            try:
                infos.append(
                    GtInfo(
                        bbox_obj=tuple(int(v) for v in d["bbox_obj"]),  # type: ignore[arg-type]
                        bbox_visib=tuple(int(v) for v in d["bbox_visib"]),  # type: ignore[arg-type]
                        px_count_all=int(d.get("px_count_all", 0)),
                        px_count_visib=int(d.get("px_count_visib", 0)),
                        px_count_valid=int(d.get("px_count_valid", 0)),
                        visib_fract=float(d["visib_fract"]),
                    )
                )
            except (KeyError, TypeError, ValueError) as exc:
                raise BopFormatError(f"{path}: image {im_id} gt {i}: missing or bad field {exc}") from exc
        out[im_id] = infos
    return out


def parse_targets(path: str | Path) -> list[Target]:
    path = Path(path)
    data = read_json(path)
    if not isinstance(data, list):
        raise BopFormatError(f"{path}: expected a JSON list of targets")
    try:
        return [Target(int(d["scene_id"]), int(d["im_id"]), int(d["obj_id"]), int(d["inst_count"])) for d in data]
    except (KeyError, TypeError, ValueError) as exc:
        raise BopFormatError(f"{path}: target missing or bad field {exc}") from exc


# ---------------------------------------------------------------------------------- writers


def _lines_json(items: Mapping[int, Any]) -> str:
    """The BOP toolkit's layout: one entry per line, keys sorted numerically."""
    body = ",\n".join(f'  "{k}": {json.dumps(v, sort_keys=True)}' for k, v in sorted(items.items()))
    return "{\n" + body + "\n}\n"


def _flat(a: Any, n: int) -> list[float]:
    arr = np.asarray(a, dtype=np.float64).reshape(-1)
    if arr.size != n:
        raise ValueError(f"expected {n} numbers, got {arr.size}")
    return [float(v) for v in arr]


def write_scene_camera(path: str | Path, cameras: Mapping[int, Camera]) -> Path:
    items = {}
    for im_id, c in cameras.items():
        d: dict[str, Any] = {"cam_K": _flat(c.K, 9), "depth_scale": float(c.depth_scale)}
        if c.R_w2c is not None and c.t_w2c is not None:
            d["cam_R_w2c"] = _flat(c.R_w2c, 9)
            d["cam_t_w2c"] = _flat(c.t_w2c, 3)
        items[int(im_id)] = d
    return atomic_write_text(path, _lines_json(items))


def write_scene_gt(path: str | Path, gts: Mapping[int, list[GtPose]]) -> Path:
    items = {
        int(im_id): [{"cam_R_m2c": _flat(g.R, 9), "cam_t_m2c": _flat(g.t, 3), "obj_id": int(g.obj_id)} for g in lst]
        for im_id, lst in gts.items()
    }
    return atomic_write_text(path, _lines_json(items))


def write_scene_gt_info(path: str | Path, infos: Mapping[int, list[GtInfo]]) -> Path:
    items = {
        int(im_id): [
            {
                "bbox_obj": [int(v) for v in g.bbox_obj],
                "bbox_visib": [int(v) for v in g.bbox_visib],
                "px_count_all": int(g.px_count_all),
                "px_count_valid": int(g.px_count_valid),
                "px_count_visib": int(g.px_count_visib),
                "visib_fract": float(g.visib_fract),
            }
            for g in lst
        ]
        for im_id, lst in infos.items()
    }
    return atomic_write_text(path, _lines_json(items))


def write_models_info(path: str | Path, infos: Mapping[int, ModelInfo]) -> Path:
    return atomic_write_text(path, _lines_json({int(k): v.as_dict() for k, v in infos.items()}))


def write_targets(path: str | Path, targets: list[Target]) -> Path:
    rows = [
        json.dumps({"im_id": t.im_id, "inst_count": t.inst_count, "obj_id": t.obj_id, "scene_id": t.scene_id}, sort_keys=True)
        for t in sorted(targets, key=lambda t: (t.scene_id, t.im_id, t.obj_id))
    ]
    return atomic_write_text(path, "[\n  " + ",\n  ".join(rows) + "\n]\n")
