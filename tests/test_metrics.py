"""Waymo-style AP / APH (model.eval.metrics) and the assignment solver (model.eval.assignment).

Reference numbers come from waymo-research/waymo-open-dataset: its C++ and Python tests (cited at each test)
and, for the random scenes at the end, its official `detection_metrics` op (PyPI package
waymo-open-dataset-tf-2-12-0 1.6.7 on TensorFlow 2.13, run once outside this project).
"""

from __future__ import annotations

import itertools
import json
import math

import numpy as np
import pytest

from lidar.types import LEVEL_1, LEVEL_2, GroundTruth, Predictions
from model.eval.assignment import max_weight_matching
from model.eval.metrics import (
    WAYMO_SCORE_CUTOFFS,
    MetricsConfig,
    ap_aph_from_counts,
    average_precision,
    count_ground_truths,
    crop_to_fov,
    evaluate,
    format_table,
    heading_accuracy,
    iou_matrix,
    matching_weights,
    measure,
)

V, P, C = 0, 1, 2  # VEHICLE, PEDESTRIAN, CYCLIST
# the op tests' config (detection_metrics_ops_test.py _BuildConfig): cut-offs 0, 0.1, ..., 1, IoU 0.5
OPS_TEST_CFG = MetricsConfig(
    iou_thresholds=(0.5, 0.5, 0.5), score_cutoffs=tuple(float(np.float32(i / 10)) for i in range(11))
)
CPP_TEST_CFG = MetricsConfig(iou_thresholds=(0.5, 0.5, 0.5), score_cutoffs=(0.0, 0.5, 1.0))


def preds(boxes: list, scores: list, labels: list) -> Predictions:
    b = np.asarray(boxes, np.float32).reshape(-1, 7)
    return Predictions(b, np.asarray(scores, np.float32), np.asarray(labels, np.int64))


def truths(boxes: list, labels: list, points: list | None = None, levels: list | None = None) -> GroundTruth:
    b = np.asarray(boxes, np.float32).reshape(-1, 7)
    pts = np.asarray(points if points is not None else [50] * len(b), np.int64)
    lv = np.asarray(levels if levels is not None else [LEVEL_1] * len(b), np.int8)
    return GroundTruth(b, np.asarray(labels, np.int64), pts, lv)


def waymo_box(iou: float) -> list[float]:
    """detection_metrics_test.cc BuildObject: a box with IoU `iou` against waymo_box(1.0)."""
    return [0.0, 0.0, 0.0, iou * 100, 1.0, 1.0, 0.0]


# ---------------------------------------------------------------- Waymo's own test cases


def test_waymo_one_shard() -> None:
    """detection_metrics_test.cc DetectionMetricsTest.OneShard."""
    pd = preds([waymo_box(0.9), waymo_box(0.6)], [0.0, 0.5], [V, V])
    gt = truths([waymo_box(1.0)], [V])
    m = measure([pd], [gt], CPP_TEST_CFG)
    assert m.tp[V].tolist() == [1, 1, 0]
    assert m.fp[V].tolist() == [1, 0, 0]
    assert m.fn[V, 1].tolist() == [0, 0, 1]
    np.testing.assert_allclose(m.sum_ha[V], [1.0, 1.0, 0.0], atol=1e-10)
    result = evaluate([pd, pd], [gt, gt], CPP_TEST_CFG)
    assert result["LEVEL_2"]["VEHICLE"]["AP"] == pytest.approx(1.0, abs=1e-6)
    assert result["LEVEL_2"]["VEHICLE"]["APH"] == pytest.approx(1.0, abs=1e-6)


def test_waymo_multiple_types() -> None:
    """detection_metrics_test.cc DetectionMetricsTest.MultipleTypes (one shard = sum over the classes)."""
    pd = preds([waymo_box(x) for x in (0.9, 0.6, 0.6, 0.8)], [0.0, 0.25, 0.5, 0.75], [V, V, P, P])
    gt = truths([waymo_box(1.0), waymo_box(1.0)], [V, P])
    m = measure([pd], [gt], CPP_TEST_CFG)
    assert m.tp.sum(axis=0).tolist() == [2, 1, 0]
    assert m.fp.sum(axis=0).tolist() == [2, 1, 0]
    assert m.fn[:, 1].sum(axis=0).tolist() == [0, 1, 2]
    np.testing.assert_allclose(m.sum_ha.sum(axis=0), [2.0, 1.0, 0.0], atol=1e-10)
    m2 = measure([pd, pd], [gt, gt], CPP_TEST_CFG)
    ap, aph = ap_aph_from_counts(m2.tp.sum(0), m2.fp.sum(0), m2.fn[:, 1].sum(0), m2.sum_ha.sum(0), 0.05)
    assert ap == pytest.approx(0.5, abs=1e-6)
    assert aph == pytest.approx(0.5, abs=1e-6)


