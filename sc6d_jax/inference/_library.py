"""The rotation library: SO(3) grid rotations and their embeddings by a trained SO(3) encoder.

Built once per trained model (all its objects at once) from :func:`sc6d_jax.geometry.so3_grid`
and cached in the run directory as ``RUN_DIR/library/so3lib_<key>.npz`` (written atomically).
The key hashes the SO(3)-encoder parameters (the only ones the embeddings depend on), the
encoder's shape and the grid ``(n_views, n_inplane, seed)``, so a retrained or resumed model
gets a fresh library and a stale file is never used. The grid rotations themselves are not
stored: they are recomputed deterministically by ``so3_grid``.
"""

from __future__ import annotations

import hashlib
import io
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from sc6d_jax._io import atomic_write_bytes
from sc6d_jax.geometry import so3_grid

#: Library sizes of the paper's SO(3) table and the grids that give them (views x in-plane).
LIBRARY_GRIDS: dict[int, tuple[int, int]] = {
    20_000: (1000, 20),
    60_000: (1000, 60),
    180_000: (1500, 120),
    480_000: (4000, 120),
    1_440_000: (12000, 120),
}
DEFAULT_LIBRARY_SIZE = 480_000
LIBRARY_FORMAT = "sc6d-jax-library/1"


def library_grid(size: int | tuple[int, int]) -> tuple[int, int]:
    """``(n_views, n_inplane)`` for a library size (a key of :data:`LIBRARY_GRIDS`, any multiple of
    120 as ``(size / 120, 120)``, or an explicit pair)."""
    if isinstance(size, tuple):
        if len(size) != 2 or any(not isinstance(v, (int, np.integer)) or v < 1 for v in size):
            raise ValueError(f"library grid must be (n_views, n_inplane) positive ints, got {size!r}")
        return int(size[0]), int(size[1])
    if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or size < 1:
        raise ValueError(f"library size must be a positive int, got {size!r}")
    size = int(size)
    if size in LIBRARY_GRIDS:
        return LIBRARY_GRIDS[size]
    if size % 120 == 0:
        return size // 120, 120
    raise ValueError(
        f"library size {size} is not one of {sorted(LIBRARY_GRIDS)} nor a multiple of 120 "
        "(n_views x 120 in-plane angles)"
    )


@dataclass(frozen=True)
class RotationLibrary:
    """Rotations ``R (N, 3, 3)`` float32 and embeddings ``emb (O, N, E)`` float32 (unit rows); for
    an Implicit-PDF model, ``emb`` holds the rotations' encodings ``(1, N, D)`` instead."""

    R: np.ndarray
    emb: np.ndarray
    grid: tuple[int, int, int]  # (n_views, n_inplane, seed)
    key: str

    @property
    def size(self) -> int:
        return int(self.R.shape[0])


def _so3_head(params: dict) -> dict:
    return params.get("rot_head", params)


