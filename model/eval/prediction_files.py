"""Predictions in the native format (`.npz`, no pickles), so other tools can re-score them.

Arrays (K boxes over all scans and fill levels):
    format            str ()       "phim.predictions"
    version           int64 ()     1
    class_names       str (C,)     label i is class_names[i]
    scan_names        str (S,)     scans in evaluation order
    scan_index        int64 (K,)   the scan each box belongs to (index into scan_names)
    buffered_sectors  int64 (K,)   the prediction it belongs to: 0 .. sectors_per_turn - 1 buffered sectors;
                                   the largest value is the full-turn prediction
    boxes             float32 (K, 7) x, y, z (centre), l, w, h, yaw; sensor frame (x forward, y left, z up)
    scores            float32 (K,)
    labels            int64 (K,)
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from lidar.types import Predictions
from model.config import CLASS_NAMES
from model.eval.runner import ScanResult

FORMAT = "phim.predictions"
VERSION = 1


def write_predictions(path: Path, results: Sequence[ScanResult]) -> None:
    scan_index, buffered, boxes, scores, labels = [], [], [], [], []
    for s, r in enumerate(results):
        for b, p in enumerate(r.predictions):
            scan_index.append(np.full(len(p), s, np.int64))
            buffered.append(np.full(len(p), b, np.int64))
            boxes.append(p.boxes.reshape(-1, 7))
            scores.append(p.scores)
            labels.append(p.labels)
    np.savez_compressed(
        path,
        format=np.array(FORMAT),
        version=np.array(VERSION, np.int64),
        class_names=np.array(CLASS_NAMES, np.str_),
        scan_names=np.array([r.name for r in results], np.str_),
        scan_index=np.concatenate(scan_index) if scan_index else np.zeros(0, np.int64),
        buffered_sectors=np.concatenate(buffered) if buffered else np.zeros(0, np.int64),
        boxes=np.concatenate(boxes).astype(np.float32) if boxes else np.zeros((0, 7), np.float32),
        scores=np.concatenate(scores).astype(np.float32) if scores else np.zeros(0, np.float32),
        labels=np.concatenate(labels).astype(np.int64) if labels else np.zeros(0, np.int64),
    )


def read_predictions_by_fill(path: Path) -> dict[str, list[Predictions]]:
    """-> scan name -> its Predictions per fill level (index b: b buffered sectors; the last: full turn)."""
    with np.load(path, allow_pickle=False) as f:
        if "format" not in f.files or str(f["format"]) != FORMAT or int(f["version"]) != VERSION:
            raise ValueError(f"{path}: not a {FORMAT} v{VERSION} file")
        arrays = {k: f[k] for k in f.files}
    level = arrays["buffered_sectors"]
    fills = int(level.max(initial=0)) + 1
    out = {}
    for s, name in enumerate(arrays["scan_names"].tolist()):
        mine = arrays["scan_index"] == s
        out[str(name)] = [
            Predictions(arrays["boxes"][sel], arrays["scores"][sel], arrays["labels"][sel])
            for sel in (mine & (level == b) for b in range(fills))
        ]
    return out


def read_predictions(path: Path, buffered_sectors: int | None = None) -> dict[str, Predictions]:
    """-> scan name -> its Predictions at `buffered_sectors` (default: the full turn, the largest value)."""
    return {
        k: v[-1 if buffered_sectors is None else buffered_sectors]
        for k, v in read_predictions_by_fill(path).items()
    }
