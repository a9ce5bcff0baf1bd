"""CenterPoint training targets on the BEV grid of `model.layers.head` (numpy, built in the data loader).

For each ground-truth box whose centre falls on the grid: a Gaussian peak on its class heatmap at the
centre cell, and at that cell the regression targets the head predicts (offset in cells from the cell's
lower-left corner, z, log dims, sin/cos yaw). The Gaussian radius is CenterNet's: the largest radius by
which a box corner may move while the box still overlaps the true one with IoU >= `min_overlap`, in cells,
at least `min_radius` (CenterPoint: 0.1 and 2).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from model.config import BEVConfig


@dataclass(frozen=True)
class TargetConfig:
    min_overlap: float = 0.1
    min_radius: int = 2
    max_objects: int = 256  # per prediction; more are dropped (nearest first are kept)


@dataclass(frozen=True)
class BEVTargets:
    """Targets of one prediction (one BEV map)."""

    heatmap: np.ndarray  # (K, ny, nx) float32 in [0, 1]
    index: np.ndarray  # (T,) int64 flat cell index row * nx + col of each target box
    reg: np.ndarray  # (T, 8) float32 offset x, offset y, z, log l, log w, log h, sin yaw, cos yaw
    boxes: np.ndarray  # (T, 7) float32 the target boxes (for the IoU branch and the IoU loss)
    labels: np.ndarray  # (T,) int64


def gaussian_radius(length: float, width: float, min_overlap: float) -> float:
    """CenterNet's radius (in the units of length and width) for a box of that size."""
    h, w = length, width
    b1 = h + w
    c1 = w * h * (1 - min_overlap) / (1 + min_overlap)
    r1 = (b1 + math.sqrt(b1**2 - 4 * c1)) / 2
    b2 = 2 * (h + w)
    c2 = (1 - min_overlap) * w * h
    r2 = (b2 + math.sqrt(b2**2 - 16 * c2)) / 2
    a3 = 4 * min_overlap
    b3 = -2 * min_overlap * (h + w)
    c3 = (min_overlap - 1) * w * h
    r3 = (b3 + math.sqrt(b3**2 - 4 * a3 * c3)) / 2
    return min(r1, r2, r3)


def draw_gaussian(heatmap: np.ndarray, row: int, col: int, radius: int) -> None:
    """Max-blend a Gaussian with sigma (2 radius + 1) / 6 centred on (row, col) into heatmap (ny, nx)."""
    d = np.arange(-radius, radius + 1, dtype=np.float32)  # (2r+1,)
    sigma = (2 * radius + 1) / 6
    g = np.exp(-(d[:, None] ** 2 + d[None, :] ** 2) / (2 * sigma * sigma))  # (2r+1, 2r+1)
    ny, nx = heatmap.shape
    r0, r1 = max(0, row - radius), min(ny, row + radius + 1)
    c0, c1 = max(0, col - radius), min(nx, col + radius + 1)
    patch = g[r0 - row + radius : r1 - row + radius, c0 - col + radius : c1 - col + radius]
    np.maximum(heatmap[r0:r1, c0:c1], patch, out=heatmap[r0:r1, c0:c1])


def build_targets(
    boxes: np.ndarray, labels: np.ndarray, num_classes: int, bev: BEVConfig, cfg: TargetConfig
) -> BEVTargets:
    """boxes (M, 7), labels (M,) of the objects this prediction should find -> BEVTargets."""
    heatmap = np.zeros((num_classes, bev.ny, bev.nx), np.float32)
    fx = (boxes[:, 0] - bev.x_min) / bev.cell  # (M,) centre in cells
    fy = (boxes[:, 1] - bev.y_min) / bev.cell
    col, row = np.floor(fx).astype(np.int64), np.floor(fy).astype(np.int64)
    inside = (col >= 0) & (col < bev.nx) & (row >= 0) & (row < bev.ny) & (boxes[:, 3] > 0) & (boxes[:, 4] > 0)
    order = np.argsort(np.hypot(boxes[:, 0], boxes[:, 1]), kind="stable")
    order = order[inside[order]][: cfg.max_objects]
    seen: set[int] = set()
    keep = []
    for i in order:
        radius = gaussian_radius(boxes[i, 3] / bev.cell, boxes[i, 4] / bev.cell, cfg.min_overlap)
        draw_gaussian(heatmap[labels[i]], int(row[i]), int(col[i]), max(cfg.min_radius, int(radius)))
        cell = int(row[i] * bev.nx + col[i])
        if cell not in seen:  # two centres in one cell: the nearer box gets the regression target
            seen.add(cell)
            keep.append(i)
    k = np.array(keep, np.int64)
    b = boxes[k].astype(np.float32)
    reg = np.stack(
        [
            fx[k] - col[k],
            fy[k] - row[k],
            b[:, 2],
            np.log(b[:, 3]),
            np.log(b[:, 4]),
            np.log(np.maximum(b[:, 5], 1e-3)),
            np.sin(b[:, 6]),
            np.cos(b[:, 6]),
        ],
        axis=1,
    ).astype(np.float32)
    return BEVTargets(heatmap, row[k] * bev.nx + col[k], reg.reshape(-1, 8), b.reshape(-1, 7), labels[k])