@pytest.mark.parametrize(
    ("precisions", "recalls", "delta", "expected"),
    [  # metrics_utils_test.cc MetricsUtilsTest.ComputeMeanAveragePrecision
        ([], [], 0.05, 0.0),
        ([0.1], [0.2], 0.05, 0.2 * 0.1),
        ([0.1, 0.05], [0.2, 1.0], 0.05, 0.05 * 0.8 + 0.1 * 0.2 + (0.1 - 0.05) * 0.5 * 0.05),
        ([0.1, 0.05], [0.2, 1.0], 1.0, 0.2 * 0.1 + 0.5 * (0.1 + 0.05) * 0.8),
        ([0.1, 0.0, 0.05], [0.2, 0.4, 1.0], 0.05, 0.05 * 0.8 + 0.1 * 0.2 + (0.1 - 0.05) * 0.5 * 0.05),
    ],
)
def test_waymo_average_precision(precisions: list, recalls: list, delta: float, expected: float) -> None:
    assert average_precision(precisions, recalls, delta) == pytest.approx(expected, abs=1e-6)


def test_waymo_heading_accuracy() -> None:
    """metrics_utils_test.cc MetricsUtilsTest.ComputeHeadingAccuracy."""
    assert heading_accuracy(-0.1, 0.1) == pytest.approx(1.0 - 0.2 / math.pi, abs=1e-6)
    assert heading_accuracy(-math.pi + 0.1, math.pi - 0.1) == pytest.approx(1.0 - 0.2 / math.pi, abs=1e-6)
    assert heading_accuracy(0.0, math.pi) == pytest.approx(0.0, abs=1e-6)


def test_waymo_hungarian_match() -> None:
    """matcher_test.cc Matcher.HungarianMatch: IoU matrix (predictions x ground truths), threshold 0.5."""
    iou = np.array([[0.60, 0], [1.0, 0.70], [0.65, 0.71], [0, 0]], np.float32)
    match = max_weight_matching(matching_weights(iou, 0.5))
    assert match.tolist() == [-1, 0, 1, -1]
    assert max_weight_matching(np.zeros((0, 2))).tolist() == []


def test_waymo_iou_3d() -> None:
    """iou_test.cc ComputeIoU.Box3d and ComputeIoU.OverlappingBox3d (tolerance there: 1e-5)."""
    b1 = [0.0, 0.0, 0.0, 1.0, 2.0, 2.0, 0.0]
    others = [
        (b1, 1.0),
        ([10.0, 10.0, 0.0, 1.0, 2.0, 2.0, 1.0], 0.0),
        ([0.5, 0.0, 0.0, 1.0, 4.0, 4.0, 0.0], 2.0 / 18.0),
        ([0.5, 0.0, 0.0, 1.0, 4.0, 4.0, math.pi / 2], 2.0 / 18.0),
        ([0.5, 0.0, 0.0, 1.0, 4.0, 2.0, math.pi / 4], 0.24074958176697656),
        ([0.0] * 7, 0.0),
        ([0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0], 0.0),
        ([0.0, 0.0, 0.0, 1.0, 1e-12, 1.0, 0.0], 0.0),
        ([0.0, 0.0, 0.0, 1.0, 1.01e-2, 2.0, 0.0], 0.00505),
    ]
    got = iou_matrix(np.array([b1]), np.array([b for b, _ in others]))[0]
    np.testing.assert_allclose(got, [e for _, e in others], atol=1e-5)
    tiny = np.array([[0.0, 0.0, 0.0, 1.0, 1e-12, 1.0, 0.0]])
    assert iou_matrix(tiny, tiny)[0, 0] == 0.0  # Waymo: a side of at most 1 cm gives IoU 0, even with itself
    a = np.array([[70.970001220703125, 10.090000152587891, -0.37999999523162842, 4.27, 2.02, 1.66, -3.12]])
    b = a.copy()
    b[0, 3] = 4.25
    assert iou_matrix(a, b)[0, 0] == pytest.approx(1 - 0.02 / 4.27, abs=1e-5)


