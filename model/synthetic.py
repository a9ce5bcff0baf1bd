"""A deterministic synthetic LiDAR turn for benchmarks and FLOP counts when no recorded scan is given.

A 64-beam sensor 1.73 m above flat ground, ringed by walls at a random distance per azimuth block. This is
not the training simulator (that one has objects, occlusion and noise); it only gives realistic occupancy.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor


def synthetic_turn(
    seed: int = 0, beams: int = 64, firings: int = 2000, height: float = 1.73, max_range: float = 80.0
) -> Tensor:
    """-> (N, 4) float32 points x, y, z, intensity of one turn, in firing (azimuth) order."""
    g = torch.Generator().manual_seed(seed)
    elev = torch.deg2rad(torch.linspace(-24.9, 2.0, beams, dtype=torch.float64))  # (E,)
    azim = torch.linspace(-math.pi, math.pi, firings + 1, dtype=torch.float64)[:-1]  # (A,)
    blocks = 64
    wall = 8.0 + 60.0 * torch.rand(blocks, generator=g, dtype=torch.float64)  # (blocks,)
    wall_at = wall[((azim + math.pi) / (2 * math.pi) * blocks).long().clamp(max=blocks - 1)]  # (A,)
    e, a = torch.meshgrid(elev, azim, indexing="xy")  # (A, E)
    ground = torch.where(e < 0, height / torch.tan(-e).clamp(min=1e-6), torch.full_like(e, math.inf))
    wall_range = wall_at[:, None] / torch.cos(e)  # (A, E)
    rng = torch.minimum(ground / torch.cos(e), wall_range)  # slant range
    rng = rng + 0.02 * torch.randn(rng.shape, generator=g, dtype=torch.float64)
    keep = rng < max_range
    x = rng * torch.cos(e) * torch.cos(a)
    y = rng * torch.cos(e) * torch.sin(a)
    z = rng * torch.sin(e)
    inten = torch.rand(rng.shape, generator=g, dtype=torch.float64)
    pts = torch.stack([x, y, z, inten], -1)[keep]  # (N, 4)
    return pts.float()
