"""Atomic file output: write to a temporary name beside the target, then rename.

Nothing half-written is ever left under the final name, whatever happens mid-write.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any, Iterator


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    return path


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    return atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_json(path: str | os.PathLike, obj: Any, indent: int | None = 2) -> Path:
    return atomic_write_text(path, json.dumps(obj, indent=indent, sort_keys=False) + "\n")


def png_bytes(img: Any, rgb: bool = True) -> bytes:
    """PNG bytes of an image: (H,W,3) uint8 in RGB order (BGR with ``rgb=False``), or (H,W) uint8
    or uint16. Raises ValueError naming the shape and dtype when it cannot be encoded."""
    import cv2
    import numpy as np

    a = np.asarray(img)
    if a.ndim == 3 and a.shape[-1] == 3 and rgb:
        a = a[..., ::-1]
    good = a.size > 0 and a.dtype in (np.uint8, np.uint16) and (a.ndim == 2 or (a.ndim == 3 and a.shape[-1] == 3))
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(a)) if good else (False, None)
    if not ok:
        raise ValueError(f"cannot encode an image of shape {a.shape} and dtype {a.dtype} as PNG")
    return buf.tobytes()


def atomic_write_png(path: str | os.PathLike, img: Any, rgb: bool = True) -> Path:
    """Write ``img`` (see :func:`png_bytes`) as a PNG file, atomically."""
    return atomic_write_bytes(path, png_bytes(img, rgb))


@contextlib.contextmanager
def atomic_directory(path: str | os.PathLike, overwrite: bool = False) -> Iterator[Path]:
    """Yield a temporary directory that is renamed to ``path`` when the block succeeds.

    On any exception the temporary directory is removed and ``path`` is untouched.
    With ``overwrite`` an existing ``path`` is replaced only after the new one is complete.
    """
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} already exists (pass overwrite to replace it)")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent))
    try:
        yield tmp
        if path.exists():
            old = path.with_name(f".{path.name}.old")
            shutil.rmtree(old, ignore_errors=True)
            os.replace(path, old)
            os.replace(tmp, path)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
