"""Shape buckets of the fixed-shape step, chosen on the host before launch.

- Batch: 1, 2, 4, 8, 16 or 32 streams; the padding streams have no points and their outputs are dropped.
- Rows: a ladder of eight sizes per octave, 2^k * (1 + j / 8) (a bucket wastes at most an eighth of the one
  below it; with 2^k and 1.5 * 2^k, a third, and a `tiny` KITTI step took 6,144 voxel rows for 4,254 sites
  and ran 18 % slower). Points per stream pad to the largest sector's bucket; the voxel and coarse-site
  capacities are predicted from the padded batch (streams x points bucket) with the largest ratio (sites /
  points) seen so far (`CapacityPlanner`; 1.0 before the first step), so a (batch, points) bucket has one
  set of capacities: a compiled step is specialised once per bucket, at a server's warm-up, not again while
  it serves. The step reports the true counts with its candidates; a step whose sites did not fit is run
  again with capacities that hold them (never truncated), and the ratios grow to what was seen (learned
  from the true point count), so that happens rarely after the first steps.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from model.graph.step import Capacity

BATCH_BUCKETS = (1, 2, 4, 8, 16, 32)
MIN_ROWS = 256


def batch_bucket(n: int) -> int:
    """The smallest batch bucket holding n streams; ValueError above the largest."""
    for b in BATCH_BUCKETS:
        if n <= b:
            return b
    raise ValueError(f"{n} streams in one step; the graph step takes at most {BATCH_BUCKETS[-1]}")


def row_bucket(n: int) -> int:
    """The smallest ladder size (2^k * (1 + j / 8), j < 8, at least MIN_ROWS) holding n rows."""
    size = MIN_ROWS
    while True:
        for j in range(8):
            if n <= size + size * j // 8:
                return size + size * j // 8
        size *= 2


@dataclass
class CapacityPlanner:
    """Predicts a step's capacities from its points; learns the ratios from the counts steps report.

    `ratios`: [voxels, then (a) and (c) sites per strided key] per point of the batch, the largest seen so
    far; before any step, 1.0 (a voxel holds at least one point, so that fits the voxels). `frozen` ratios
    learn nothing more (a compiled detector after calibration: new capacities would compile new graphs).
    """

    num_keys: int
    ratios: list[float] = field(default_factory=list)
    frozen: bool = False

    def capacity(self, points_per_stream: int, streams: int) -> Capacity:
        """Capacities for a batch bucket of `streams` whose largest sector has `points_per_stream` points."""
        ratios = self.ratios or [1.0] * (1 + 2 * self.num_keys)
        padded = row_bucket(points_per_stream) * streams  # every stream full: holds any batch of this bucket
        rows = [row_bucket(max(1, round(r * padded))) for r in ratios]
        coarse = tuple((rows[1 + 2 * i], rows[2 + 2 * i]) for i in range(self.num_keys))
        return Capacity(points=row_bucket(points_per_stream), voxels=rows[0], coarse=coarse)

    def fits(self, cap: Capacity, counts: list[int], total_points: int) -> bool:
        """Learn from a step's true site counts (voxels, then (a), (c) per key); False if any overflowed."""
        caps = [cap.voxels, *(c for pair in cap.coarse for c in pair)]
        seen = [n / max(1, total_points) for n in counts]
        if not self.frozen:
            self.ratios = [max(a, b) for a, b in zip(self.ratios, seen, strict=True)] if self.ratios else seen
        return all(n <= c for n, c in zip(counts, caps, strict=True))

    @staticmethod
    def holding(cap: Capacity, counts: list[int]) -> Capacity:
        """`cap` grown to hold `counts` (voxels, then (a), (c) per key): for a step that did not fit."""
        rows = [row_bucket(n) for n in counts]
        coarse = tuple(
            (max(a, rows[1 + 2 * i]), max(c, rows[2 + 2 * i])) for i, (a, c) in enumerate(cap.coarse)
        )
        return replace(cap, voxels=max(cap.voxels, rows[0]), coarse=coarse)