def random_boxes(g: np.random.Generator, n: int) -> np.ndarray:
    """detection_metrics_ops_test.py _GenerateRandomBBoxes: centres in [-1, 1], sizes in [0.1, 1]."""
    return np.concatenate(
        [g.uniform(-1, 1, (n, 3)), g.uniform(0.1, 1, (n, 3)), g.uniform(-np.pi, np.pi, (n, 1))], axis=1
    )


def test_waymo_ops_perfect_and_disjoint_frames() -> None:
    """detection_metrics_ops_test.py testAPBasic: predictions equal to the ground truths give AP = APH = 1;
    the same boxes in other frames give 0."""
    g = np.random.default_rng(0)
    boxes, types, frames = random_boxes(g, 100), g.integers(0, 3, 100), g.integers(0, 10, 100)
    pds = [preds(boxes[frames == f], np.ones((frames == f).sum()), types[frames == f]) for f in range(10)]
    gts = [truths(boxes[frames == f], types[frames == f]) for f in range(10)]
    same = evaluate(pds, gts, OPS_TEST_CFG)
    for level, name in itertools.product(("LEVEL_1", "LEVEL_2"), ("VEHICLE", "PEDESTRIAN", "CYCLIST")):
        assert same[level][name] == pytest.approx({"AP": 1.0, "APH": 1.0}, abs=1e-5)
    empty_p, empty_g = preds([], [], []), truths([], [])
    shifted = evaluate(pds + [empty_p] * 10, [empty_g] * 10 + gts, OPS_TEST_CFG)
    assert shifted["LEVEL_2"]["mean"] == pytest.approx({"AP": 0.0, "APH": 0.0}, abs=1e-5)


def test_waymo_ops_all_zero_and_empty() -> None:
    """detection_metrics_ops_test.py testAllZeroValue (zero boxes and scores: every prediction is a false
    positive at cut-off 0 and gone from 0.1 on; AP 0) and testEmpty (nothing at all: AP 0)."""
    g = np.random.default_rng(1)
    pd = preds(np.zeros((20, 7)), np.zeros(20), g.integers(0, 3, 20))
    gt = truths(np.zeros((100, 7)), g.integers(0, 3, 100))
    m = measure([pd], [gt], OPS_TEST_CFG)
    assert (m.tp.sum(0)[0], m.fp.sum(0)[0], m.fn[:, 1].sum(0)[0]) == (0, 20, 100)
    assert (m.tp.sum(0)[1], m.fp.sum(0)[1], m.fn[:, 1].sum(0)[1]) == (0, 0, 100)
    assert evaluate([pd], [gt], OPS_TEST_CFG)["LEVEL_2"]["mean"] == {"AP": 0.0, "APH": 0.0}
    assert evaluate([preds([], [], [])] * 10, [truths([], [])] * 10)["LEVEL_2"]["mean"] == {
        "AP": 0.0,
        "APH": 0.0,
    }


# ---------------------------------------------------------------- behaviour


def vehicle(x: float, y: float = 0.0, yaw: float = 0.0, length: float = 4.0) -> list[float]:
    return [x, y, 0.0, length, 2.0, 1.5, yaw]


def test_perfect_predictions() -> None:
    g = np.random.default_rng(2)
    boxes = [vehicle(10 * i, yaw=float(g.uniform(-3, 3))) for i in range(6)]
    labels = [V, V, P, P, C, C]
    gt = truths(boxes, labels, levels=[LEVEL_1, LEVEL_2] * 3)
    result = evaluate([preds(boxes, g.uniform(0.1, 1, 6), labels)], [gt])
    for level in ("LEVEL_1", "LEVEL_2"):
        for name in ("VEHICLE", "PEDESTRIAN", "CYCLIST", "mean"):
            assert result[level][name] == pytest.approx({"AP": 1.0, "APH": 1.0}, abs=1e-6)


