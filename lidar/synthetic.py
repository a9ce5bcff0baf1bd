"""A deterministic synthetic LiDAR turn for benchmarks, warm-up and load tests when no recorded scan is given
(numpy only).

A 64-beam sensor 1.73 m above flat ground, ringed by walls at a random distance per azimuth block. This is
not the training simulator (that one has objects, occlusion and noise); it only gives realistic occupancy.
"""

from __future__ import annotations

import math

import numpy as np


def synthetic_turn(
    seed: int = 0, beams: int = 64, firings: int = 2000, height: float = 1.73, max_range: float = 80.0
) -> np.ndarray:
    """-> (N, 4) float32 points x, y, z, intensity of one turn, in firing (azimuth) order."""
    rng = np.random.default_rng(seed)
    elev = np.deg2rad(np.linspace(-24.9, 2.0, beams))  # (E,)
    azim = np.linspace(-math.pi, math.pi, firings + 1)[:-1]  # (A,)
    blocks = 64
    wall = 8.0 + 60.0 * rng.random(blocks)  # (blocks,)
    wall_at = wall[
        np.minimum(((azim + math.pi) / (2 * math.pi) * blocks).astype(np.int64), blocks - 1)
    ]  # (A,)
    e, a = np.meshgrid(elev, azim)  # (A, E) each
    ground = np.where(e < 0, height / np.maximum(np.tan(-e), 1e-6), np.inf)  # horizontal range
    rng_m = np.minimum(ground / np.cos(e), wall_at[:, None] / np.cos(e))  # (A, E) slant range
    rng_m = rng_m + 0.02 * rng.standard_normal(rng_m.shape)
    keep = rng_m < max_range
    x = rng_m * np.cos(e) * np.cos(a)
    y = rng_m * np.cos(e) * np.sin(a)
    z = rng_m * np.sin(e)
    intensity = rng.random(rng_m.shape)
    return np.stack([x, y, z, intensity], -1)[keep].astype(np.float32)  # (N, 4)
