"""Where a detector's boxes go wrong (`phim diagnose`): its regression read at the true centre cells.

For each labelled scan (no augmentation, all sectors as one stream, full-turn prediction) the head's outputs
are read at the centre cell of every target box, exactly where training supervises them, and decoded as the
loss decodes them. Per class this reports each part's error (centre, z, dims, heading axis and direction),
the 3D IoU of the decoded box with its target, and the same IoU with one part of the target put in (its yaw,
its size, its centre): how much of the shortfall at the AP threshold each part is; optionally broken down
by how well each box is seen (points inside it) or by its range. It says nothing about false positives or
missed peaks; `phim eval` is the metric.
"""

from __future__ import annotations

import enum
import itertools
import math
from collections.abc import Callable, Sequence

import numpy as np
import torch
from torch import Tensor

from lidar.readers import feature_columns, sector_of_xy
from lidar.types import LabeledScan
from model.detector import PHiM
from model.eval.metrics import MetricsConfig
from model.geometry.boxes import rotated_iou_3d_aligned
from model.layers.head import decoded_boxes, gather_cells, regression_at
from model.layers.head_targets import BEVTargets, TargetConfig, build_targets
from model.layers.phim_block import StreamLayout

# per target box: label, centre error (m), |dz| (m), |l/l'-1|, |w/w'-1|, |h/h'-1|, axis error (deg),
# direction flipped (0/1), IoU, IoU with the true yaw / size (l, w, h) / centre (x, y, z), heatmap score at
# the centre
TRUE_PARTS = ("yaw", "size", "centre")
COLUMNS = (
    *("centre_m", "z_m", "rel_l", "rel_w", "rel_h", "axis_deg", "flipped"),
    *("iou", *(f"iou_true_{part}" for part in TRUE_PARTS), "score"),
)
# per target box, after COLUMNS: the points of the scan inside it, its distance from the sensor (m)
CONTEXT = ("points", "range_m")


class Breakdown(enum.StrEnum):
    """How `diagnose` groups the target boxes: by class, or by class and a bucket of points or range."""

    CLASS = "class"
    POINTS = "points"
    RANGE = "range"


# the CONTEXT column each breakdown buckets, and the buckets' lower edges (points: counts; range: metres)
BUCKETS = {Breakdown.POINTS: ("points", (0, 21, 51, 101, 301)), Breakdown.RANGE: ("range_m", (0, 15, 30, 45))}


def box_errors(pred: Tensor, true: Tensor, score: Tensor) -> Tensor:
    """pred, true (T, 7) float64 boxes, score (T,) -> (T, len(COLUMNS)) float64."""
    dyaw = torch.remainder(pred[:, 6] - true[:, 6] + math.pi, 2 * math.pi) - math.pi  # (T,) in [-pi, pi)
    axis = torch.remainder(dyaw + math.pi / 2, math.pi) - math.pi / 2  # (T,) in [-pi/2, pi/2)
    with_true = (  # pred with the true yaw, size, centre: (T, 7) each
        torch.cat([pred[:, :6], true[:, 6:]], 1),
        torch.cat([pred[:, :3], true[:, 3:6], pred[:, 6:]], 1),
        torch.cat([true[:, :3], pred[:, 3:]], 1),
    )
    cols = [
        torch.linalg.vector_norm(pred[:, :2] - true[:, :2], dim=1),
        (pred[:, 2] - true[:, 2]).abs(),
        *(pred[:, 3:6] / true[:, 3:6] - 1).abs().unbind(1),
        axis.abs() * 180 / math.pi,
        (dyaw.abs() > math.pi / 2).double(),
        rotated_iou_3d_aligned(pred, true),
        *(rotated_iou_3d_aligned(b, true) for b in with_true),
        score,
    ]
    return torch.stack(cols, 1)


def turn_targets(scan: LabeledScan, model: PHiM) -> tuple[list[Tensor], BEVTargets]:
    """The scan as the model's sectors in azimuth order (no augmentation) and the full turn's training
    targets: every labelled box with at least one point, as training builds them."""
    cfg = model.cfg
    points = feature_columns(scan, cfg.vfe.point_features)  # (N, C)
    sector = sector_of_xy(points[:, 0], points[:, 1], cfg.sectors_per_turn)  # (N,)
    sectors = [torch.from_numpy(points[sector == k]).to(model.device) for k in range(cfg.sectors_per_turn)]
    seen = scan.gt.num_points > 0  # a box without points is not a target (Waymo)
    boxes, labels = scan.gt.boxes[seen], scan.gt.labels[seen]
    return sectors, build_targets(boxes, labels, len(cfg.head.class_names), cfg.bev, TargetConfig())


@torch.inference_mode()
def diagnose_scan(model: PHiM, scan: LabeledScan) -> np.ndarray:
    """One scan -> (T, 1 + len(COLUMNS) + len(CONTEXT)) float64 rows per target box: the label, COLUMNS,
    CONTEXT."""
    sectors, t = turn_targets(scan, model)
    dev = model.device
    enc = model.encode(sectors, StreamLayout.single_stream(len(sectors), dev), model.init_states(1))
    out = model.predict([enc.sectors])  # the full turn
    _, _, h, w = out.heatmap.shape
    flat = torch.from_numpy(t.index).to(dev)
    reg = regression_at(out, flat)  # (T, 6 + R)
    pred = decoded_boxes(reg, flat, w, h, model.cfg.bev, model.cfg.head.heading).cpu().double()  # (T, 7)
    true = torch.from_numpy(t.boxes).double()  # (T, 7)
    labels = torch.from_numpy(t.labels)
    score = torch.sigmoid(gather_cells(out.heatmap, flat)).cpu().gather(1, labels[:, None])[:, 0]  # (T,)
    errors = box_errors(pred, true, score.double()).numpy()
    return np.column_stack([t.labels, errors, _context(t.boxes, scan)])