def test_flipped_heading_keeps_ap_and_zeroes_aph() -> None:
    gt = truths([vehicle(10, yaw=0.3), vehicle(-10, yaw=-2.0)], [V, V])
    pd = preds([vehicle(10, yaw=0.3 + math.pi), vehicle(-10, yaw=-2.0 - math.pi)], [0.9, 0.8], [V, V])
    result = evaluate([pd], [gt])["LEVEL_1"]["VEHICLE"]
    assert result["AP"] == pytest.approx(1.0, abs=1e-6)
    assert result["APH"] == pytest.approx(0.0, abs=1e-6)
    square = truths([vehicle(10, yaw=0.3, length=2.0)], [V])  # 2 m x 2 m: a quarter turn keeps IoU 1
    quarter = preds([vehicle(10, yaw=0.3 + math.pi / 2, length=2.0)], [0.9], [V])  # heading accuracy 0.5
    assert evaluate([quarter], [square])["LEVEL_1"]["VEHICLE"] == pytest.approx(
        {"AP": 1.0, "APH": 0.5}, abs=1e-6
    )


@pytest.mark.parametrize(("label", "threshold"), [(V, 0.7), (P, 0.5), (C, 0.5)])
def test_iou_just_below_threshold_is_a_false_positive(label: int, threshold: float) -> None:
    gt = truths([vehicle(0)], [label])
    for ratio, expected in ((threshold - 0.002, 0.0), (threshold + 0.002, 1.0)):
        pd = preds([vehicle(0, length=4.0 * ratio)], [0.9], [label])  # inside the ground truth: IoU = ratio
        assert iou_matrix(pd.boxes, gt.boxes)[0, 0] == pytest.approx(ratio, abs=1e-6)
        m = measure([pd], [gt], MetricsConfig())
        assert (m.tp[label, 0], m.fp[label, 0]) == (int(expected), 1 - int(expected))
        name = ("VEHICLE", "PEDESTRIAN", "CYCLIST")[label]
        assert evaluate([pd], [gt])["LEVEL_2"][name]["AP"] == pytest.approx(expected, abs=1e-6)


def test_levels() -> None:
    """LEVEL_2 counts every box; LEVEL_1 misses only LEVEL_1 boxes, but (as Waymo's IsTP) a prediction
    matched to a LEVEL_2 box is a true positive at LEVEL_1 too."""
    gt = truths([vehicle(10), vehicle(20), vehicle(30)], [V, V, V], levels=[LEVEL_1, LEVEL_2, LEVEL_2])
    only_l1 = evaluate([preds([vehicle(10)], [0.9], [V])], [gt])
    assert only_l1["LEVEL_1"]["VEHICLE"]["AP"] == pytest.approx(1.0, abs=1e-6)
    assert only_l1["LEVEL_2"]["VEHICLE"]["AP"] == pytest.approx(1 / 3, abs=1e-6)
    only_l2 = evaluate([preds([vehicle(20)], [0.9], [V])], [gt])
    assert only_l2["LEVEL_1"]["VEHICLE"]["AP"] == pytest.approx(0.5, abs=1e-6)  # 1 TP, 1 FN (the L1 box)
    assert only_l2["LEVEL_2"]["VEHICLE"]["AP"] == pytest.approx(1 / 3, abs=1e-6)
    m = measure([preds([vehicle(20)], [0.9], [V])], [gt], MetricsConfig())
    assert (m.tp[V, 0], m.fn[V, 0, 0], m.fn[V, 1, 0]) == (1, 1, 2)
    assert m.num_gt[V].tolist() == [1, 3]


def test_mean_skips_classes_without_ground_truth() -> None:
    """Pedestrians: one LEVEL_2 box only, so none at LEVEL_1 (its AP there is Waymo's 1.0 from the matched
    LEVEL_2 box) and the LEVEL_1 mean is over vehicles; cyclists: none at all, AP 0, not in the means."""
    gt = truths([vehicle(10), vehicle(20), vehicle(40)], [V, V, P], levels=[LEVEL_1, LEVEL_1, LEVEL_2])
    result = evaluate([preds([vehicle(10), vehicle(40)], [0.9, 0.8], [V, P])], [gt])
    assert result["LEVEL_1"]["VEHICLE"]["AP"] == pytest.approx(0.5, abs=1e-6)
    assert result["LEVEL_1"]["PEDESTRIAN"]["AP"] == pytest.approx(1.0, abs=1e-6)
    assert result["LEVEL_1"]["CYCLIST"] == {"AP": 0.0, "APH": 0.0}
    assert result["LEVEL_1"]["mean"]["AP"] == pytest.approx(0.5, abs=1e-6)
    assert result["LEVEL_2"]["mean"]["AP"] == pytest.approx(0.75, abs=1e-6)
    counts = count_ground_truths([gt])
    assert counts["LEVEL_1"] == {"VEHICLE": 2, "PEDESTRIAN": 0, "CYCLIST": 0}
    assert counts["LEVEL_2"] == {"VEHICLE": 2, "PEDESTRIAN": 1, "CYCLIST": 0}


