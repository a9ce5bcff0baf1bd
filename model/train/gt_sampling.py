"""Ground-truth sampling (copy-paste, SECOND / OpenPCDet's `gt_sampling`): labelled objects cut with their
points from other scans of the training data and pasted into a training scan at the place they were seen
(so their density and the side the sensor sees stay true), each checked against every box already there.

The bank is built once per data-loader process from `bank_scans` scans of a stream the training never
reads. A pasted object's footprint is cleared of the scan's own points first. Training pastes only before
`fade` of its steps: the last phase sees unaltered scans (the paper's "faded" recipe).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from lidar.types import GroundTruth, LabeledScan, points_in_boxes


@dataclass(frozen=True)
class GTSamplingConfig:
    per_class: tuple[int, ...] = (4, 6, 6)  # objects tried per scan, per class of CLASS_NAMES
    min_points: int = 5  # objects with fewer points are not banked
    bank_scans: int = 100  # scans the bank is cut from
    fade: float = 0.8  # paste only in the first `fade` of the training steps


@dataclass(frozen=True)
class ObjectBank:
    boxes: np.ndarray  # (K, 7) float32 where each object was seen (sensor frame)
    labels: np.ndarray  # (K,) int64
    points: np.ndarray  # (P, C) float32 every object's points, object after object
    offsets: np.ndarray  # (K + 1,) int64: object k's points are points[offsets[k]:offsets[k + 1]]
    fields: tuple[str, ...]

    def __len__(self) -> int:
        return int(self.labels.shape[0])

    def object_points(self, k: int) -> np.ndarray:
        return self.points[self.offsets[k] : self.offsets[k + 1]]


def build_bank(scan_at: Callable[[int], LabeledScan], scans: int, min_points: int) -> ObjectBank:
    """Cut every labelled object with at least `min_points` points out of scans 0 .. scans - 1."""
    boxes, labels, pieces, fields = [], [], [], None
    for i in range(scans):
        scan = scan_at(i)
        fields = fields or scan.fields
        if scan.fields != fields:
            raise ValueError(f"{scan.name}: fields {scan.fields}; the bank's scans have {fields}")
        inside = points_in_boxes(scan.points[:, :3], scan.gt.boxes)  # (N, M)
        for m in np.flatnonzero(scan.gt.num_points >= min_points):
            boxes.append(scan.gt.boxes[m])
            labels.append(scan.gt.labels[m])
            pieces.append(scan.points[inside[:, m]])
    counts = [len(p) for p in pieces]
    return ObjectBank(
        np.asarray(boxes, np.float32).reshape(-1, 7),
        np.asarray(labels, np.int64),
        np.concatenate(pieces) if pieces else np.zeros((0, len(fields or ())), np.float32),
        np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
        tuple(fields or ()),
    )


def _radius(boxes: np.ndarray) -> np.ndarray:
    return 0.5 * np.hypot(boxes[:, 3], boxes[:, 4])  # (M,) half the footprint's diagonal


def _free(box: np.ndarray, taken: np.ndarray) -> bool:
    """Whether `box`'s footprint circle misses every taken box's (a conservative collision check)."""
    if len(taken) == 0:
        return True
    gap = np.hypot(taken[:, 0] - box[0], taken[:, 1] - box[1]) - _radius(taken) - _radius(box[None])[0]
    return bool((gap > 0.1).all())


def paste_objects(
    scan: LabeledScan, bank: ObjectBank, rng: np.random.Generator, cfg: GTSamplingConfig
) -> LabeledScan:
    """The scan with up to `cfg.per_class` bank objects per class pasted where no box is (points in their
    footprints removed first); labels and point counts follow."""
    if scan.fields != bank.fields:
        raise ValueError(f"{scan.name}: fields {scan.fields}; the object bank's are {bank.fields}")
    taken, picked = scan.gt.boxes.astype(np.float32), []
    for label, tries in enumerate(cfg.per_class):
        pool = np.flatnonzero(bank.labels == label)
        for k in rng.choice(pool, min(tries, len(pool)), replace=False) if len(pool) else ():
            if _free(bank.boxes[k], taken):
                taken = np.concatenate([taken, bank.boxes[k][None]])
                picked.append(int(k))
    if not picked:
        return scan
    new = bank.boxes[picked]  # (K, 7)
    cleared = scan.points[~points_in_boxes(scan.points[:, :3], new).any(axis=1)]
    points = np.concatenate([cleared, *(bank.object_points(k) for k in picked)])
    labels = np.concatenate([scan.gt.labels, bank.labels[picked]])
    gt = GroundTruth.from_boxes(np.concatenate([scan.gt.boxes, new]), labels, points)
    return LabeledScan(scan.name, points, scan.fields, gt, None, None, scan.label_fov, scan.spin)
