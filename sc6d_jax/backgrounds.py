"""Procedural textured backgrounds (numpy + cv2, seeded): one home for the training crop stream
(:mod:`sc6d_jax.data`) and the rendered test datasets (:mod:`sc6d_jax.render`)."""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["random_background"]


def random_background(rng: np.random.Generator, size: int) -> np.ndarray:
    """A textured S x S uint8 background: gradient + shapes + stripes or checks + noise."""
    c0, c1 = rng.integers(0, 256, 3), rng.integers(0, 256, 3)
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32) / max(size - 1, 1)
    a = rng.uniform(0, 2 * np.pi)
    g = np.clip(0.5 + (np.cos(a) * (xx - 0.5) + np.sin(a) * (yy - 0.5)), 0, 1)[..., None]
    img = (c0 * (1 - g) + c1 * g).astype(np.float32)
    kind = rng.integers(3)
    if kind == 0:  # stripes
        f = rng.uniform(2, 12)
        b = rng.uniform(0, 2 * np.pi)
        s = (np.sin(2 * np.pi * f * (np.cos(b) * xx + np.sin(b) * yy)) > 0)[..., None]
        img = np.where(s, img, img * rng.uniform(0.4, 0.9) + rng.uniform(-40, 40, 3))
    elif kind == 1:  # checks
        n = rng.integers(2, 10)
        s = (((xx * n).astype(int) + (yy * n).astype(int)) % 2 == 0)[..., None]
        img = np.where(s, img, rng.integers(0, 256, 3).astype(np.float32))
    for _ in range(rng.integers(2, 7)):  # shapes
        col = tuple(int(c) for c in rng.integers(0, 256, 3))
        p = tuple(int(v) for v in rng.integers(0, size, 2))
        r = int(rng.integers(max(size // 16, 1), max(size // 3, 2)))
        if rng.random() < 0.5:
            cv2.circle(img, p, r, col, -1)
        else:
            q = tuple(int(v) for v in rng.integers(0, size, 2))
            cv2.rectangle(img, p, q, col, -1)
    img += rng.normal(0, rng.uniform(0, 12), img.shape).astype(np.float32)
    return np.clip(img, 0, 255).astype(np.uint8)