def _context(targets: np.ndarray, scan: LabeledScan) -> np.ndarray:
    """(T, 7) target boxes (unaugmented copies of ground-truth boxes) -> (T, 2): points inside, range."""
    gt = scan.gt.boxes
    dist = np.hypot(targets[:, None, 0] - gt[None, :, 0], targets[:, None, 1] - gt[None, :, 1])  # (T, M)
    match = dist.argmin(axis=1) if gt.shape[0] else np.zeros(0, np.int64)  # (T,)
    if targets.shape[0] and not (dist.min(axis=1) < 1e-3).all():
        raise ValueError(f"scan {scan.name}: a target box is not one of the ground-truth boxes")
    return np.column_stack([scan.gt.num_points[match], np.hypot(gt[match, 0], gt[match, 1])])


def _bucket_names(by: Breakdown) -> list[str]:
    edges, unit = BUCKETS[by][1], "points" if by is Breakdown.POINTS else "m"
    step = 1 if by is Breakdown.POINTS else 0  # points are counts: 0-20, 21-50; ranges meet: 0-15, 15-30
    names = [f"{lo}-{hi - step} {unit}" for lo, hi in itertools.pairwise(edges)]
    return [*names, f">= {edges[-1]} {unit}"]


def _summary(sel: np.ndarray, thr: float) -> dict[str, float]:
    """Rows of one group (COLUMNS first) -> target count, medians (`flipped`: the fraction), share >= thr."""
    summary = {"targets": float(len(sel))}
    for j, col in enumerate(COLUMNS):
        summary[col] = float(sel[:, j].mean() if col == "flipped" else np.median(sel[:, j]))
    summary["iou_threshold"] = thr
    summary["at_threshold"] = float((sel[:, COLUMNS.index("iou")] >= thr).mean())
    for part in TRUE_PARTS:
        iou = sel[:, COLUMNS.index(f"iou_true_{part}")]
        summary[f"at_threshold_true_{part}"] = float((iou >= thr).mean())
    return summary


def diagnose(
    model: PHiM,
    indices: Sequence[int],
    scan_at: Callable[[int], LabeledScan],
    metrics: MetricsConfig | None = None,
    by: Breakdown = Breakdown.CLASS,
) -> dict[str, dict[str, float]]:
    """Per class name (with `by` points / range: per "CLASS, bucket"): target count, the median of each
    COLUMNS entry (`flipped`: the fraction), and the fraction of targets whose IoU reaches the class's AP
    threshold, as predicted and with the true yaw, size or centre put in. Empty groups are left out."""
    thresholds = (metrics or MetricsConfig()).iou_thresholds
    width = 1 + len(COLUMNS) + len(CONTEXT)
    rows = np.concatenate([diagnose_scan(model, scan_at(i)) for i in indices] or [np.zeros((0, width))])
    out: dict[str, dict[str, float]] = {}
    for k, name in enumerate(model.cfg.head.class_names):
        of_class = rows[rows[:, 0] == k, 1:]
        if by is Breakdown.CLASS:
            groups = {name: of_class}
        else:
            column, edges = BUCKETS[by]
            value = of_class[:, len(COLUMNS) + CONTEXT.index(column)]  # (n,)
            bucket = np.searchsorted(np.asarray(edges), value, side="right") - 1  # (n,)
            groups = {f"{name}, {b}": of_class[bucket == i] for i, b in enumerate(_bucket_names(by))}
        out.update({key: _summary(sel, thresholds[k]) for key, sel in groups.items() if len(sel)})
    return out


def format_diagnosis(d: dict[str, dict[str, float]]) -> str:
    head = (
        "| group | targets | centre err | z err | l / w / h rel. err | axis err | flipped | IoU "
        "| IoU, true yaw | IoU >= thr | same, true yaw / size / centre | score |"
    )
    rows = [head, "|" + "---|" * 12]
    for name, s in d.items():
        rows.append(
            f"| {name} | {s['targets']:.0f} | {s['centre_m']:.2f} m | {s['z_m']:.2f} m "
            f"| {s['rel_l']:.2f} / {s['rel_w']:.2f} / {s['rel_h']:.2f} | {s['axis_deg']:.1f} deg "
            f"| {s['flipped']:.0%} | {s['iou']:.2f} | {s['iou_true_yaw']:.2f} "
            f"| {s['at_threshold']:.0%} (>= {s['iou_threshold']:g}) "
            f"| {' / '.join(format(s['at_threshold_true_' + p], '.0%') for p in TRUE_PARTS)} "
            f"| {s['score']:.2f} |"
        )
    return "\n".join(rows) + "\n(medians at the true centre cells; flipped and IoU >= thr are fractions)"
