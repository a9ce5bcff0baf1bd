"""Bird's-eye-view pictures of points and boxes (matplotlib, Agg backend): predictions solid, labels dashed.

Boxes are (K, 7) x, y, z, l, w, h, yaw in the points' frame (x forward, y left): drawn as rotated rectangles
with a line from the centre to the front.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

CLASS_COLOURS = {"vehicle": "tab:red", "car": "tab:red", "pedestrian": "tab:orange", "cyclist": "tab:purple"}
LABEL_COLOUR = "lime"
MAX_POINTS = 60_000


@dataclass(frozen=True)
class BoxSet:
    boxes: np.ndarray  # (K, 7) x, y, z, l, w, h, yaw
    names: tuple[str, ...]  # (K,)
    scores: np.ndarray | None = None  # (K,) or None (labels)


def box_corners(boxes: np.ndarray) -> np.ndarray:
    """(K, 7) boxes -> (K, 4, 2) BEV corners, counter-clockwise from front-left."""
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    half = np.stack([b[:, 3] / 2, b[:, 4] / 2], axis=1)  # (K, 2)
    signs = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]], dtype=np.float64)  # (4, 2)
    local = signs[None] * half[:, None]  # (K, 4, 2)
    c, s = np.cos(b[:, 6])[:, None], np.sin(b[:, 6])[:, None]
    x = local[..., 0] * c - local[..., 1] * s + b[:, None, 0]
    y = local[..., 0] * s + local[..., 1] * c + b[:, None, 1]
    return np.stack([x, y], axis=-1)


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _draw_boxes(ax, boxes: BoxSet, dashed: bool) -> None:
    for corners, box, i in zip(box_corners(boxes.boxes), boxes.boxes, range(len(boxes.names)), strict=True):
        name = boxes.names[i]
        colour = LABEL_COLOUR if dashed else CLASS_COLOURS.get(name.lower(), "tab:blue")
        ring = np.vstack([corners, corners[:1]])
        ax.plot(ring[:, 0], ring[:, 1], color=colour, linewidth=1.1, linestyle="--" if dashed else "-")
        front = corners[[0, 3]].mean(axis=0)
        ax.plot([box[0], front[0]], [box[1], front[1]], color=colour, linewidth=0.9)
        if boxes.scores is not None:
            ax.text(box[0], box[1], f"{boxes.scores[i]:.2f}", color=colour, fontsize=5)


def bev_axes(points: np.ndarray, extent_m: float):
    """-> (pyplot, figure, axes): a black BEV of points (N, >=3) coloured by height, the sensor at 0."""
    plt = _pyplot()
    pts = np.asarray(points)[:: max(1, len(points) // MAX_POINTS)]
    fig, ax = plt.subplots(figsize=(8, 8))
    ax.set_facecolor("black")
    ax.scatter(pts[:, 0], pts[:, 1], c=np.clip(pts[:, 2], -2.5, 2.0), s=0.3, cmap="viridis", linewidths=0)
    ax.plot([0], [0], marker="^", color="white", markersize=6)
    ax.set_xlim(-extent_m, extent_m)
    ax.set_ylim(-extent_m, extent_m)
    ax.set_aspect("equal")
    ax.set_xlabel("x forward (m)")
    ax.set_ylabel("y left (m)")
    return plt, fig, ax


def save_figure(plt, fig, path: Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def draw_bev(
    path: Path,
    points: np.ndarray,
    predictions: BoxSet | None = None,
    labels: BoxSet | None = None,
    title: str = "",
    extent_m: float = 50.0,
) -> Path:
    """Write a BEV PNG: points (N, >=3; x, y, z first) coloured by height, predicted and label boxes."""
    plt, fig, ax = bev_axes(points, extent_m)
    if labels is not None:
        _draw_boxes(ax, labels, dashed=True)
    if predictions is not None:
        _draw_boxes(ax, predictions, dashed=False)
    n_pred = 0 if predictions is None else len(predictions.names)
    n_lab = 0 if labels is None else len(labels.names)
    ax.set_title(f"{title}  predictions {n_pred} (solid)  labels {n_lab} (dashed)", fontsize=9)
    return save_figure(plt, fig, path)
