"""What each solid of a scene is (a tag per solid), and the scenery that targets must keep clear of.

`TaggedSolidList` is a `SolidList` that remembers a tag (SLAB, BUILDING, ...) for every solid it collects, so
tests and statistics can tell which points fell on vegetation, facades or targets. `Obstacles` answers
whether a target's label box would overlap any scenery solid (footprints and heights both), so a parked car
may stand under a tree crown but not inside a hedge, a bay window or a bush.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lidar.sim.raycast import BOX, CYLINDER, Num, SolidList, Solids, material_of

SLAB, BUILDING, WINDOW, INTERIOR, VEGETATION, FENCE, FURNITURE, TARGET = range(8)
TAG_NAMES = ("slab", "building", "window", "interior", "vegetation", "fence", "furniture", "target")
CLEARANCE = 0.05  # metres kept between a target's box and scenery


class TaggedSolidList(SolidList):
    """A SolidList whose solids carry the tag that was current (`self.tag`) when they were added. Batches are
    buffered and handed to the SolidList together (boxes, then cylinders) when `build()` or `tags()` is
    called, so many small batches cost one concatenation."""

    def __init__(self) -> None:
        super().__init__()
        self.tag = FURNITURE
        self._tags: list[np.ndarray] = []
        self._pending: dict[int, list[tuple[np.ndarray, ...]]] = {BOX: [], CYLINDER: []}

    def _queue(self, kind: int, centre: np.ndarray, values: tuple[Num, ...], material: Num | None) -> None:
        c = np.asarray(centre, np.float64).reshape(-1, 2)  # (K, 2)
        n = len(c)
        cols = tuple(
            np.full(n, v, np.float64) if np.ndim(v) == 0 else np.asarray(v, np.float64) for v in values
        )
        mat = material_of(cols[-1], material)  # the last value is the porosity
        self._pending[kind].append((c, *cols, mat, np.full(n, self.tag, np.int8)))

    def boxes(
        self,
        centre: np.ndarray,
        z0: Num,
        z1: Num,
        length: Num,
        width: Num,
        yaw: Num,
        refl: Num,
        porosity: Num = 0.0,
        material: Num | None = None,
    ) -> None:
        self._queue(BOX, centre, (z0, z1, length, width, yaw, refl, porosity), material)

    def cylinders(
        self,
        centre: np.ndarray,
        z0: Num,
        z1: Num,
        radius: Num,
        refl: Num,
        porosity: Num = 0.0,
        material: Num | None = None,
    ) -> None:
        self._queue(CYLINDER, centre, (z0, z1, radius, refl, porosity), material)

    def _flush(self) -> None:
        for kind, add in ((BOX, super().boxes), (CYLINDER, super().cylinders)):
            if self._pending[kind]:
                cols = [np.concatenate(c) for c in zip(*self._pending[kind], strict=True)]
                add(*cols[:-1])
                self._tags.append(cols[-1])
                self._pending[kind] = []

    def build(self) -> Solids:
        self._flush()
        return super().build()

    def tags(self) -> np.ndarray:
        """(P,) int8 tag of every solid, in the order of `build()`."""
        self._flush()
        return np.concatenate(self._tags) if self._tags else np.zeros(0, np.int8)


@dataclass(frozen=True)
class Obstacles:
    """Scenery solids (ground slabs left out) as footprints with heights, for overlap tests."""

    solids: Solids
    reach: np.ndarray  # (P,) radius of each footprint's bounding disc

    @staticmethod
    def of(solids: Solids, tags: np.ndarray) -> Obstacles:
        s = solids.select(tags != SLAB)
        return Obstacles(s, np.hypot(s.half[:, 0], np.where(s.kind == BOX, s.half[:, 1], 0.0)))

    def clear(self, box: np.ndarray) -> bool:
        """One label box (7,) x, y, z, l, w, h, yaw -> whether it keeps clear of every solid."""
        s = self.solids
        rel = s.centre - box[:2]  # (P, 2)
        near = np.hypot(rel[:, 0], rel[:, 1]) < self.reach + math.hypot(box[3], box[4]) / 2 + CLEARANCE
        near &= (s.z[:, 0] < box[2] + box[5] / 2 - 0.02) & (s.z[:, 1] > box[2] - box[5] / 2 + 0.02)
        idx = np.flatnonzero(near)
        if len(idx) == 0:
            return True
        c, sn = math.cos(box[6]), math.sin(box[6])
        lx, ly = rel[idx, 0] * c + rel[idx, 1] * sn, -rel[idx, 0] * sn + rel[idx, 1] * c  # box frame
        hl, hw = box[3] / 2 + CLEARANCE, box[4] / 2 + CLEARANCE
        box_kind = s.kind[idx] == BOX
        gap = np.hypot(np.maximum(np.abs(lx) - hl, 0), np.maximum(np.abs(ly) - hw, 0))  # circle test
        hits = ~box_kind & (gap < s.half[idx, 0])
        if box_kind.any():
            hits[box_kind] = _rectangles_overlap(box, (hl, hw), s, idx[box_kind])
        return not bool(hits.any())


def _rectangles_overlap(box: np.ndarray, half: tuple[float, float], s: Solids, idx: np.ndarray) -> np.ndarray:
    """Separating-axis test of one rectangle against box solids `idx` (K,) -> (K,) bool overlap."""
    yaws = np.stack([np.full(len(idx), box[6]), s.yaw[idx]], 1)  # (K, 2) the four candidate axes
    axes = np.concatenate(
        [np.stack([np.cos(yaws), np.sin(yaws)], -1), np.stack([-np.sin(yaws), np.cos(yaws)], -1)], 1
    )
    d = s.centre[idx] - box[:2]  # (K, 2)
    dist = np.abs(np.einsum("kad,kd->ka", axes, d))  # (K, 4)
    ca, sa = math.cos(box[6]), math.sin(box[6])
    ra = half[0] * np.abs(axes @ np.array([ca, sa])) + half[1] * np.abs(axes @ np.array([-sa, ca]))
    cb, sb = np.cos(s.yaw[idx])[:, None], np.sin(s.yaw[idx])[:, None]  # (K, 1)
    along_b = np.abs(axes[..., 0] * cb + axes[..., 1] * sb)
    across_b = np.abs(-axes[..., 0] * sb + axes[..., 1] * cb)
    rb = s.half[idx, 0:1] * along_b + s.half[idx, 1:2] * across_b
    return np.all(dist < ra + rb, axis=1)
