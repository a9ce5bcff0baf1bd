"""Property lines beside a road: hedges, porous fences on posts, low walls with pillars, and the runs of a
roadside where they may stand (off every other road and its sidewalks)."""

from __future__ import annotations

import numpy as np

from lidar.sim.ground import Ground
from lidar.sim.layout import Road, clear_of, disc_corners, ground_z
from lidar.sim.parts import FENCE, TaggedSolidList
from lidar.sim.vegetation import hedge

HEDGE, FENCE_LINE, WALL, NOTHING = range(4)
KIND_PROBS = (0.35, 0.3, 0.15, 0.2)  # of a property line


def free_runs(
    road: Road, side: int, others: tuple[Road, ...], s: tuple[float, float], d: tuple[float, float]
) -> list[tuple[float, float]]:
    """Along-road runs (s0, s1) within `s` where a strip from d[0] to d[1] beyond the sidewalk keeps clear of
    the other roads, tested every metre; runs shorter than 1 m are dropped."""
    along = np.arange(s[0], s[1] + 1.0, 1.0)  # (K,)
    mid = (d[0] + d[1]) / 2
    xy = road.outward(side, along, np.full(len(along), mid))
    ok = clear_of(list(others), disc_corners(xy, np.full(len(along), (d[1] - d[0]) / 2 + 0.5)))
    runs, start = [], None
    for a, good in zip(along.tolist(), ok.tolist(), strict=True):
        if good and start is None:
            start = a
        if not good and start is not None:
            runs.append((start, a - 1.0))
            start = None
    if start is not None:
        runs.append((start, min(float(along[-1]), s[1])))
    return [(a, b) for a, b in runs if b - a >= 1.0]


def boundary(
    solids: TaggedSolidList,
    rng: np.random.Generator,
    road: Road,
    side: int,
    s: tuple[float, float],
    d: float,
    ground: Ground,
    kind: int,
) -> None:
    """A hedge, fence or wall from s[0] to s[1] along the road, `d` metres beyond the sidewalk."""
    length = s[1] - s[0]
    if kind == NOTHING or length < 1.0:
        return
    start = road.outward(side, np.array([s[0]]), np.array([d]))[0]
    if kind == HEDGE:
        size = (rng.uniform(0.6, 1.4), rng.uniform(0.8, 2.2))
        hedge(
            solids,
            rng,
            start,
            road.yaw,
            length,
            lambda xy: ground_z(ground, road, xy, np.full(len(xy), d)),
            size,
        )
        return
    posts = s[0] + np.arange(0.0, length + 0.01, rng.uniform(2.0, 3.5))  # (n,)
    xy = road.outward(side, posts, np.full(len(posts), d))
    z = ground_z(ground, road, xy, np.full(len(posts), d))
    mid = road.outward(side, np.array([(s[0] + s[1]) / 2]), np.array([d]))
    z_mid = float(ground_z(ground, road, mid, np.array([d]))[0])
    solids.tag = FENCE
    if kind == FENCE_LINE:
        height = rng.uniform(1.0, 2.0)
        solids.cylinders(xy, z - 0.3, z + height + 0.05, 0.05, rng.uniform(0.2, 0.5))
        porosity = [0.85, 0.5, 0.15][int(rng.integers(3))]  # chain link, pickets, boards
        solids.boxes(
            mid, z_mid - 0.05, z_mid + height, length, 0.04, road.yaw, rng.uniform(0.2, 0.5), porosity
        )
        return
    height = rng.uniform(0.5, 1.8)
    solids.boxes(
        mid, z_mid - 0.3, z_mid + height, length, rng.uniform(0.2, 0.4), road.yaw, rng.uniform(0.2, 0.5)
    )
    solids.boxes(xy, z - 0.3, z + height + 0.15, 0.45, 0.45, road.yaw, rng.uniform(0.2, 0.5))


def pick_kind(rng: np.random.Generator) -> int:
    return int(rng.choice(len(KIND_PROBS), p=KIND_PROBS))
