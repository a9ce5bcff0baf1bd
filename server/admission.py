"""A sector message's points, checked against the model and the contract's value rules (finite, coordinates
within `MAX_COORDINATE_M`) and converted to a tensor before it is queued: a bad sector never enters a batch
(its own INVALID_FIELD error names the field and what was expected)."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
import torch

from contract import MAX_COORDINATE_M, POINT_FIELDS, ErrorCode, SectorMessage, ServiceError
from model.config import PHiMConfig


def sector_points(msg: SectorMessage, cfg: PHiMConfig) -> torch.Tensor:
    """Check the sector against the model and convert it; a bad sector never enters a batch."""
    if not 0 <= msg.sector_index < cfg.sectors_per_turn:
        raise ServiceError(
            ErrorCode.INVALID_FIELD,
            f"sector_index: {msg.sector_index}; expected 0..{cfg.sectors_per_turn - 1} "
            f"(the model splits a turn into {cfg.sectors_per_turn} sectors)",
            "sector_index",
        )
    used = min(len(msg.fields), cfg.vfe.point_features)
    if tuple(msg.fields[:used]) != POINT_FIELDS[:used]:
        expected = list(POINT_FIELDS[: cfg.vfe.point_features])
        raise ServiceError(
            ErrorCode.INVALID_FIELD,
            f"fields: {list(msg.fields)}; the model reads the columns {expected} (in this order)",
            "fields",
        )
    points = np.array(msg.points, dtype=np.float32, copy=True)  # (N, C), owns its memory
    if points.ndim != 2 or points.shape[1] < 4:
        raise ServiceError(
            ErrorCode.INVALID_FIELD,
            f"points: shape {points.shape}; expected 2-D (N, C>=4): x, y, z, intensity[, ...]",
            "points",
        )
    check_values(points)
    return torch.from_numpy(points)


def check_values(points: np.ndarray) -> None:
    """points (N, C>=3) float32: every value finite and every coordinate within the contract's range
    (|x|, |y|, |z| <= MAX_COORDINATE_M), else INVALID_FIELD on `points` naming the first bad row and the rule.
    One rule for all: a sector with a bad point is refused whole, never cut (HTTP, zenoh and the ROS 2 bridge
    all submit through here)."""
    # numpy, not torch: a torch op here would start a second OpenMP team in the transport's thread,
    # competing for the cores with the device loop's (the model checks its input again anyway)
    if not np.isfinite(points).all():  # a flat check first: the per-row one is ~30x slower
        bad = ~np.isfinite(points).all(axis=1)  # (N,)
        raise ServiceError(
            ErrorCode.INVALID_FIELD,
            f"points: {int(bad.sum())} rows contain NaN or inf values (row {int(bad.argmax())} first); "
            "expected finite float32",
            "points",
        )
    # a flat check first, every column (intensity is inside the range too, as a rule): 0.05 against 0.7 ms
    # for 120,000 points' strided x, y, z on the 2-core machine
    flat = points.reshape(-1)
    if flat.size and not (flat.max() <= MAX_COORDINATE_M and flat.min() >= -MAX_COORDINATE_M):
        far = np.abs(points[:, :3]) > MAX_COORDINATE_M  # (N, 3): the coordinates, per row
        if not far.any():
            return
        row = int(far.any(axis=1).argmax())
        col = int(far[row].argmax())
        raise ServiceError(
            ErrorCode.INVALID_FIELD,
            f"points: {int(far.any(axis=1).sum())} rows have a coordinate beyond {MAX_COORDINATE_M:g} m (row "
            f"{row} first: {POINT_FIELDS[col]} = {float(points[row, col]):g}); expected |x|, |y|, |z| <= "
            f"{MAX_COORDINATE_M:g} m",
            "points",
        )


@dataclass
class Backlog:
    """The sectors and points waiting for the device loop (not running), against their limits. The points
    bound the memory the queue holds (a sector's points are copied on admission): a sector that would pass
    `max_points` waits for room (OVERLOADED, retry later) unless the queue is empty, so one sector of up
    to `max_points` per sector (the decoder's limit) can always run."""

    max_sectors: int
    max_points: int
    sectors: int = 0
    points: int = 0

    def check(self, n_points: int, retry_after_s: float) -> None:
        """Raise OVERLOADED unless a sector of n_points fits."""
        if self.sectors >= self.max_sectors:
            why = f"queue full: {self.sectors} sectors waiting (queue_size={self.max_sectors})"
        elif self.sectors and self.points + n_points > self.max_points:
            why = (
                f"queue full: {self.points} points waiting, {n_points} more would pass "
                f"max_queued_points={self.max_points}"
            )
        else:
            return
        raise ServiceError(
            ErrorCode.OVERLOADED, f"{why}; retry after {retry_after_s:.2f} s", retry_after_s=retry_after_s
        )

    def add(self, n_points: int) -> None:
        self.sectors += 1
        self.points += n_points

    def remove(self, point_counts: Iterable[int]) -> None:
        for n in point_counts:
            self.sectors -= 1
            self.points -= n
