"""Run a model over labelled scans the way the server streams them, and score it (`phim eval`).

Each scan is cut into the model's sectors (sector 0 first, as the simulator's sweep), encoded as one stream
(exactly what streaming the sectors one by one computes), and predicted at every buffer fill level:
prediction b sees sector b and the b sectors before it. Prediction S - 1 covers the whole turn: that is the
full-turn prediction. A partial prediction is scored two ways: against the ground truth of what it has
seen (boxes, predicted and true, whose centre lies in its sectors: `by_buffered_sectors`), and against the
whole turn's ground truth (`by_buffered_sectors_global`, the paper's Figure 8: what a client knows of the
whole scene at that moment).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from lidar.readers import feature_columns, sector_of_xy
from lidar.types import GroundTruth, LabeledScan, Predictions
from model.config import CLASS_NAMES, Precision
from model.detector import PHiM
from model.ego import drop_ego_boxes, drop_ego_points
from model.eval.metrics import MetricsConfig, crop_to_fov, evaluate
from model.layers.head import decode
from model.layers.phim_block import StreamLayout
from model.layers.refine import refine
from model.precision import autocast, check_precision


@dataclass(frozen=True)
class ScanResult:
    name: str
    predictions: list[Predictions]  # per fill level b = 0 .. S-1: the new sector and b buffered ones
    truths: list[GroundTruth]  # the ground truth each prediction is scored against


def _select(p: Predictions, keep: np.ndarray) -> Predictions:
    return Predictions(p.boxes[keep], p.scores[keep], p.labels[keep])


def truths_by_fill(scan: LabeledScan, sectors: int) -> list[GroundTruth]:
    """The ground truth prediction b (b buffered sectors) is scored against: boxes centred in the first b + 1
    sectors of the sweep (sector 0 first, in the scan's spin order)."""
    order = scan.spin.order(sectors)
    gt_sector = sector_of_xy(scan.gt.boxes[:, 0], scan.gt.boxes[:, 1], sectors)  # (M,)
    return [scan.gt.select(np.isin(gt_sector, order[: b + 1])) for b in range(sectors)]


def crop_prediction(p: Predictions, b: int, scan: LabeledScan, sectors: int) -> Predictions:
    """Prediction b keeps the boxes centred in the sweep's first b + 1 sectors (all of them for the full turn)
    and in the scan's `label_fov`."""
    p = crop_to_fov(p, scan.label_fov)
    if b < sectors - 1:
        seen = scan.spin.order(sectors)[: b + 1]
        p = _select(p, np.isin(sector_of_xy(p.boxes[:, 0], p.boxes[:, 1], sectors), seen))
    return p


def scan_sectors(scan: LabeledScan, point_features: int, sectors: int) -> list[torch.Tensor]:
    """The scan's points cut into `sectors` azimuth sectors (N_k, C), in sweep order: sector 0 first, then
    by the scan's spin (as a sensor starting its turn in sector 0 sends them)."""
    points = feature_columns(scan, point_features)  # (N, C)
    sector = sector_of_xy(points[:, 0], points[:, 1], sectors)  # (N,)
    return [torch.from_numpy(np.ascontiguousarray(points[sector == k])) for k in scan.spin.order(sectors)]


@torch.inference_mode()
def predict_scan(model: PHiM, scan: LabeledScan, precision: Precision = Precision.FP32) -> ScanResult:
    """The predictions at every fill level; the forward runs in `precision`, the decoding in float32. As the
    server streams: without the ego vehicle's points and boxes (`cfg.ego`), every other box kept."""
    cfg = model.cfg
    n = cfg.sectors_per_turn
    sectors = drop_ego_points(scan_sectors(scan, cfg.vfe.point_features, n), cfg.ego)
    sectors = [s.to(model.device) for s in sectors]
    with autocast(precision, model.device):
        enc = model.encode(sectors, StreamLayout.single_stream(n, model.device), model.init_states(1))
        maps = model.predict([enc.sectors[: b + 1] for b in range(n)])  # float32 maps
    dets = decode(maps, cfg.head, cfg.bev, cfg.every_cell)
    if model.refiner is not None:  # prediction b covers sectors 0 .. b
        dets = [refine(model.refiner, d, torch.cat(sectors[: b + 1])) for b, d in enumerate(dets)]
    dets = [drop_ego_boxes(d, cfg.ego) for d in dets]
    preds = [
        crop_prediction(
            Predictions(d.boxes.cpu().numpy(), d.scores.cpu().numpy(), d.labels.cpu().numpy()), b, scan, n
        )
        for b, d in enumerate(dets)
    ]
    return ScanResult(scan.name, preds, truths_by_fill(scan, n))


def rescore_scan(scan: LabeledScan, by_fill: list[Predictions]) -> ScanResult:
    """Predictions read back from a file (one per fill level) -> the ScanResult `score` takes."""
    n = len(by_fill)
    preds = [crop_prediction(p, b, scan, n) for b, p in enumerate(by_fill)]
    return ScanResult(scan.name, preds, truths_by_fill(scan, n))


def _near(boxes: np.ndarray, max_range: float) -> np.ndarray:
    return np.hypot(boxes[:, 0], boxes[:, 1]) <= max_range  # (K,) box centres within max_range (BEV)


def within_range(r: ScanResult, max_range: float | None) -> ScanResult:
    """The result with only the predictions and ground truths whose box centre lies within `max_range`
    metres of the sensor (BEV): every model is scored on the same region, whatever its own range."""
    if max_range is None:
        return r
    preds = [_select(p, _near(p.boxes, max_range)) for p in r.predictions]
    return ScanResult(r.name, preds, [t.select(_near(t.boxes, max_range)) for t in r.truths])


def score(results: Sequence[ScanResult], cfg: MetricsConfig | None = None) -> dict:
    """-> the stable JSON shape: full-turn LEVEL_1 / LEVEL_2, and the same per buffered-sector count, scored
    on the sectors seen (`by_buffered_sectors`) and on the whole turn (`by_buffered_sectors_global`)."""
    cfg = cfg or MetricsConfig()
    n = len(results[0].predictions)
    preds = [[r.predictions[b] for r in results] for b in range(n)]
    seen = {str(b): evaluate(preds[b], [r.truths[b] for r in results], cfg) for b in range(n)}
    whole = [r.truths[-1] for r in results]
    # the full turn has seen everything: its score is the same both ways, so it is computed once
    scene = {str(b): evaluate(preds[b], whole, cfg) for b in range(n - 1)} | {str(n - 1): seen[str(n - 1)]}
    full = seen[str(n - 1)]
    return {
        "LEVEL_1": full["LEVEL_1"],
        "LEVEL_2": full["LEVEL_2"],
        "by_buffered_sectors": seen,
        "by_buffered_sectors_global": scene,
    }


def vehicle_ap(results: Sequence[ScanResult], iou: float) -> float:
    """LEVEL_1 vehicle AP of the full-turn predictions at 3D IoU `iou` (`score` gives Waymo's 0.7)."""
    preds, truths = [r.predictions[-1] for r in results], [r.truths[-1] for r in results]
    cfg = MetricsConfig(iou_thresholds=(iou, *MetricsConfig().iou_thresholds[1:]))
    return evaluate(preds, truths, cfg)["LEVEL_1"][CLASS_NAMES[0]]["AP"]


def run_eval(
    model: PHiM,
    scans: Sequence[int] | range,
    source: Callable[[int], LabeledScan],
    on_scan: Callable[[LabeledScan, ScanResult], None] | None = None,
    precision: Precision = Precision.FP32,
) -> list[ScanResult]:
    """Predict scans source(i) for i in `scans` in `precision`; `on_scan` sees each scan and its result
    (pictures)."""
    check_precision(precision, model.device)
    model.eval()
    out = []
    for i in scans:
        scan = source(i)
        r = predict_scan(model, scan, precision)
        out.append(r)
        if on_scan is not None:
            on_scan(scan, r)
    return out


def run_rescore(
    by_name: dict[str, list[Predictions]],
    scans: Sequence[int] | range,
    source: Callable[[int], LabeledScan],
    on_scan: Callable[[LabeledScan, ScanResult], None] | None = None,
) -> list[ScanResult]:
    """Score stored predictions (scan name -> per fill level) against scans source(i) for i in `scans`."""
    out = []
    for i in scans:
        scan = source(i)
        if scan.name not in by_name:
            raise KeyError(f"the predictions file has no scan {scan.name!r} (data scan {i})")
        r = rescore_scan(scan, by_name[scan.name])
        out.append(r)
        if on_scan is not None:
            on_scan(scan, r)
    return out
