"""Training samples: one augmented scan cut into the model's sectors in time order, with the targets of
every buffer fill level.

A sample's sectors run in time order starting at a random sector (a stream can start anywhere in the turn),
counter-clockwise or, with chance `clockwise`, clockwise (sensors spin either way: KITTI's and Waymo's
counter-clockwise, nuScenes' clockwise).
The model encodes them as one stream, so the global Mamba carries its state from sector to sector exactly as
when streaming (causal: nothing of a later sector reaches an earlier one). Prediction k (k = 0 .. S-1) is
made from the first k + 1 sectors in time, that is the new one with k buffered ones, and its targets are the
boxes whose centre lies in those sectors: every fill level of the buffer is learned in every step.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor
from torch.utils.data import IterableDataset, get_worker_info

from lidar.readers import feature_columns, sector_of_xy
from lidar.types import LabeledScan, Spin
from model.config import PHiMConfig
from model.layers.head_targets import BEVTargets, TargetConfig, build_targets
from model.train.gt_sampling import GTSamplingConfig, ObjectBank, build_bank, paste_objects


@dataclass(frozen=True)
class AugmentConfig:
    rotate: bool = True  # a uniform random yaw about z, before the scan is cut into sectors
    flip: bool = True  # mirror left/right (y -> -y) with probability 0.5
    scale: tuple[float, float] = (0.95, 1.05)  # uniform global scale of points and boxes
    # intensity (column 3) differs by sensor and driver: a gain drawn log-uniformly per scan (clipped to
    # [0, 1]), and with chance `constant_intensity` one value for every point (data without intensity, such
    # as the Argoverse conversion's constant 1.0)
    intensity_gain: tuple[float, float] = (0.5, 2.0)
    constant_intensity: float = 0.1


@dataclass(frozen=True)
class SampleConfig:
    augment: AugmentConfig = field(default_factory=AugmentConfig)
    targets: TargetConfig = field(default_factory=TargetConfig)
    random_start: bool = True  # the first sector in time is random (else sector 0)
    clockwise: float = 0.5  # chance that the sectors run clockwise (a sensor spinning the other way round)
    gt_sampling: GTSamplingConfig | None = field(default_factory=GTSamplingConfig)  # None: no copy-paste


@dataclass(frozen=True)
class TrainSample:
    name: str
    sectors: list[Tensor]  # S x (N_k, C) float32, in time order
    targets: list[BEVTargets]  # S: targets of the prediction from sectors[: k + 1]


def augment(
    points: np.ndarray, boxes: np.ndarray, rng: np.random.Generator, cfg: AugmentConfig
) -> tuple[np.ndarray, np.ndarray]:
    """points (N, C), boxes (M, 7) -> augmented copies (same shapes)."""
    p, b = points.copy(), boxes.astype(np.float32).copy()
    if cfg.flip and rng.random() < 0.5:
        p[:, 1] *= -1
        b[:, 1] *= -1
        b[:, 6] *= -1
    if cfg.rotate:
        a = rng.uniform(-math.pi, math.pi)
        c, s = math.cos(a), math.sin(a)
        for arr in (p, b):
            x, y = arr[:, 0].copy(), arr[:, 1].copy()
            arr[:, 0], arr[:, 1] = c * x - s * y, s * x + c * y
        b[:, 6] += a
    lo, hi = cfg.scale
    if hi > lo:
        k = rng.uniform(lo, hi)
        p[:, :3] *= k
        b[:, :6] *= k
    b[:, 6] = (b[:, 6] + math.pi) % (2 * math.pi) - math.pi
    if p.shape[1] > 3:
        _intensity(p[:, 3], rng, cfg)
    return p, b


def _intensity(values: np.ndarray, rng: np.random.Generator, cfg: AugmentConfig) -> None:
    """Augment the intensity column (N,) in place."""
    lo, hi = cfg.intensity_gain
    if hi > lo:
        values *= math.exp(rng.uniform(math.log(lo), math.log(hi)))
        np.clip(values, 0.0, 1.0, out=values)
    if rng.random() < cfg.constant_intensity:
        values[:] = rng.choice([0.0, 1.0, rng.random()])


def is_target(boxes: np.ndarray, num_points: np.ndarray, model_cfg: PHiMConfig) -> np.ndarray:
    """boxes (M, 7), their points (M,) -> (M,) bool: which boxes the model is asked to find. A box without
    points is not a target (Waymo); neither is one whose centre lies outside the polar grid's range: the
    square BEV map reaches beyond r_max in its corners (and inside r_min), where the voxelizer keeps no
    point, and a peak there would teach the heatmap to fire on nothing."""
    grid = model_cfg.grid
    r = np.hypot(boxes[:, 0], boxes[:, 1])  # (M,)
    return (num_points > 0) & (r >= grid.r_min) & (r < grid.r_max)


def make_sample(
    scan: LabeledScan, model_cfg: PHiMConfig, cfg: SampleConfig, rng: np.random.Generator
) -> TrainSample:
    points = feature_columns(scan, model_cfg.vfe.point_features)
    points, boxes = augment(points, scan.gt.boxes, rng, cfg.augment)
    n = model_cfg.sectors_per_turn
    start = int(rng.integers(n)) if cfg.random_start else 0
    order = (Spin.CW if rng.random() < cfg.clockwise else Spin.CCW).order(n, start)
    point_sector = sector_of_xy(points[:, 0], points[:, 1], n)  # (N,)
    box_sector = sector_of_xy(boxes[:, 0], boxes[:, 1], n)  # (M,)
    target = is_target(boxes, scan.gt.num_points, model_cfg)
    sectors = [torch.from_numpy(np.ascontiguousarray(points[point_sector == k])) for k in order]
    targets = []
    for k in range(n):
        sel = target & np.isin(box_sector, order[: k + 1])
        targets.append(
            build_targets(
                boxes[sel], scan.gt.labels[sel], len(model_cfg.head.class_names), model_cfg.bev, cfg.targets
            )
        )
    return TrainSample(scan.name, sectors, targets)


class SampleStream(IterableDataset):
    """Endless TrainSamples: scan i comes from `scan_at(i)` for i = first, first + stride, ...

    `stride` and `first` spread scans over DDP ranks; data-loader workers split them further. The
    augmentation of scan i is seeded by (seed, i), so a resumed run sees the same samples again. With
    `cfg.gt_sampling`, scans before index `paste_before` get objects pasted from a bank cut from `bank_at`'s
    scans (built once per process).
    """

    def __init__(
        self,
        scan_at,
        model_cfg: PHiMConfig,
        cfg: SampleConfig,
        seed: int,
        first: int,
        stride: int,
        bank_at=None,
        paste_before: int = 0,
    ):
        super().__init__()
        self.scan_at, self.model_cfg, self.cfg = scan_at, model_cfg, cfg
        self.seed, self.first, self.stride = seed, first, stride
        self.bank_at, self.paste_before = bank_at, paste_before

    def _bank(self) -> ObjectBank | None:
        gts = self.cfg.gt_sampling
        if gts is None or self.bank_at is None or self.first >= self.paste_before:
            return None
        return build_bank(self.bank_at, gts.bank_scans, gts.min_points)

    def __iter__(self) -> Iterator[TrainSample]:
        info = get_worker_info()
        wid, nw = (info.id, info.num_workers) if info is not None else (0, 1)
        if info is not None:
            torch.set_num_threads(1)
        i = self.first + wid * self.stride
        bank = self._bank()
        while True:
            rng = np.random.default_rng([self.seed, i])
            scan = self.scan_at(i)
            if bank is not None and self.cfg.gt_sampling is not None and i < self.paste_before:
                scan = paste_objects(scan, bank, rng, self.cfg.gt_sampling)
            yield make_sample(scan, self.model_cfg, self.cfg, rng)
            i += nw * self.stride
