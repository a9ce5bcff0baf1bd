"""Waymo-style 3D detection metrics: AP and APH per class at LEVEL_1 and LEVEL_2.

Reproduces the Waymo Open Dataset's official detection metric (OBJECT_TYPE breakdown, LEVEL_1 and LEVEL_2,
Hungarian matcher, 3D IoU thresholds 0.7 / 0.5 / 0.5, score cut-offs 0, 0.01, ..., 0.99, 1.0). The rules and
the files of waymo-research/waymo-open-dataset they come from are written down in docs/evaluation.md.

Per scan and class, predictions at or above each score cut-off are matched to the ground truths (boxes with
no point removed) by a maximum-weight matching on quantized IoU, pairs below the class's IoU threshold
excluded. A matched prediction is a true positive whatever the ground truth's difficulty; an unmatched one
is a false positive; an unmatched ground truth is a false negative at the levels it belongs to (LEVEL_2
counts every box, LEVEL_1 only LEVEL_1 boxes). Counts are summed over scans, turned into one
precision / recall pair per cut-off, and integrated into AP; APH weights every true positive by its heading
accuracy 1 - |heading error| / pi.

The matching only changes where a prediction drops out, so it is solved once per group of predictions and
ground truths that touch each other (a connected component of the above-threshold pairs) and per distinct
number of that group's predictions above the cut-off, not once per cut-off.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from lidar.types import GroundTruth, Predictions
from model.config import CLASS_NAMES
from model.eval.assignment import max_weight_matching
from model.geometry.boxes import rotated_iou_3d

LEVEL_NAMES: tuple[str, str] = ("LEVEL_1", "LEVEL_2")
LEVELS: tuple[int, int] = (1, 2)  # difficulty values of lidar.types (LEVEL_1, LEVEL_2)
# Waymo's cut-offs: i * 0.01 for i < 100, then 1.0, stored as float32 (metrics.proto `repeated float`)
WAYMO_SCORE_CUTOFFS: tuple[float, ...] = (*(float(np.float32(i * 0.01)) for i in range(100)), 1.0)
MIN_BOX_DIM = 1e-2  # iou.cc: IoU is 0 when any length / width / height is at most this
IOU_WEIGHT_SCALE = 1_000_000  # iou.cc kMaxIoU: matching weights are round(IoU * 1e6)
RECALL_EPS = 1e-6  # metrics_utils.cc ComputeMeanAveragePrecision kError


@dataclass(frozen=True)
class MetricsConfig:
    iou_thresholds: tuple[float, ...] = (0.7, 0.5, 0.5)  # 3D IoU to match, per class of CLASS_NAMES
    score_cutoffs: tuple[float, ...] = WAYMO_SCORE_CUTOFFS  # one precision / recall pair each
    recall_delta: float = 0.05  # metrics.proto desired_recall_delta: largest recall step in the integration

    def __post_init__(self) -> None:
        if len(self.iou_thresholds) != len(CLASS_NAMES):
            raise ValueError(f"need one IoU threshold per class {CLASS_NAMES}, got {self.iou_thresholds}")
        if not all(0.0 < t <= 1.0 for t in self.iou_thresholds):
            raise ValueError(f"IoU thresholds must lie in (0, 1], got {self.iou_thresholds}")
        if not self.score_cutoffs or not all(0.0 <= s <= 1.0 for s in self.score_cutoffs):
            raise ValueError("score_cutoffs must be a non-empty list of values in [0, 1]")
        if not 0.0 < self.recall_delta <= 1.0:
            raise ValueError(f"recall_delta must lie in (0, 1], got {self.recall_delta}")


@dataclass(frozen=True)
class Measurements:
    """Waymo's per-cut-off counts, summed over scans. C: number of score cut-offs."""

    tp: np.ndarray  # (3, C) int64 matched predictions per class (the same at both levels)
    fp: np.ndarray  # (3, C) int64 unmatched predictions
    fn: np.ndarray  # (3, 2, C) int64 unmatched ground truths counted at LEVEL_1, LEVEL_2
    sum_ha: np.ndarray  # (3, C) float64 heading accuracy summed over the true positives
    num_gt: np.ndarray  # (3, 2) int64 ground truths counted at LEVEL_1, LEVEL_2 (boxes with points)