def test_zero_point_ground_truth_is_dropped() -> None:
    gt = truths([vehicle(10), vehicle(30)], [V, V], points=[40, 0], levels=[LEVEL_1, LEVEL_2])
    missed_empty = evaluate([preds([vehicle(10)], [0.9], [V])], [gt])
    assert missed_empty["LEVEL_2"]["VEHICLE"]["AP"] == pytest.approx(1.0, abs=1e-6)  # not a false negative
    # a prediction on the empty box is an ordinary false positive: ranked first, it halves the AP
    on_empty = evaluate([preds([vehicle(30), vehicle(10)], [0.9, 0.5], [V, V])], [gt])
    assert on_empty["LEVEL_2"]["VEHICLE"]["AP"] == pytest.approx(0.5, abs=1e-6)
    assert count_ground_truths([gt])["LEVEL_2"]["VEHICLE"] == 1


def test_crop_to_fov() -> None:
    boxes = [vehicle(10, 0), vehicle(0, 10), vehicle(0, -10), vehicle(-10, 0.01), vehicle(10, 10)]
    pd = preds(boxes, [0.9, 0.8, 0.7, 0.6, 0.5], [V, P, C, V, P])
    front = crop_to_fov(pd, (-math.pi / 4, math.pi / 4))  # [lo, hi): azimuth exactly pi/4 is out
    assert front.boxes[:, 0].tolist() == [10.0] and front.scores.tolist() == pytest.approx([0.9])
    assert front.labels.tolist() == [V]
    assert crop_to_fov(pd, (-math.pi / 2, math.pi / 2)).labels.tolist() == [V, C, P]
    behind = crop_to_fov(pd, (3 * math.pi / 4, -3 * math.pi / 4))  # lo > hi: wraps through +-pi
    assert behind.boxes[:, 0].tolist() == [-10.0]
    assert crop_to_fov(pd, None) is pd


def test_result_shape_and_table() -> None:
    gt = truths([vehicle(10), vehicle(20)], [V, C])
    result = evaluate([preds([vehicle(10)], [0.9], [V])], [gt])
    assert list(result) == ["LEVEL_1", "LEVEL_2"]
    for level in result.values():
        assert list(level) == ["VEHICLE", "PEDESTRIAN", "CYCLIST", "mean"]
        for row in level.values():
            assert list(row) == ["AP", "APH"] and all(type(v) is float and 0 <= v <= 1 for v in row.values())
    assert json.loads(json.dumps(result)) == result
    table = format_table(result, count_ground_truths([gt]))
    assert len(table.splitlines()) == 2 + 2 * 4
    assert "LEVEL_2  CYCLIST      0.0000  0.0000       1" in table
    assert "GT" not in format_table(result)


def test_config_validation_and_defaults() -> None:
    cfg = MetricsConfig()
    assert cfg.iou_thresholds == (0.7, 0.5, 0.5) and len(WAYMO_SCORE_CUTOFFS) == 101
    assert WAYMO_SCORE_CUTOFFS[0] == 0.0 and WAYMO_SCORE_CUTOFFS[-1] == 1.0
    assert WAYMO_SCORE_CUTOFFS[7] == float(np.float32(0.07))
    with pytest.raises(ValueError):
        MetricsConfig(iou_thresholds=(0.7, 0.5))
    with pytest.raises(ValueError):
        MetricsConfig(iou_thresholds=(0.0, 0.5, 0.5))
    with pytest.raises(ValueError):
        evaluate([preds([], [], [])], [])


# ---------------------------------------------------------------- matching


def brute_force_best(w: np.ndarray) -> float:
    """Largest total weight of any matching of the rows of w (N, M) to distinct columns."""
    n, m = w.shape
    if n > m:
        return brute_force_best(w.T)
    return max(
        (sum(w[i, j] for i, j in enumerate(cols)) for cols in itertools.permutations(range(m), n)), default=0
    )


