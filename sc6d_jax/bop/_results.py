"""BOP results CSV: ``scene_id,im_id,obj_id,score,R,t,time`` (R row-major, t in mm)."""

from __future__ import annotations

import csv
import io
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

import numpy as np

from sc6d_jax._io import atomic_write_text
from sc6d_jax.bop._formats import BopFormatError

HEADER = ["scene_id", "im_id", "obj_id", "score", "R", "t", "time"]
_NAME_RE = re.compile(r"^[^_]+_[A-Za-z0-9]+-[A-Za-z0-9]+\.csv$")


@dataclass(frozen=True)
class PoseEstimate:
    scene_id: int
    im_id: int
    obj_id: int
    score: float
    R: np.ndarray  # (3, 3)
    t: np.ndarray  # (3,) mm
    time: float = -1.0  # seconds per image; -1 = unknown (BOP's convention)


def results_name_ok(path: str | Path) -> bool:
    """Whether a file name follows BOP's ``METHOD_DATASET-SPLIT.csv`` (METHOD without '_')."""
    return bool(_NAME_RE.match(Path(path).name))


def _fmt(values: Iterable[float]) -> str:
    return " ".join(repr(float(v)) for v in values)


def write_results_csv(path: str | Path, estimates: Iterable[PoseEstimate]) -> Path:
    """Write estimates atomically; the time of every estimate of one image is made equal (max)."""
    ests = list(estimates)
    times: dict[tuple[int, int], float] = {}
    for e in ests:
        R = np.asarray(e.R, dtype=np.float64)
        t = np.asarray(e.t, dtype=np.float64)
        if R.shape != (3, 3) or t.shape != (3,):
            raise ValueError(f"estimate {e.scene_id}/{e.im_id}/{e.obj_id}: R must be 3x3 and t 3-vector")
        if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t)) and math.isfinite(e.score)):
            raise ValueError(f"estimate {e.scene_id}/{e.im_id}/{e.obj_id}: NaN or infinite value")
        key = (e.scene_id, e.im_id)
        times[key] = max(times.get(key, -1.0), float(e.time))
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(HEADER)
    for e in ests:
        w.writerow(
            [
                int(e.scene_id),
                int(e.im_id),
                int(e.obj_id),
                repr(float(e.score)),
                _fmt(np.asarray(e.R, dtype=np.float64).reshape(9)),
                _fmt(np.asarray(e.t, dtype=np.float64).reshape(3)),
                repr(times[(e.scene_id, e.im_id)]),
            ]
        )
    return atomic_write_text(path, buf.getvalue())


def read_results_csv(path: str | Path) -> list[PoseEstimate]:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: results file not found")
    out = []
    with path.open(newline="") as f:
        reader = csv.reader(f)
        header = next(reader, None)
        if header is None or [h.strip() for h in header] != HEADER:
            raise BopFormatError(f"{path}: header must be {','.join(HEADER)}, got {header}")
        for lineno, row in enumerate(reader, start=2):
            if not row:
                continue
            if len(row) != 7:
                raise BopFormatError(f"{path}:{lineno}: expected 7 fields, got {len(row)}")
            try:
                R = np.array([float(v) for v in row[4].split()], dtype=np.float64)
                t = np.array([float(v) for v in row[5].split()], dtype=np.float64)
                e = PoseEstimate(int(row[0]), int(row[1]), int(row[2]), float(row[3]), R.reshape(3, 3), t.reshape(3), float(row[6]))
            except ValueError as exc:
                raise BopFormatError(f"{path}:{lineno}: bad value ({exc})") from exc
            out.append(e)
    return out
