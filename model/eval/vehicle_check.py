"""What a user looks at first on real scans: are the well-seen vehicles found, and how many vehicle boxes sit
on nothing? (`phim eval` prints it beside the Waymo AP/APH.)

At one operating point, predictions with score >= `score` (full-turn predictions, already cropped to the
labels' field of view and the evaluation range):
- recall: of the labelled vehicles with at least `min_points` points whose centre lies within `max_range`
  metres, the share that a predicted vehicle overlaps at rotated BEV IoU >= `iou`;
- false vehicle boxes: predicted vehicles that cover at most `false_overlap` of every labelled object's
  footprint (of any target class): boxes on vegetation, walls, clutter; a loose or duplicate box on a
  labelled object is not counted here (the AP sees it), per scan;
- below the score: the counted vehicles missed at the operating point that a predicted vehicle of lower
  score overlaps at the same IoU (boxed, but scored too low: a calibration miss, not a detection miss).
Scans are grouped by the part of their name before "/" (a samples subfolder: KITTI, Argoverse, nuScenes).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from model.config import CLASS_NAMES
from model.eval.runner import ScanResult
from model.geometry.boxes import rotated_iou_bev

VEHICLE = CLASS_NAMES.index("VEHICLE")


@dataclass(frozen=True)
class VehicleCheckConfig:
    min_points: int = 50  # a labelled vehicle counts for recall with at least this many points
    max_range: float = 50.0  # metres, box centre (BEV)
    iou: float = 0.5  # rotated BEV IoU to count a labelled vehicle as found
    score: float = 0.5  # the operating point: predictions at or above this score
    false_overlap: float = 0.1  # false: a vehicle box covering at most this share of every labelled footprint


@dataclass
class Tally:
    scans: int = 0
    vehicles: int = 0  # labelled vehicles counted for recall
    found: int = 0
    below_score: int = 0  # missed at the operating point, boxed at a lower score
    false_boxes: int = 0

    def add(self, other: Tally) -> None:
        self.scans += other.scans
        self.vehicles += other.vehicles
        self.found += other.found
        self.below_score += other.below_score
        self.false_boxes += other.false_boxes

    def as_dict(self) -> dict[str, float | int | None]:
        return {
            "scans": self.scans,
            "vehicles": self.vehicles,
            "found": self.found,
            "recall": self.found / self.vehicles if self.vehicles else None,
            "below_score": self.below_score,
            "false_boxes": self.false_boxes,
            "false_per_scan": self.false_boxes / self.scans if self.scans else None,
        }


def iou_bev(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(A, 7), (B, 7) boxes -> (A, B) rotated BEV IoU."""
    if len(a) == 0 or len(b) == 0:
        return np.zeros((len(a), len(b)), np.float64)
    iou = rotated_iou_bev(torch.from_numpy(a).double(), torch.from_numpy(b).double())
    return iou.numpy()


def _covered(gt: np.ndarray, boxes: np.ndarray, iou: np.ndarray) -> np.ndarray:
    """(M, K) share of each labelled box's footprint that each predicted box covers, from their IoU:
    intersection = IoU (A + B) / (1 + IoU)."""
    area_gt, area = gt[:, 3] * gt[:, 4], boxes[:, 3] * boxes[:, 4]  # (M,), (K,)
    inter = iou * (area_gt[:, None] + area[None, :]) / (1.0 + iou)  # (M, K)
    return inter / np.maximum(area_gt[:, None], 1e-9)


def check_scan(r: ScanResult, cfg: VehicleCheckConfig) -> Tally:
    pred, truth = r.predictions[-1], r.truths[-1]
    vehicles = pred.labels == VEHICLE  # (K,)
    boxes = np.asarray(pred.boxes, np.float64)[vehicles & (pred.scores >= cfg.score)]
    lower = np.asarray(pred.boxes, np.float64)[vehicles & (pred.scores < cfg.score)]
    gt = np.asarray(truth.boxes, np.float64)  # (M, 7) every labelled target
    wanted = (
        (truth.labels == VEHICLE)
        & (truth.num_points >= cfg.min_points)
        & (np.hypot(gt[:, 0], gt[:, 1]) <= cfg.max_range)
    )  # (M,)
    iou = iou_bev(gt, boxes)  # (M, K)
    found = (iou >= cfg.iou).any(axis=1) & wanted  # (M,)
    below = (iou_bev(gt, lower) >= cfg.iou).any(axis=1) & wanted & ~found  # (M,)
    false = int((_covered(gt, boxes, iou) <= cfg.false_overlap).all(axis=0).sum())
    return Tally(1, int(wanted.sum()), int(found.sum()), int(below.sum()), false)


def vehicle_check(results: Sequence[ScanResult], cfg: VehicleCheckConfig | None = None) -> dict:
    """-> {"config": ..., "all": tally, "by_group": {group: tally}} (tallies as `Tally.as_dict`)."""
    cfg = cfg or VehicleCheckConfig()
    total, groups = Tally(), {}
    for r in results:
        t = check_scan(r, cfg)
        total.add(t)
        groups.setdefault(r.name.split("/")[0] if "/" in r.name else "", Tally()).add(t)
    by_group = {g: t.as_dict() for g, t in sorted(groups.items())} if len(groups) > 1 else {}
    return {"config": dataclasses.asdict(cfg), "all": total.as_dict(), "by_group": by_group}


def format_check(check: dict) -> str:
    cfg = check["config"]
    head = (
        f"vehicles with >= {cfg['min_points']} points within {cfg['max_range']:g} m found at BEV IoU "
        f">= {cfg['iou']:g}, and vehicle boxes on no labelled object, at score >= {cfg['score']:g} (below: "
        "missed vehicles that a lower-scored box overlaps):"
    )
    rows = [("all", check["all"]), *check["by_group"].items()]
    lines = [head, f"{'scans':<30} {'n':>4} {'found':>11} {'recall':>7} {'below':>6} {'false/scan':>11}"]
    for name, t in rows:
        recall = "-" if t["recall"] is None else f"{t['recall']:.3f}"
        lines.append(
            f"{name:<30} {t['scans']:>4} {t['found']:>5} / {t['vehicles']:<3} {recall:>7} "
            f"{t['below_score']:>6} {t['false_per_scan']:>11.2f}"
        )
    return "\n".join(lines)
