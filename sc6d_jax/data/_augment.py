"""The authors' colour augmentation, numpy + cv2, seeded (backgrounds: :mod:`sc6d_jax.backgrounds`)."""

from __future__ import annotations

import cv2
import numpy as np

from sc6d_jax.backgrounds import random_background

__all__ = ["camera_effects", "colour_augment", "random_background"]


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


def camera_effects(
    rng: np.random.Generator, img: np.ndarray, side: float, resample: bool = True, sensor: bool = True
) -> np.ndarray:
    """What a real camera does to a crop that a render at crop resolution lacks.

    ``img`` is an (S, S, 3) uint8 crop rendered directly at S x S whose box is ``side`` pixels wide
    in its image. A real crop is cut from a camera image, so when ``side < S`` it holds only
    ``side`` x ``side`` pixels of detail, up-sampled.

    - ``resample``: the crop is reduced to ``side`` x ``side`` (area) and enlarged back (linear),
      as the estimator's warp enlarges a real crop; nothing happens when ``side >= S``.
    - ``sensor``: each with its own chance, sized in image pixels: motion blur (3-7 image px along
      a random direction, p 0.3), a gamma curve (0.7-1.5, p 0.5), Gaussian sensor noise (sigma
      2-10 grey levels per image pixel, p 0.5), JPEG compression (quality 30-95, p 0.5). When
      the crop shows its box smaller than the image did (``side > S``), blur and noise shrink
      with it (a crop pixel averages ``side / S`` image pixels across).
    """
    S = img.shape[0]
    r = int(round(min(float(S), max(float(side), 8.0)))) if resample else S
    x = img if r >= S else cv2.resize(img, (r, r), interpolation=cv2.INTER_AREA)
    f = min(1.0, r / max(float(side), 1e-6))  # working pixels per image pixel
    if sensor:
        if rng.random() < 0.3:  # motion blur: a normalised line kernel
            n = max(1, int(round(int(rng.integers(3, 8)) * f)))
            k = np.zeros((n, n), np.float32)
            a = rng.uniform(0, np.pi)
            c, d = (n - 1) / 2 * np.cos(a), (n - 1) / 2 * np.sin(a)
            m = (n - 1) / 2
            cv2.line(k, (int(round(m - c)), int(round(m - d))), (int(round(m + c)), int(round(m + d))), 1.0, 1)
            x = cv2.filter2D(x, -1, k / k.sum())
        if rng.random() < 0.5:  # gamma
            g = rng.uniform(0.7, 1.5)
            lut = np.clip(255.0 * (np.arange(256) / 255.0) ** g + 0.5, 0, 255).astype(np.uint8)
            x = cv2.LUT(x, lut)
        if rng.random() < 0.5:  # sensor noise
            noise = np.empty(x.shape, np.float32)
            cv2.setRNGSeed(int(rng.integers(2**31 - 1)))
            sigma = float(rng.uniform(2, 10)) * f
            cv2.randn(noise, (0.0,) * x.shape[-1], (sigma,) * x.shape[-1])
            x = np.clip(x.astype(np.float32) + noise, 0, 255).astype(np.uint8)
        if rng.random() < 0.5:  # JPEG
            q = int(rng.integers(30, 96))
            ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(x), [cv2.IMWRITE_JPEG_QUALITY, q])
            if ok:
                x = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED).reshape(x.shape)
    if r < S:
        x = cv2.resize(x, (S, S), interpolation=cv2.INTER_LINEAR)
    return np.ascontiguousarray(x, np.uint8)