def library_key(params: dict, mcfg: Any, grid: tuple[int, int, int]) -> str:
    """SHA-256 (hex, 24 chars) of the SO(3)-encoder params, its shape and the grid."""
    h = hashlib.sha256()
    h.update(LIBRARY_FORMAT.encode())
    h.update(repr((mcfg.n_objects, mcfg.emb_dim, mcfg.so3_hidden, mcfg.rot_head, tuple(grid))).encode())
    leaves, _ = jax.tree_util.tree_flatten_with_path(_so3_head(params))
    for path, leaf in leaves:
        a = np.ascontiguousarray(np.asarray(leaf))
        h.update(jax.tree_util.keystr(path).encode())
        h.update(str(a.dtype).encode() + str(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()[:24]


def embed_library(params: dict, mcfg: Any, R: np.ndarray, chunk: int = 32768, progress: bool = True) -> np.ndarray:
    """Embeddings ``(O, N, E)`` float32 of rotations ``R (N,3,3)`` for every object of the model."""
    from sc6d_jax.model import encode_rotations

    if mcfg.rot_head != "so3":
        raise ValueError("a rotation library needs a model with rot_head='so3'")
    head = jax.tree.map(jnp.asarray, _so3_head(params))
    n = R.shape[0]
    chunk = int(min(chunk, n))
    n_obj = mcfg.n_objects

    @jax.jit
    def enc(head, Rc):
        return jnp.stack([encode_rotations(head, mcfg, Rc, o) for o in range(n_obj)])

    out = np.empty((n_obj, n, mcfg.emb_dim), np.float32)
    starts = range(0, n, chunk)
    if progress:
        from tqdm import tqdm

        starts = tqdm(starts, desc="rotation library", unit="chunk", leave=False)
    for s in starts:
        Rc = R[s : s + chunk]
        m = Rc.shape[0]
        if m < chunk:  # same shape every call: one compilation
            Rc = np.concatenate([Rc, np.broadcast_to(np.eye(3, dtype=np.float32), (chunk - m, 3, 3))])
        out[:, s : s + m] = np.asarray(enc(head, jnp.asarray(Rc)))[:, :m]
    return out


def ipdf_library_features(mcfg: Any, R: np.ndarray) -> np.ndarray:
    """The "library" of an Implicit-PDF head (``rot_head="ipdf"``): the rotations' encodings
    ``(1, N, D)`` (shared by all objects; the head scores each one with the crop at inference,
    :func:`sc6d_jax.inference.ipdf_match_blocks`). Cheap to compute, so never cached; traceable
    (the validator computes them under jit)."""
    from sc6d_jax.model import rotation_features

    return rotation_features(jnp.asarray(R, jnp.float32), mcfg.ipdf_pe_freqs)[None]


def load_or_build_library(
    params: dict,
    mcfg: Any,
    size: int | tuple[int, int] = DEFAULT_LIBRARY_SIZE,
    cache_dir: str | os.PathLike | None = None,
    seed: int = 0,
    progress: bool = True,
) -> RotationLibrary:
    """The rotation library of a model, read from ``cache_dir`` when a file with the same key
    exists (and is intact), otherwise built and written there atomically (``cache_dir=None``:
    no cache). An Implicit-PDF model's library is its rotations' encodings (nothing cached)."""
    n_views, n_inplane = library_grid(size)
    grid = (n_views, n_inplane, int(seed))
    R = so3_grid(n_views, n_inplane, seed=seed)
    if mcfg.rot_head == "ipdf":
        return RotationLibrary(R=R, emb=np.asarray(ipdf_library_features(mcfg, R), np.float32), grid=grid, key="ipdf")
    key = library_key(params, mcfg, grid)
    path = None if cache_dir is None else Path(cache_dir) / f"so3lib_{key}.npz"
    if path is not None and path.is_file():
        try:
            with np.load(path, allow_pickle=False) as z:
                emb, fmt, k = z["emb"], str(z["format"]), str(z["key"])
            if fmt == LIBRARY_FORMAT and k == key and emb.shape == (mcfg.n_objects, R.shape[0], mcfg.emb_dim):
                return RotationLibrary(R=R, emb=emb.astype(np.float32), grid=grid, key=key)
        except (OSError, ValueError, KeyError):
            pass  # unreadable cache: rebuild and overwrite
    emb = embed_library(params, mcfg, R, progress=progress)
    if path is not None:
        buf = io.BytesIO()
        np.savez(buf, emb=emb, format=np.asarray(LIBRARY_FORMAT), key=np.asarray(key), grid=np.asarray(grid))
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(path, buf.getvalue())
    return RotationLibrary(R=R, emb=emb, grid=grid, key=key)


def pack_library(emb: np.ndarray, block: int) -> tuple[jax.Array, int]:
    """Per-object embeddings ``(O, N, E)`` -> transposed blocks ``(O, nb, E, block)`` (zero-padded
    rows) and N: each query is matched against its own object's library only
    (:func:`sc6d_jax.inference.match_blocks` with ``obj_idx``)."""
    from sc6d_jax.inference._matching import pad_library

    if np.ndim(emb) != 3:
        raise ValueError(f"library embeddings must be (O, N, E), got shape {np.shape(emb)}")
    return pad_library(emb, block)
