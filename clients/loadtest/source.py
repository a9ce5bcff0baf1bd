"""Where the simulated vehicles' sectors come from: recorded scans cut by the sectorizer, or synthetic turns.

Every turn is a list of (sector_index, points (N, 4) float32 x, y, z, intensity) in sweep order.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from clients.loadtest.config import SourceConfig
from contract import REQUIRED_FIELDS
from lidar.readers import find_scans, read_scan
from lidar.sectorizer import Spin, split_scan
from lidar.synthetic import synthetic_turn

Turn = list[tuple[int, np.ndarray]]  # (sector_index, (N, 4) float32) in sweep order


@dataclass(frozen=True)
class SectorSource:
    turns: list[Turn]
    description: str
    fields: tuple[str, ...] = REQUIRED_FIELDS

    def sector(self, vehicle: int, k: int) -> tuple[int, np.ndarray]:
        """The k-th sector a vehicle sends: vehicles start on different turns and cycle through them."""
        spt = len(self.turns[0])
        turn = self.turns[(vehicle * 7 + k // spt) % len(self.turns)]
        return turn[k % spt]

    @property
    def mean_points(self) -> float:
        return float(np.mean([p.shape[0] for t in self.turns for _, p in t]))


def load_source(cfg: SourceConfig, sectors_per_turn: int) -> SectorSource:
    if cfg.folder is not None:
        paths = find_scans(cfg.folder)[: cfg.max_scans]
        if not paths:
            raise FileNotFoundError(f"{cfg.folder}: no .bin / .npz / .pcd.bin scans")
        turns = [_turn(read_scan(p), sectors_per_turn, cfg.every) for p in paths]
        return SectorSource(turns, f"{len(paths)} scans from {cfg.folder} (every {cfg.every})")
    turns = []
    for seed in range(cfg.synthetic_turns):
        pts = synthetic_turn(seed=seed)
        turns.append(_split(pts, REQUIRED_FIELDS, sectors_per_turn, cfg.every))
    return SectorSource(turns, f"{cfg.synthetic_turns} synthetic turns (every {cfg.every})")


def _turn(scan, sectors: int, every: int) -> Turn:
    return _split(scan.points, scan.fields, sectors, every, scan.spin)


def _split(points: np.ndarray, fields, sectors: int, every: int, spin: Spin = Spin.CCW) -> Turn:
    return [(s.index, s.points[:: max(1, every)]) for s in split_scan(points, fields, sectors, spin)]
