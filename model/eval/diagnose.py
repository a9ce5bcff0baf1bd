"""Where a detector's boxes go wrong (`phim diagnose`): its regression read at the true centre cells.

For each labelled scan (no augmentation, all sectors as one stream, full-turn prediction) the head's outputs
are read at the centre cell of every target box, exactly where training supervises them, and decoded as the
loss decodes them. Per class this reports each part's error (centre, z, dims, heading axis and direction),
the 3D IoU of the decoded box with its target, and the same IoU with the true yaw put in: how much of the
shortfall at the AP threshold is heading. It says nothing about false positives or missed peaks; `phim eval`
is the metric.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np
import torch
from torch import Tensor

from model.boxes import rotated_iou_3d_aligned
from model.data.types import LabeledScan
from model.detector import PHiM
from model.eval.metrics import MetricsConfig
from model.phim_block import StreamLayout
from model.train.data import AugmentConfig, SampleConfig, make_sample
from model.train.loss import decoded_boxes, gather_cells, regression_at

NO_AUGMENT = SampleConfig(
    augment=AugmentConfig(rotate=False, flip=False, scale=(1.0, 1.0)), random_start=False
)

# per target box: label, centre error (m), |dz| (m), |l/l'-1|, |w/w'-1|, |h/h'-1|, axis error (deg),
# direction flipped (0/1), IoU, IoU with the true yaw, heatmap score at the centre
COLUMNS = (
    *("centre_m", "z_m", "rel_l", "rel_w", "rel_h", "axis_deg", "flipped"),
    *("iou", "iou_true_yaw", "score"),
)


def box_errors(pred: Tensor, true: Tensor, score: Tensor) -> Tensor:
    """pred, true (T, 7) float64 boxes, score (T,) -> (T, len(COLUMNS)) float64."""
    dyaw = torch.remainder(pred[:, 6] - true[:, 6] + math.pi, 2 * math.pi) - math.pi  # (T,) in [-pi, pi)
    axis = torch.remainder(dyaw + math.pi / 2, math.pi) - math.pi / 2  # (T,) in [-pi/2, pi/2)
    with_true_yaw = torch.cat([pred[:, :6], true[:, 6:]], 1)
    cols = [
        torch.linalg.vector_norm(pred[:, :2] - true[:, :2], dim=1),
        (pred[:, 2] - true[:, 2]).abs(),
        *(pred[:, 3:6] / true[:, 3:6] - 1).abs().unbind(1),
        axis.abs() * 180 / math.pi,
        (dyaw.abs() > math.pi / 2).double(),
        rotated_iou_3d_aligned(pred, true),
        rotated_iou_3d_aligned(with_true_yaw, true),
        score,
    ]
    return torch.stack(cols, 1)


@torch.inference_mode()
def diagnose_scan(model: PHiM, scan: LabeledScan) -> np.ndarray:
    """One scan -> (T, 1 + len(COLUMNS)) float64 rows: the label, then COLUMNS, per target box."""
    sample = make_sample(scan, model.cfg, NO_AUGMENT, np.random.default_rng(0))
    dev = model.device
    sectors = [s.to(dev) for s in sample.sectors]
    enc = model.encode(sectors, StreamLayout.single_stream(len(sectors), dev), model.init_states(1))
    out = model.predict([enc.sectors])  # the full turn
    t = sample.targets[-1]
    _, _, h, w = out.heatmap.shape
    flat = torch.from_numpy(t.index).to(dev)
    reg = regression_at(out, flat)  # (T, 6 + R)
    pred = decoded_boxes(reg, flat, w, h, model.cfg.bev, model.cfg.head.heading).cpu().double()  # (T, 7)
    true = torch.from_numpy(t.boxes).double()  # (T, 7)
    labels = torch.from_numpy(t.labels)
    score = torch.sigmoid(gather_cells(out.heatmap, flat)).cpu().gather(1, labels[:, None])[:, 0]  # (T,)
    return torch.cat([labels.double()[:, None], box_errors(pred, true, score.double())], 1).numpy()


def diagnose(
    model: PHiM,
    indices: Sequence[int],
    scan_at: Callable[[int], LabeledScan],
    metrics: MetricsConfig | None = None,
) -> dict[str, dict[str, float]]:
    """Per class name: target count, the median of each COLUMNS entry (`flipped`: the fraction), and the
    fraction of targets whose IoU reaches the class's AP threshold, with the predicted and the true yaw."""
    thresholds = (metrics or MetricsConfig()).iou_thresholds
    rows = np.concatenate(
        [diagnose_scan(model, scan_at(i)) for i in indices] or [np.zeros((0, 1 + len(COLUMNS)))]
    )
    out: dict[str, dict[str, float]] = {}
    for k, name in enumerate(model.cfg.head.class_names):
        sel = rows[rows[:, 0] == k, 1:]
        if not len(sel):
            continue
        summary = {"targets": float(len(sel))}
        for j, col in enumerate(COLUMNS):
            summary[col] = float(sel[:, j].mean() if col == "flipped" else np.median(sel[:, j]))
        thr = thresholds[k]
        summary["iou_threshold"] = thr
        summary["at_threshold"] = float((sel[:, COLUMNS.index("iou")] >= thr).mean())
        summary["at_threshold_true_yaw"] = float((sel[:, COLUMNS.index("iou_true_yaw")] >= thr).mean())
        out[name] = summary
    return out


def format_diagnosis(d: dict[str, dict[str, float]]) -> str:
    head = (
        "| class | targets | centre err | z err | l / w / h rel. err | axis err | flipped | IoU "
        "| IoU, true yaw | IoU >= thr | same, true yaw | score |"
    )
    rows = [head, "|" + "---|" * 12]
    for name, s in d.items():
        rows.append(
            f"| {name} | {s['targets']:.0f} | {s['centre_m']:.2f} m | {s['z_m']:.2f} m "
            f"| {s['rel_l']:.2f} / {s['rel_w']:.2f} / {s['rel_h']:.2f} | {s['axis_deg']:.1f} deg "
            f"| {s['flipped']:.0%} | {s['iou']:.2f} | {s['iou_true_yaw']:.2f} "
            f"| {s['at_threshold']:.0%} (>= {s['iou_threshold']:g}) | {s['at_threshold_true_yaw']:.0%} "
            f"| {s['score']:.2f} |"
        )
    return "\n".join(rows) + "\n(medians at the true centre cells; flipped and IoU >= thr are fractions)"