def test_assignment_matches_brute_force() -> None:
    g = np.random.default_rng(3)
    for _ in range(400):
        n, m = (int(x) for x in g.integers(0, 6, 2))
        w = g.integers(0, 6, (n, m)) * (g.random((n, m)) < 0.6)  # integer weights: many ties and zeros
        if g.random() < 0.5:
            w = g.random((n, m)) * (g.random((n, m)) < 0.5)
        match = max_weight_matching(w)
        assert match.shape == (n,)
        hit = match >= 0
        assert len(set(match[hit].tolist())) == int(hit.sum())  # distinct columns
        assert np.all(w[hit, match[hit]] > 0)  # weight-0 pairs are reported unmatched
        assert w[hit, match[hit]].sum() == pytest.approx(brute_force_best(w), abs=1e-9)


def test_assignment_rejects_bad_weights() -> None:
    with pytest.raises(ValueError):
        max_weight_matching(np.array([[1.0, -1.0]]))
    with pytest.raises(ValueError):
        max_weight_matching(np.zeros(3))


def direct_counts(pd: Predictions, gt: GroundTruth, cfg: MetricsConfig) -> tuple[np.ndarray, ...]:
    """The same counts as `measure`, matching the whole class subset afresh at every cut-off, as Waymo's
    ComputeDetectionMeasurementsPerBreakdownShard does."""
    gt = gt.select(gt.num_points > 0)
    n_cut = len(cfg.score_cutoffs)
    tp, fp, ha = np.zeros((3, n_cut), np.int64), np.zeros((3, n_cut), np.int64), np.zeros((3, n_cut))
    fn = np.zeros((3, 2, n_cut), np.int64)
    for c in range(3):
        pi, gi = np.nonzero(pd.labels == c)[0], np.nonzero(gt.labels == c)[0]
        weight = matching_weights(iou_matrix(pd.boxes[pi], gt.boxes[gi]), cfg.iou_thresholds[c])
        for k, cut in enumerate(np.float32(cfg.score_cutoffs)):
            keep = pd.scores[pi] >= cut
            match = max_weight_matching(weight[keep])
            hit = match >= 0
            tp[c, k], fp[c, k] = hit.sum(), (~hit).sum()
            ha[c, k] = heading_accuracy(pd.boxes[pi[keep][hit], 6], gt.boxes[gi[match[hit]], 6]).sum()
            free = np.ones(len(gi), bool)
            free[match[hit]] = False
            fn[c, :, k] = [(free & (gt.difficulty[gi] <= lv)).sum() for lv in (LEVEL_1, LEVEL_2)]
    return tp, fp, fn, ha


def random_scene(seed: int, scans: int, max_gt: int, extra: int, spread: float, jitter: float):
    """Scans of random boxes of the three classes; predictions are noisy copies (some turned around, some
    of the wrong class) plus random boxes; scores partly rounded to 0.01 (ties, values on the cut-offs);
    about 10 % of the boxes have no point. -> (list[Predictions], list[GroundTruth])."""
    g = np.random.default_rng(seed)
    size = np.array([[4.5, 2.0, 1.6], [0.8, 0.8, 1.7], [1.8, 0.7, 1.7]])  # (3, 3) l, w, h per class
    all_p, all_g = [], []
    for _ in range(scans):
        m = int(g.integers(0, max_gt + 1))
        cls = g.integers(0, 3, m)
        centre = g.uniform(-spread, spread, (m, 3)) * [1, 1, 0.05]
        gt = np.concatenate(
            [centre, size[cls] * g.uniform(0.8, 1.2, (m, 3)), g.uniform(-np.pi, np.pi, (m, 1))], 1
        )
        points = g.integers(0, 30, m) * (g.random(m) > 0.1)
        level = np.where((points <= 5) | (g.random(m) < 0.1), LEVEL_2, LEVEL_1)
        copies = g.integers(0, 4, m)  # (m,) noisy predictions per box
        src = np.repeat(np.arange(m), copies)
        pb = gt[src] + g.normal(0, jitter, (len(src), 7)) * [1, 1, 0.3, 0, 0, 0, 0]
        pb[:, 3:6] *= np.exp(g.normal(0, jitter / 2, (len(src), 3)))
        pb[:, 6] += np.where(g.random(len(src)) < 0.15, np.pi, g.normal(0, 0.3, len(src)))
        plabel = np.where(g.random(len(src)) < 0.05, g.integers(0, 3, len(src)), cls[src])
        k = int(g.integers(0, extra + 1))
        junk = np.concatenate([g.uniform(-spread, spread, (k, 2)), np.zeros((k, 1)), np.tile(size[0], (k, 1)),
                               g.uniform(-3, 3, (k, 1))], 1)  # fmt: skip
        scores = g.random(len(src) + k).astype(np.float32)
        coarse = g.random(len(scores)) < 0.3
        scores[coarse] = np.round(scores[coarse], 2)
        all_p.append(preds(np.concatenate([pb, junk]), scores, np.concatenate([plabel, g.integers(0, 3, k)])))
        all_g.append(truths(gt, cls, points.tolist(), level.tolist()))
    return all_p, all_g


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_component_shortcut_equals_direct_matching(seed: int) -> None:
    cfg = MetricsConfig(score_cutoffs=tuple(float(np.float32(i / 20)) for i in range(21)))
    for pd, gt in zip(*random_scene(seed, 6, 25, 8, 8.0, 0.1), strict=True):
        m = measure([pd], [gt], cfg)
        tp, fp, fn, ha = direct_counts(pd, gt, cfg)
        np.testing.assert_array_equal(m.tp, tp)
        np.testing.assert_array_equal(m.fp, fp)
        np.testing.assert_array_equal(m.fn, fn)
        np.testing.assert_allclose(m.sum_ha, ha, atol=1e-9)


