"""A BEV picture of one evaluated scan: points, ground truth (dashed) and the full-turn predictions a server
at `min_score` would return (solid), drawn as `phim replay --frames` draws a reply (lidar.pictures)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from contract import DEFAULT_MIN_SCORE
from lidar.pictures import BoxSet, draw_bev
from lidar.types import LabeledScan, Predictions
from model.config import CLASS_NAMES
from model.eval.runner import ScanResult


def draw_result(
    path: Path, scan: LabeledScan, result: ScanResult, min_score: float = DEFAULT_MIN_SCORE
) -> Path:
    gt = result.truths[-1]
    truth = gt.select(gt.num_points > 0)
    labels = BoxSet(truth.boxes, tuple(CLASS_NAMES[i] for i in truth.labels))
    preds = replied_boxes(result.predictions[-1], min_score)
    return draw_bev(path, scan.points, preds, labels, title=scan.name, min_score=min_score)


def replied_boxes(p: Predictions, min_score: float) -> BoxSet:
    """The boxes a server at `min_score` returns of these predictions (those scored at least it)."""
    shown = p.scores >= np.float32(min_score)  # (K,) as the server compares
    return BoxSet(p.boxes[shown], tuple(CLASS_NAMES[i] for i in p.labels[shown]), p.scores[shown])
