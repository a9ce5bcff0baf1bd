"""bf16 against fp32: the bounds the detections of the two precisions are held to (test_precision on the
CPU, test_cuda on a GPU); no server import, so a GPU machine with the model's dependencies alone runs it."""

from __future__ import annotations

import torch

from model.geometry.boxes import Detections

# bf16 against fp32 on a KITTI scan (docs/benchmarks.md, "bf16 against fp32": 97.9 % over six scans, at most
# 2.7 cm and 0.015 in score, the detector alone): fp32 boxes scoring at least MIN_SCORE need a bf16 box of
# their class within MATCH_M metres for at least MIN_MATCHED of them, and 90 % of the matched scores differ
# by at most MAX_SCORE_DIFF, all by at most MAX_SCORE_OUTLIER. The shipped box refiner re-reads the points at
# each box's grown faces, so a detector box that bf16 moves a little may read other points: on simulated scan
# 0 of stream 7, 11 % of the boxes moved 5-10 cm, none more, and on KITTI 000000 (fixed step) 1 of 19 more
# than 10 cm; reading 64 points a box, one box of 20 changed its refined score by 0.05 (eager) and 0.086
# (fixed step), the next by at most 0.028 (2026-11-29); its IoU score puts fewer boxes above 0.3
MIN_SCORE, MATCH_M, MIN_MATCHED, MAX_SCORE_DIFF, MAX_SCORE_OUTLIER = 0.2, 0.1, 0.9, 0.04, 0.12
# The refiner with its context layer (2026-12-02) moves more of them: on KITTI 000000, 3 of 21 boxes (eager)
# and 4 of 21 (fixed step) 0.17-0.67 m, their refined scores by up to 0.08; its second stage re-reads the
# points around the first's boxes: 4 of 21 moved 0.1-0.68 m in both engines, their scores by up to 0.15, 90 %
# of them within 0.085 (eager) and 0.043 (fixed step). Over the six KITTI scans (2026-12-04) the boxes that
# swing are the unsure ones -- a cyclist box on a pedestrian, pedestrian boxes on a spot no label covers --
# where a few centimetres of the detector's box change the refiner's mind: 90 % of the matched scores within
# 0.19 (the weights before today's: 0.11), the largest 0.35 (0.19), every scan's boxes matched within 1 m
# but one of 7 and one of 22 (the weights before). The detector alone stays within the bounds above, and the
# refined boxes are held to these
REFINED = {"match_m": 1.0, "max_score_diff": 0.2, "max_score_outlier": 0.4}  # assert_agree's bounds


def assert_agree(
    fp32: Detections,
    bf16: Detections,
    min_boxes: int = 15,
    match_m: float = MATCH_M,
    max_score_diff: float = MAX_SCORE_DIFF,
    max_score_outlier: float = MAX_SCORE_OUTLIER,
) -> None:
    """Most of the fp32 boxes scoring >= MIN_SCORE (at least `min_boxes` of them) have a bf16 box of their
    class within `match_m`; their scores differ by at most `max_score_diff` (90 %) and `max_score_outlier`."""
    keep = fp32.scores >= MIN_SCORE
    boxes, labels, scores = fp32.boxes[keep], fp32.labels[keep], fp32.scores[keep]
    assert len(boxes) >= min_boxes  # enough boxes for the fraction to mean something
    dist = torch.cdist(boxes[:, :3], bf16.boxes[:, :3])  # (n32, n16) centre distances
    dist[labels[:, None] != bf16.labels[None, :]] = float("inf")
    nearest, j = dist.min(1)  # (n32,)
    matched = nearest <= match_m
    assert matched.float().mean() >= MIN_MATCHED, f"{matched.float().mean():.3f} of the fp32 boxes matched"
    score_diff = (scores[matched] - bf16.scores[j[matched]]).abs()
    assert score_diff.quantile(0.9) <= max_score_diff and score_diff.max() <= max_score_outlier
    assert score_diff.max() > 0  # bf16 did change something