# ---------------------------------------------------------------- agreement with the official implementation

# Waymo's official `detection_metrics` op (waymo-open-dataset-tf-2-12-0 1.6.7, TensorFlow 2.13) on the scenes
# of random_scene(seed, scans, max_gt, extra, spread, jitter), with the leaderboard config (OBJECT_TYPE,
# LEVEL_1 + LEVEL_2, Hungarian, IoU 0.7 / 0.5 / 0.5, cut-offs 0:0.01:1) and boxes without points removed as in
# compute_detection_metrics_main.cc. Per scene: (AP, APH) at LEVEL_1 and at LEVEL_2 for VEHICLE, PEDESTRIAN,
# CYCLIST (float32 outputs), then per class (TP, FP, FN at LEVEL_1, FN at LEVEL_2) summed over the cut-offs.
# fmt: off
OFFICIAL = {
    (10, 30, 25, 6, 15.0, 0.05): (
        [(0.234584, 0.1775717), (0.5374636, 0.413695), (0.4736357, 0.3600672)],
        [(0.2090262, 0.1572604), (0.4923878, 0.3771949), (0.4213369, 0.3202263)],
        [(3932, 7856, 6707, 8592), (6334, 6575, 4512, 5988), (4678, 4913, 5631, 7543)],
    ),
    (11, 20, 30, 10, 6.0, 0.1): (
        [(0.2916046, 0.240827), (0.4847745, 0.4352951), (0.4332184, 0.3514109)],
        [(0.266538, 0.2183879), (0.4243159, 0.3797213), (0.3979733, 0.3234631)],
        [(2742, 5447, 4038, 4934), (3502, 4108, 3116, 4275), (3106, 4276, 3086, 4166)],
    ),
    (12, 40, 20, 3, 30.0, 0.02): (
        [(0.4666179, 0.380866), (0.5138148, 0.3783089), (0.457829, 0.3780226)],
        [(0.4092541, 0.3312364), (0.4728301, 0.3497505), (0.4356185, 0.3585915)],
        [(4710, 5612, 4875, 6804), (5585, 5634, 5012, 6131), (5749, 5896, 5629, 6876)],
    ),
}
# fmt: on


@pytest.mark.parametrize("scene", list(OFFICIAL))
def test_agrees_with_official_implementation(scene: tuple) -> None:
    pds, gts = random_scene(*scene)
    m = measure(pds, gts, MetricsConfig())
    result = evaluate(pds, gts)
    ap_l1, ap_l2, counts = OFFICIAL[scene]
    for c, name in enumerate(("VEHICLE", "PEDESTRIAN", "CYCLIST")):
        assert (m.tp[c].sum(), m.fp[c].sum(), m.fn[c, 0].sum(), m.fn[c, 1].sum()) == counts[c]
        for level, aps in (("LEVEL_1", ap_l1), ("LEVEL_2", ap_l2)):
            assert result[level][name]["AP"] == pytest.approx(aps[c][0], abs=3e-7)
            assert result[level][name]["APH"] == pytest.approx(aps[c][1], abs=3e-7)