def _wrap_angle(a: np.ndarray) -> np.ndarray:
    """Angles in radians -> the same angles in [-pi, pi), float64."""
    return np.mod(np.asarray(a, np.float64) + math.pi, 2 * math.pi) - math.pi


def heading_accuracy(pd_yaw: np.ndarray, gt_yaw: np.ndarray) -> np.ndarray:
    """1 - |heading difference| / pi, the difference wrapped into [0, pi]; broadcasts. metrics_utils.cc."""
    diff = np.abs(_wrap_angle(pd_yaw) - _wrap_angle(gt_yaw))
    diff = np.where(diff > math.pi, 2 * math.pi - diff, diff)
    return np.clip(1.0 - diff / math.pi, 0.0, 1.0)


def iou_matrix(pd_boxes: np.ndarray, gt_boxes: np.ndarray) -> np.ndarray:
    """(K, 7), (M, 7) boxes -> (K, M) float32 3D IoU, 0 for boxes with a side of at most MIN_BOX_DIM."""
    a = torch.as_tensor(np.asarray(pd_boxes, np.float64).reshape(-1, 7))
    b = torch.as_tensor(np.asarray(gt_boxes, np.float64).reshape(-1, 7))
    iou = rotated_iou_3d(a, b).numpy().clip(0.0, 1.0)  # (K, M) float64, as Waymo computes it
    pd_ok = np.all(a[:, 3:6].numpy() > MIN_BOX_DIM, axis=1)  # (K,)
    gt_ok = np.all(b[:, 3:6].numpy() > MIN_BOX_DIM, axis=1)  # (M,)
    return np.where(pd_ok[:, None] & gt_ok[None, :], iou, 0.0).astype(np.float32)


