"""A BEV picture of one evaluated scan: points, ground truth (dashed) and full-turn predictions (solid)."""

from __future__ import annotations

from pathlib import Path

from model.config import CLASS_NAMES
from model.data.pictures import BoxSet, draw_bev
from model.data.types import LabeledScan
from model.eval.runner import ScanResult

MIN_SCORE = 0.3  # predictions drawn; lower ones would hide the picture


def draw_result(path: Path, scan: LabeledScan, result: ScanResult) -> Path:
    p, gt = result.predictions[-1], result.truths[-1]
    shown = p.scores >= MIN_SCORE
    preds = BoxSet(p.boxes[shown], tuple(CLASS_NAMES[i] for i in p.labels[shown]), p.scores[shown])
    truth = gt.select(gt.num_points > 0)
    labels = BoxSet(truth.boxes, tuple(CLASS_NAMES[i] for i in truth.labels))
    title = f"{scan.name} (scores >= {MIN_SCORE})"
    return draw_bev(path, scan.points, preds, labels, title=title)
