"""Split a full LiDAR turn into the model's azimuth sectors (aligned with the polar grid's theta bins).

Sector k of K covers azimuth [-pi + k * 2pi/K, -pi + (k+1) * 2pi/K). This is the simple split used by the
model's benchmarks and tests; the clients' sectorizer handles firing order, spin direction and packets.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor


def sector_of_points(x: Tensor, y: Tensor, sectors: int) -> Tensor:
    """(N,) x, y -> (N,) int64 sector index in [0, sectors)."""
    theta = torch.atan2(y, x)  # [-pi, pi]
    k = torch.floor((theta + math.pi) / (2 * math.pi / sectors)).long()
    return k.clamp_(0, sectors - 1)


def split_turn(points: Tensor, sectors: int) -> list[Tensor]:
    """(N, C) points of one turn -> list of `sectors` tensors (N_k, C), in azimuth order."""
    k = sector_of_points(points[:, 0].contiguous(), points[:, 1].contiguous(), sectors)
    order = torch.argsort(k, stable=True)
    counts = torch.bincount(k, minlength=sectors).tolist()
    return list(points.index_select(0, order).split(counts))


def load_kitti_bin(path: str) -> Tensor:
    """A KITTI velodyne .bin file -> (N, 4) float32 x, y, z, reflectance."""
    return torch.from_numpy(np.fromfile(path, dtype=np.float32).reshape(-1, 4).copy())
