"""The authors' colour augmentation, numpy + cv2, seeded (backgrounds: :mod:`sc6d_jax.backgrounds`)."""

from __future__ import annotations

import cv2
import numpy as np

from sc6d_jax.backgrounds import random_background

__all__ = ["colour_augment", "random_background"]


def colour_augment(rng: np.random.Generator, img: np.ndarray, p: float = 0.8) -> np.ndarray:
    """Noise, dropout, blur, add, invert, multiply, contrast (each with its own chance), applied
    with overall probability ``p`` (the authors' list)."""
    if rng.random() >= p:
        return img
    x = img.astype(np.float32)
    if rng.random() < 0.3:  # blur
        k = int(rng.choice([3, 5]))
        x = cv2.GaussianBlur(x, (k, k), 0)
    # per-channel scalars through cv2: numpy's broadcast over a last axis of 3 is ~4x slower
    if rng.random() < 0.5:  # multiply per channel
        x = cv2.multiply(x, (*rng.uniform(0.7, 1.3, 3).tolist(), 0.0))
    if rng.random() < 0.5:  # add per channel
        x = cv2.add(x, (*rng.uniform(-25, 25, 3).tolist(), 0.0))
    if rng.random() < 0.4:  # contrast
        m = x.mean()
        x = (x - m) * rng.uniform(0.6, 1.4) + m
    if rng.random() < 0.3:  # gaussian noise
        # cv2.randn seeded from rng (deterministic; 3.5x faster than rng.standard_normal)
        sigma = float(rng.uniform(2, 12))
        noise = np.empty_like(x)
        cv2.setRNGSeed(int(rng.integers(2**31 - 1)))
        cv2.randn(noise, (0.0,) * x.shape[-1], (sigma,) * x.shape[-1])
        x += noise
    if rng.random() < 0.2:  # coarse dropout of pixels
        x[rng.random(x.shape[:2]) < rng.uniform(0.01, 0.05)] = 0
    if rng.random() < 0.05:  # invert
        x = 255.0 - x
    return np.clip(x, 0, 255).astype(np.uint8)
