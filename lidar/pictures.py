"""Bird's-eye-view pictures of points and boxes (matplotlib, Agg backend): predictions solid, labels dashed.

Boxes are (K, 7) x, y, z, l, w, h, yaw in the points' frame (x forward, y left): drawn as rotated rectangles
with a line from the centre to the front. `phim replay --frames` and `phim eval --pictures` both draw here:
the boxes given (what a reply returned, or what a server at the given min_score would return), each
prediction labelled with its class initial and score in a font readable at 100 % zoom, and a legend of the
classes' colours, the labels' style and the score threshold.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

CLASS_COLOURS = {"vehicle": "tab:red", "car": "tab:red", "pedestrian": "tab:orange", "cyclist": "tab:purple"}
OTHER_COLOUR = "tab:blue"  # a class not listed above
LABEL_COLOUR = "lime"
MAX_POINTS = 60_000
FONT_SIZE = 9  # points: about 12 pixels at the pictures' 100 dpi
TEXT_BOX = {"boxstyle": "round,pad=0.15", "facecolor": "black", "edgecolor": "none", "alpha": 0.6}


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


def class_colour(name: str) -> str:
    return CLASS_COLOURS.get(name.lower(), OTHER_COLOUR)


def _draw_boxes(ax, boxes: BoxSet, dashed: bool, extent_m: float) -> None:
    for corners, box, i in zip(box_corners(boxes.boxes), boxes.boxes, range(len(boxes.names)), strict=True):
        colour = LABEL_COLOUR if dashed else class_colour(boxes.names[i])
        ring = np.vstack([corners, corners[:1]])
        ax.plot(ring[:, 0], ring[:, 1], color=colour, linewidth=1.4, linestyle="--" if dashed else "-")
        front = corners[[0, 3]].mean(axis=0)
        ax.plot([box[0], front[0]], [box[1], front[1]], color=colour, linewidth=1.1)
    if boxes.scores is not None:
        _label_boxes(ax, boxes, extent_m)


def _label_boxes(ax, boxes: BoxSet, extent_m: float) -> None:
    """Each box's class initial and score beside it (above, below, right, left, or a line further above or
    below: the first place no label of a higher-scored box took; none free: above), best scores first."""
    m_per_pt = 2 * extent_m / (7.0 * 72)  # the axes are about 7 of the figure's 8 inches
    high, wide = 1.6 * FONT_SIZE * m_per_pt, 0.75 * FONT_SIZE * m_per_pt  # a line, a character (metres)
    taken: list[tuple[float, float, float, float]] = []  # placed labels: x0, y0, x1, y1
    corners = box_corners(boxes.boxes)  # (K, 4, 2)
    for i in np.argsort(-np.asarray(boxes.scores), kind="stable"):
        lo, hi = corners[i].min(axis=0), corners[i].max(axis=0)
        text = f"{boxes.names[i][:1].upper()} {boxes.scores[i]:.2f}"
        w, cx, cy = wide * len(text), (lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2
        places = [(cx - w / 2, hi[1] + 0.3), (cx - w / 2, lo[1] - 0.3 - high), (hi[0] + 0.3, cy - high / 2)]
        places += [
            (lo[0] - 0.3 - w, cy - high / 2),
            (cx - w / 2, hi[1] + high),
            (cx - w / 2, lo[1] - 2 * high),
        ]
        free = [(x, y) for x, y in places if not any(_overlap((x, y, x + w, y + high), t) for t in taken)]
        x, y = free[0] if free else places[0]
        if max(abs(cx), abs(cy)) >= extent_m:
            continue
        taken.append((x, y, x + w, y + high))
        colour = class_colour(boxes.names[i])
        ax.text(x, y, text, color=colour, fontsize=FONT_SIZE, bbox=TEXT_BOX, clip_on=True, va="bottom")


def _overlap(a: tuple[float, ...], b: tuple[float, ...]) -> bool:
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


def _legend(ax, names: list[str], labels: bool, min_score: float | None) -> None:
    """Classes and their colours, the labels' dashes, what the numbers are."""
    from matplotlib.lines import Line2D

    handles = [
        Line2D([], [], color=class_colour(n), linewidth=2, label=f"{n[:1].upper()}  {n.lower()}")
        for n in names
    ]
    if labels:
        handles.append(Line2D([], [], color=LABEL_COLOUR, linestyle="--", linewidth=1.5, label="label"))
    cut = "" if min_score is None else f" >= {min_score:g}"
    title = f"predictions: class initial, score{cut}"
    legend = ax.legend(
        handles=handles, loc="upper left", fontsize=FONT_SIZE, title=title, title_fontsize=FONT_SIZE
    )
    legend.get_frame().set_facecolor("black")
    legend.get_frame().set_alpha(0.7)
    for t in (*legend.get_texts(), legend.get_title()):
        t.set_color("white")


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
    min_score: float | None = None,
    classes: tuple[str, ...] = ("VEHICLE", "PEDESTRIAN", "CYCLIST"),
) -> Path:
    """Write a BEV PNG: points (N, >=3; x, y, z first) coloured by height, predicted and label boxes, and a
    legend of `classes` (and any other predicted class) and of `min_score`, the threshold the predictions
    passed (None: not said)."""
    plt, fig, ax = bev_axes(points, extent_m)
    if labels is not None:
        _draw_boxes(ax, labels, dashed=True, extent_m=extent_m)
    if predictions is not None:
        _draw_boxes(ax, predictions, dashed=False, extent_m=extent_m)
    shown = list(classes) + sorted(
        {n for n in (predictions.names if predictions else ()) if n not in classes}
    )
    _legend(ax, shown, labels is not None, min_score)
    n_pred = 0 if predictions is None else len(predictions.names)
    n_lab = 0 if labels is None else len(labels.names)
    counts = f"predictions {n_pred} (solid)  labels {n_lab} (dashed)"
    ax.set_title(f"{title}{chr(10) if len(title) > 45 else '  '}{counts}", fontsize=10)  # long: 2 lines
    return save_figure(plt, fig, path)
