"""Precision and recall against the score threshold (`phim eval --score-curve`): where to cut the boxes a
server returns (`phim serve --min-score`, docs/model-card.md, "The score threshold").

The full-turn predictions, cropped to the labels' field of view and to --max-range as for the AP, at each
threshold t in `CUTOFFS`: a box scored >= t is a true positive where Waymo's matching (`metrics.measure`)
pairs it with a labelled object of its class at 3D IoU >= the class's `IOU`, else a false positive; recall
is over the LEVEL_1 labels (more than 5 points). F1 = 2 P R / (P + R). Boxes per scan counts every class
at t, in the labels' field of view. The evaluation itself reads every box: only this curve cuts.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from model.config import CLASS_NAMES
from model.eval.metrics import MetricsConfig, measure
from model.eval.runner import ScanResult

CUTOFFS: tuple[float, ...] = tuple(round(0.05 * i, 2) for i in range(1, 19))  # 0.05 .. 0.90
# 3D IoU per class (vehicle, pedestrian, cyclist): a box in the right place, the size roughly right (the AP
# asks 0.7 of a vehicle)
IOU: tuple[float, ...] = (0.5, 0.5, 0.5)


def _ratio(num: np.ndarray, den: np.ndarray) -> list[float | None]:
    return [float(n / d) if d > 0 else None for n, d in zip(num, den, strict=True)]


def score_curve(
    results: Sequence[ScanResult], iou: tuple[float, ...] = IOU, cutoffs: tuple[float, ...] = CUTOFFS
) -> dict:
    """-> {"iou": {class: IoU}, "cutoffs": [t], "boxes_per_scan": [mean at t], "max_boxes_per_scan": [...],
    "classes": {class: {"labels", "precision": [P or None], "recall": [R], "f1": [F1], "best": t of the
    highest F1 or None}}} (lists: one value per cut-off)."""
    preds, truths = [r.predictions[-1] for r in results], [r.truths[-1] for r in results]
    m = measure(preds, truths, MetricsConfig(iou_thresholds=iou, score_cutoffs=cutoffs))
    cut = np.asarray(cutoffs, np.float32)  # (C,)
    per_scan = np.array([(np.asarray(p.scores)[:, None] >= cut[None]).sum(0) for p in preds])  # (S, C)
    classes = {}
    for c, name in enumerate(CLASS_NAMES):
        tp, fp, fn = m.tp[c], m.fp[c], m.fn[c, 0]  # (C,) each
        precision, recall = _ratio(tp, tp + fp), _ratio(tp, tp + fn)
        f1 = [2 * p * r / (p + r) if p and r else 0.0 for p, r in zip(precision, recall, strict=True)]
        best = int(np.argmax(f1)) if max(f1) > 0 else None
        classes[name] = {
            "labels": int(m.num_gt[c, 0]),
            "precision": precision,
            "recall": recall,
            "f1": f1,
            "best": None if best is None else cutoffs[best],
        }
    return {
        "iou": dict(zip(CLASS_NAMES, iou, strict=True)),
        "cutoffs": list(cutoffs),
        "boxes_per_scan": per_scan.mean(0).tolist() if len(preds) else [0.0] * len(cutoffs),
        "max_boxes_per_scan": per_scan.max(0).tolist() if len(preds) else [0] * len(cutoffs),
        "classes": classes,
    }


def _num(v: float | None) -> str:
    return "-" if v is None else f"{v:.3f}"


def format_curve(curve: dict) -> str:
    """The curve as a table: a row per cut-off, precision / recall / F1 per class with labels."""
    names = [n for n, c in curve["classes"].items() if c["labels"] > 0]
    iou = ", ".join(f"{n} {curve['iou'][n]:g}" for n in names)
    head = f"precision / recall / F1 by score threshold (3D IoU {iou}; recall of LEVEL_1 labels):"
    cols = "".join(f" {n[:10] + ' P/R/F1':>22}" for n in names)
    lines = [head, f"{'score >=':>8} {'boxes/scan':>10}{cols}"]
    for k, t in enumerate(curve["cutoffs"]):
        row = f"{t:>8.2f} {curve['boxes_per_scan'][k]:>10.1f}"
        for n in names:
            c = curve["classes"][n]
            p, r = (_num(c[key][k]) for key in ("precision", "recall"))
            row += f" {p:>8}/{r}/{c['f1'][k]:.3f}"
        lines.append(row)
    best = ", ".join(f"{n} {curve['classes'][n]['best']}" for n in names)
    lines.append(f"highest F1 at: {best}")
    return "\n".join(lines)
