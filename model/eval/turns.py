"""Multi-turn evaluation (`phim eval --turns N`): several turns streamed as one stream, sector by sector,
through the serving path (`model.stream.StreamingDetector`), each turn's full-turn prediction scored on its
own. Under the config's `history` policy (docs/model.md, "Streaming history") turn N should score as turn 1.

A scan's N turns are the same scan sent N times: a vehicle standing still (the simulator has no drive of
consecutive turns through one scene).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

from lidar.types import LabeledScan, Predictions
from model.config import Precision
from model.detector import PHiM
from model.eval.metrics import MetricsConfig, evaluate
from model.eval.runner import ScanResult, crop_prediction, scan_sectors, truths_by_fill
from model.stream import StreamingDetector


def stream_turns(det: StreamingDetector, scan: LabeledScan, turns: int) -> list[ScanResult]:
    """The scan's `turns` turns as one stream, in sweep order each turn -> per turn the ScanResult of its
    last sector (the full-turn prediction: it sees the new sector and the S - 1 buffered ones)."""
    n = det.cfg.sectors_per_turn
    sectors = scan_sectors(scan, det.cfg.vfe.point_features, n)
    state, out = det.new_state(), []
    for _ in range(turns):
        for s in sectors:
            (r,), (state,) = det.step([s], [state])
        d = r.detections
        pred = Predictions(d.boxes.cpu().numpy(), d.scores.cpu().numpy(), d.labels.cpu().numpy())
        out.append(
            ScanResult(scan.name, [crop_prediction(pred, n - 1, scan, n)], truths_by_fill(scan, n)[-1:])
        )
    return out


def run_turns(
    model: PHiM,
    scans: Sequence[int] | range,
    source: Callable[[int], LabeledScan],
    turns: int,
    precision: Precision = Precision.FP32,
) -> list[list[ScanResult]]:
    """-> per turn (1 .. turns) the results over `scans`; batch norms unfolded, as `run_eval` runs."""
    det = StreamingDetector(model, fold_bn=False, precision=precision)
    per_scan = [stream_turns(det, source(i), turns) for i in scans]
    return [[r[t] for r in per_scan] for t in range(turns)]


def score_turns(by_turn: Sequence[Sequence[ScanResult]], cfg: MetricsConfig | None = None) -> dict:
    """-> {"1": {"LEVEL_1": ..., "LEVEL_2": ...}, "2": ...}: each turn's full-turn predictions scored."""
    cfg = cfg or MetricsConfig()
    return {
        str(t + 1): evaluate([r.predictions[-1] for r in rs], [r.truths[-1] for r in rs], cfg)
        for t, rs in enumerate(by_turn)
    }