def _components(edges: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """(K, M) bool pairs -> connected groups (prediction indices, ground truth indices) with an edge."""
    k, m = edges.shape
    parent = np.arange(k + m)  # union-find over predictions 0..K-1 and ground truths K..K+M-1

    def root(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = int(parent[a])
        return a

    for i, j in zip(*np.nonzero(edges), strict=True):
        parent[root(int(i))] = root(k + int(j))
    roots = np.array([root(a) for a in range(k + m)], np.int64)  # (K + M,)
    touched = np.concatenate([edges.any(axis=1), edges.any(axis=0)])  # (K + M,)
    groups = []
    for r in np.unique(roots[touched]):
        members = np.nonzero(roots == r)[0]
        groups.append((members[members < k], members[members >= k] - k))
    return groups


def matching_weights(iou: np.ndarray, threshold: float) -> np.ndarray:
    """(K, M) float32 IoU -> (K, M) Waymo matching weights: round(IoU * 1e6) where IoU >= threshold, else 0
    (matcher.cc HungarianMatcher, matcher.h QuantizedWeight)."""
    iou = np.asarray(iou, np.float32)
    quantized = np.floor(iou.astype(np.float64) * IOU_WEIGHT_SCALE + 0.5)  # std::round for IoU >= 0
    return np.where(iou >= np.float32(threshold), quantized, 0.0)


def _prefix_tables(
    weight: np.ndarray, ha: np.ndarray, counted: np.ndarray, lengths: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Matching of the first n predictions of one component (sorted by score), for each n in lengths (L,).
    weight, ha (k, g), counted (2, g) -> matched predictions (L,), their heading accuracy (L,), unmatched
    ground truths counted per level (2, L)."""
    if weight.shape[1] == 1:  # one ground truth: it takes the heaviest prediction kept (first one on ties)
        w = weight[:, 0]  # (k,) all positive: every prediction of the component can match it
        is_new_best = w > np.concatenate([[-1.0], np.maximum.accumulate(w)[:-1]])  # (k,)
        # (k,) best among the first i + 1 predictions
        best = np.maximum.accumulate(np.where(is_new_best, np.arange(w.shape[0]), 0))
        some = lengths > 0  # (L,)
        tp = some.astype(np.int64)
        sum_ha = np.where(some, ha[best[np.maximum(lengths - 1, 0)], 0], 0.0)
        return tp, sum_ha, (counted[:, :1] & ~some[None, :]).astype(np.int64)
    tp, sum_ha = np.zeros(lengths.shape[0], np.int64), np.zeros(lengths.shape[0])
    fn = np.zeros((2, lengths.shape[0]), np.int64)
    for i, n in enumerate(lengths):
        match = max_weight_matching(weight[:n])  # (n,) index into the ground truths or -1
        hit = match >= 0
        matched_gt = np.zeros(weight.shape[1], bool)
        matched_gt[match[hit]] = True
        tp[i], sum_ha[i] = hit.sum(), ha[:n][hit, match[hit]].sum()
        fn[:, i] = counted[:, ~matched_gt].sum(axis=1)
    return tp, sum_ha, fn


def _match_class(
    iou: np.ndarray,
    ha: np.ndarray,
    scores: np.ndarray,
    gt_level: np.ndarray,
    threshold: float,
    cutoffs: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One scan, one class. iou, ha (K, M), scores (K,) float32, gt_level (M,), cutoffs (C,) float32 ->
    tp (C,), fp (C,), fn (2, C), sum_ha (C,) at every score cut-off."""
    n_cut = cutoffs.shape[0]
    weight = matching_weights(iou, threshold)  # (K, M)
    edges = weight > 0  # (K, M) pairs allowed to match
    above = scores[:, None] >= cutoffs[None, :]  # (K, C) prediction kept at each cut-off
    counted = gt_level[None, :] <= np.array(LEVELS)[:, None]  # (2, M) ground truth counted at each level
    tp, sum_ha = np.zeros(n_cut, np.int64), np.zeros(n_cut)
    fp = above[~edges.any(axis=1)].sum(axis=0).astype(np.int64)  # never matchable: false positives
    fn = np.repeat(counted[:, ~edges.any(axis=0)].sum(axis=1, keepdims=True), n_cut, axis=1)  # (2, C)
    for preds, gts in _components(edges):
        preds = preds[np.argsort(-scores[preds], kind="stable")]  # kept predictions are a prefix
        kept = above[preds].sum(axis=0)  # (C,) prefix length at each cut-off
        lengths = np.unique(kept)  # (L,) sorted
        pair = np.ix_(preds, gts)
        t_tp, t_ha, t_fn = _prefix_tables(weight[pair], ha[pair], counted[:, gts], lengths)
        at = np.searchsorted(lengths, kept)  # (C,) row of the table for each cut-off
        tp += t_tp[at]
        fp += kept - t_tp[at]
        sum_ha += t_ha[at]
        fn += t_fn[:, at]
    return tp, fp, fn, sum_ha


def measure(
    predictions: Sequence[Predictions], ground_truths: Sequence[GroundTruth], cfg: MetricsConfig
) -> Measurements:
    """Waymo's true / false positive and false negative counts per class, level and score cut-off."""
    if len(predictions) != len(ground_truths):
        raise ValueError(f"{len(predictions)} prediction sets for {len(ground_truths)} scans")
    n_cls, cutoffs = len(CLASS_NAMES), np.asarray(cfg.score_cutoffs, np.float32)  # (C,)
    tp, fp = np.zeros((n_cls, cutoffs.shape[0]), np.int64), np.zeros((n_cls, cutoffs.shape[0]), np.int64)
    fn, sum_ha = np.zeros((n_cls, 2, cutoffs.shape[0]), np.int64), np.zeros((n_cls, cutoffs.shape[0]))
    num_gt = np.zeros((n_cls, 2), np.int64)
    for pred, gt in zip(predictions, ground_truths, strict=True):
        gt = gt.select(np.asarray(gt.num_points) > 0)  # Waymo drops boxes without a point
        iou = iou_matrix(pred.boxes, gt.boxes)  # (K, M) all classes at once
        ha = heading_accuracy(np.asarray(pred.boxes)[:, None, 6], np.asarray(gt.boxes)[None, :, 6])  # (K, M)
        scores = np.asarray(pred.scores, np.float32)
        for c in range(n_cls):
            pidx = np.nonzero(np.asarray(pred.labels) == c)[0]  # (Kc,)
            gidx = np.nonzero(np.asarray(gt.labels) == c)[0]  # (Mc,)
            level = np.asarray(gt.difficulty, np.int64)[gidx]  # (Mc,)
            num_gt[c] += [(level <= lv).sum() for lv in LEVELS]
            pairs = np.ix_(pidx, gidx)
            counts = _match_class(iou[pairs], ha[pairs], scores[pidx], level, cfg.iou_thresholds[c], cutoffs)
            tp[c] += counts[0]
            fp[c] += counts[1]
            fn[c] += counts[2]
            sum_ha[c] += counts[3]
    return Measurements(tp, fp, fn, sum_ha, num_gt)


def average_precision(precisions: Sequence[float], recalls: Sequence[float], recall_delta: float) -> float:
    """Area under Waymo's precision / recall curve (metrics_utils.cc ComputeMeanAveragePrecision).

    The curve holds (recall 0, precision 1) and, per recall, the best precision; going from high to low
    recall, precision becomes the best one at this recall or above, and points are inserted every
    `recall_delta` into larger gaps; the point at recall 0 takes the precision of its neighbour; then the
    trapezoid rule.
    """
    if len(precisions) == 0:
        return 0.0
    best: dict[float, float] = {0.0: 1.0}  # recall -> highest precision
    for p, r in zip(precisions, recalls, strict=True):
        best[float(r)] = max(best.get(float(r), 0.0), float(p))
    curve: list[tuple[float, float]] = []  # (recall, precision), recall decreasing
    last, top = 0.0, 0.0  # as in Waymo, `last` starts at the lowest recall: nothing is added above the top
    for r in sorted(best, reverse=True):
        while last - r > recall_delta + RECALL_EPS:
            last -= recall_delta
            curve.append((last, top))
        top = max(top, best[r])
        curve.append((r, top))
        last = r
    if len(curve) >= 2:
        curve[-1] = (curve[-1][0], curve[-2][1])
    return float(sum(0.5 * (r0 - r1) * (p0 + p1) for (r0, p0), (r1, p1) in itertools.pairwise(curve)))


def ap_aph_from_counts(
    tp: np.ndarray, fp: np.ndarray, fn: np.ndarray, sum_ha: np.ndarray, recall_delta: float
) -> tuple[float, float]:
    """(C,) counts per cut-off -> (AP, APH), with Waymo's precision and recall (detection_metrics.cc)."""
    tp, fp, fn = (np.asarray(x, np.float64) for x in (tp, fp, fn))
    claimed, existing = tp + fp, tp + fn  # (C,)
    precision = np.where(claimed > 0, tp / np.maximum(claimed, 1), 0.0).astype(np.float32)
    precision_ha = np.where(claimed > 0, sum_ha / np.maximum(claimed, 1), 0.0).astype(np.float32)
    recall = np.where(existing > 0, tp / np.maximum(existing, 1), 0.0).astype(np.float32)
    precision = np.where(recall == 0, 1.0, precision)  # Waymo: precision 1 where recall is 0
    precision_ha = np.where(recall == 0, 1.0, precision_ha)
    ap = average_precision(precision.tolist(), recall.tolist(), recall_delta)
    aph = average_precision(precision_ha.tolist(), recall.tolist(), recall_delta)
    return float(np.clip(ap, 0.0, 1.0)), float(np.clip(aph, 0.0, 1.0))


def summarize(m: Measurements, cfg: MetricsConfig = MetricsConfig()) -> dict:
    """Counts -> {level: {class: {"AP", "APH"}, "mean": {...}}}. The mean is over the classes with at least
    one ground truth counted at that level (0.0 when there is none)."""
    result: dict = {}
    for li, level in enumerate(LEVEL_NAMES):
        table: dict = {}
        present: list[tuple[float, float]] = []
        for ci, name in enumerate(CLASS_NAMES):
            ap, aph = ap_aph_from_counts(m.tp[ci], m.fp[ci], m.fn[ci, li], m.sum_ha[ci], cfg.recall_delta)
            table[name] = {"AP": ap, "APH": aph}
            if m.num_gt[ci, li] > 0:
                present.append((ap, aph))
        mean = np.mean(present, axis=0).tolist() if present else [0.0, 0.0]
        table["mean"] = {"AP": float(mean[0]), "APH": float(mean[1])}
        result[level] = table
    return result


def evaluate(
    predictions: Sequence[Predictions],
    ground_truths: Sequence[GroundTruth],
    cfg: MetricsConfig = MetricsConfig(),
) -> dict:
    """AP and APH per class and level over a set of scans (predictions[i] belongs to ground_truths[i])."""
    return summarize(measure(predictions, ground_truths, cfg), cfg)


def count_ground_truths(ground_truths: Sequence[GroundTruth]) -> dict:
    """{level: {class: boxes counted at that level}}: boxes with at least one point, LEVEL_2 all of them."""
    counts = {level: dict.fromkeys(CLASS_NAMES, 0) for level in LEVEL_NAMES}
    for gt in ground_truths:
        keep = np.asarray(gt.num_points) > 0
        labels, difficulty = np.asarray(gt.labels)[keep], np.asarray(gt.difficulty)[keep]
        for level, lv in zip(LEVEL_NAMES, LEVELS, strict=True):
            for c, name in enumerate(CLASS_NAMES):
                counts[level][name] += int(((labels == c) & (difficulty <= lv)).sum())
    return counts


def crop_to_fov(pred: Predictions, fov: tuple[float, float] | None) -> Predictions:
    """Keep predictions whose centre azimuth atan2(y, x) lies in [lo, hi) (radians in [-pi, pi]); lo > hi
    means the range wraps through +-pi. None keeps everything (labels all around)."""
    if fov is None:
        return pred
    lo, hi = fov
    boxes = np.asarray(pred.boxes)
    azimuth = np.arctan2(boxes[:, 1].astype(np.float64), boxes[:, 0])  # (K,)
    inside = (azimuth >= lo) & (azimuth < hi)  # (K,)
    keep = inside if lo <= hi else (azimuth >= lo) | (azimuth < hi)
    return Predictions(boxes[keep], np.asarray(pred.scores)[keep], np.asarray(pred.labels)[keep])


def format_table(result: dict, num_gt: dict | None = None) -> str:
    """Human-readable table of `evaluate`'s result: one row per level and class, columns AP, APH (and the
    number of ground truths, from `count_ground_truths`, when given)."""
    header = f"{'level':<8} {'class':<11} {'AP':>7} {'APH':>7}" + (f" {'GT':>7}" if num_gt else "")
    lines = [header, "-" * len(header)]
    for level in LEVEL_NAMES:
        for name in (*CLASS_NAMES, "mean"):
            row = result[level][name]
            line = f"{level:<8} {name:<11} {row['AP']:>7.4f} {row['APH']:>7.4f}"
            if num_gt:
                n = num_gt[level].get(name)
                line += f" {n if n is not None else '':>7}"
            lines.append(line)
    return "\n".join(lines)
