"""Vegetation as the irregular, porous clutter that real scans are full of: every crown, bush and hedge is
several overlapping porous parts (vertical cylinders and yawed boxes) of random size and offset, so its
outline, top and depth vary and rays reach into it and sometimes through it.

All functions are vectorized over K plants: (K, 2) centres in the sensor frame, (K,) ground heights.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from lidar.sim.ground import Ground
from lidar.sim.layout import Road, clear_of, disc_corners, ground_z
from lidar.sim.parts import VEGETATION, TaggedSolidList

FOLIAGE = (0.3, 0.6)  # reflectivity of leaves (bright in the near infrared)
BARK = (0.2, 0.35)
BOX_PART_SHARE = 0.3  # of crown parts that are yawed boxes rather than cylinders


def clumps(
    solids: TaggedSolidList,
    rng: np.random.Generator,
    xy: np.ndarray,
    z: tuple[np.ndarray, np.ndarray],
    radius: np.ndarray,
    parts: tuple[int, int],
    porosity: tuple[float, float],
) -> None:
    """K irregular porous masses: each 2-6 parts offset up to half its radius from `xy` (K, 2), part radii
    40-75 % of `radius` (K,), each spanning a random part of its height range z = (bottom (K,), top (K,))."""
    solids.tag = VEGETATION
    m = rng.integers(parts[0], parts[1] + 1, len(xy))
    idx = np.repeat(np.arange(len(xy)), m)  # (n,) the clump of each part
    n = len(idx)
    angle, off = rng.uniform(0, 2 * math.pi, n), radius[idx] * rng.uniform(0, 0.5, n)
    centre = xy[idx] + off[:, None] * np.stack([np.cos(angle), np.sin(angle)], 1)  # (n, 2)
    r = radius[idx] * rng.uniform(0.4, 0.75, n)
    height = z[1][idx] - z[0][idx]
    lo = z[0][idx] + height * rng.uniform(0, 0.4, n) * (rng.random(n) < 0.6)
    hi = z[1][idx] - height * rng.uniform(0, 0.35, n)
    refl, poro = rng.uniform(*FOLIAGE, n), rng.uniform(*porosity, n)
    box = rng.random(n) < BOX_PART_SHARE
    solids.cylinders(centre[~box], lo[~box], hi[~box], r[~box], refl[~box], poro[~box])
    yaw = rng.uniform(-math.pi, math.pi, int(box.sum()))
    solids.boxes(centre[box], lo[box], hi[box], 1.6 * r[box], 1.2 * r[box], yaw, refl[box], poro[box])


@dataclass(frozen=True)
class TreeShape:
    trunk: tuple[float, float] = (0.1, 0.3)  # radius (m)
    crown_base: tuple[float, float] = (1.8, 4.0)  # above the ground (m)
    crown_height: tuple[float, float] = (2.5, 7.0)
    crown_radius: tuple[float, float] = (1.2, 3.2)


STREET_TREE = TreeShape()
FOREST_TREE = TreeShape((0.12, 0.4), (0.4, 2.0), (5.0, 14.0), (1.5, 3.5))


def trees(
    solids: TaggedSolidList, rng: np.random.Generator, xy: np.ndarray, z: np.ndarray, shape: TreeShape
) -> np.ndarray:
    """K trees (trunk + irregular crown) -> (K,) trunk radii."""
    k = len(xy)
    trunk = rng.uniform(*shape.trunk, k)
    base = z + rng.uniform(*shape.crown_base, k)
    top = base + rng.uniform(*shape.crown_height, k)
    solids.tag = VEGETATION
    solids.cylinders(xy, z - 0.2, base + 0.8, trunk, rng.uniform(*BARK, k))
    clumps(solids, rng, xy, (base, top), rng.uniform(*shape.crown_radius, k), (3, 6), (0.35, 0.6))
    return trunk


def bushes(
    solids: TaggedSolidList,
    rng: np.random.Generator,
    xy: np.ndarray,
    z: np.ndarray,
    radius: np.ndarray,
    height: np.ndarray,
) -> None:
    """K bushes: dense irregular clumps from the ground up to `height` (K,)."""
    clumps(solids, rng, xy, (z - 0.1, z + height), radius, (2, 5), (0.25, 0.45))


def hedge(
    solids: TaggedSolidList,
    rng: np.random.Generator,
    start: np.ndarray,
    yaw: float,
    length: float,
    z_at: Callable[[np.ndarray], np.ndarray],
    size: tuple[float, float],
) -> None:
    """A hedge from `start` (2,) along heading `yaw`: segments of 0.7-2 m whose depth (around size[0]),
    top (around size[1]), lateral position and heading vary, with a few clumps sticking out of its top.
    `z_at` maps (n, 2) points to their ground heights (n,)."""
    seg = np.cumsum(rng.uniform(0.7, 2.0, int(length / 0.7) + 2))
    seg = seg[seg < length + 0.5]
    mid = seg - np.diff(np.concatenate([[0.0], seg])) / 2  # (n,) along
    n = len(mid)
    u, nrm = np.array([math.cos(yaw), math.sin(yaw)]), np.array([-math.sin(yaw), math.cos(yaw)])
    centre = start + mid[:, None] * u + rng.normal(0, 0.1, n)[:, None] * nrm  # (n, 2)
    z = z_at(centre)
    depth, top = size[0] * rng.uniform(0.75, 1.25, n), z + size[1] * rng.uniform(0.85, 1.12, n)
    lengths = np.diff(np.concatenate([[0.0], seg])) + 0.3
    solids.tag = VEGETATION
    refl, poro = rng.uniform(*FOLIAGE, n), rng.uniform(0.25, 0.45, n)
    solids.boxes(centre, z - 0.1, top, lengths, depth, yaw + rng.normal(0, 0.04, n), refl, poro)
    tufts = rng.random(n) < 0.3
    r = size[0] * rng.uniform(0.4, 0.7, int(tufts.sum()))
    clumps(solids, rng, centre[tufts], (top[tufts] - 0.5, top[tufts] + 0.4), r, (1, 2), (0.3, 0.5))


@dataclass(frozen=True)
class Strip:
    """A band beside a road, beyond its sidewalk: along s0..s1, from d0 to d1 metres beyond the sidewalk."""

    road: Road
    side: int
    others: tuple[Road, ...]
    s: tuple[float, float]
    d: tuple[float, float]

    def scatter(self, rng: np.random.Generator, spacing: tuple[float, float], r: np.ndarray | float) -> tuple:
        """Points along the strip `spacing` apart, at random depths, clear of other roads -> xy (K, 2),
        d (K,)."""
        s = self.s[0] + np.cumsum(rng.uniform(*spacing, int((self.s[1] - self.s[0]) / spacing[0]) + 1))
        s = s[s < self.s[1]]
        d = rng.uniform(*self.d, len(s))
        xy = self.road.outward(self.side, s, d)
        keep = clear_of(list(self.others), disc_corners(xy, np.broadcast_to(r, len(s))))
        return xy[keep], d[keep]


def belt(solids: TaggedSolidList, rng: np.random.Generator, strip: Strip, ground: Ground, kind: int) -> None:
    """A vegetation belt: 0 hedgerow (dense bushes, some trees), 1 forest edge (trees to the ground, shrubs
    under them), 2 a row of trees over grass."""
    road = strip.road
    if kind in (0, 1):  # bushes scattered through the depth of the belt, around one height per stretch
        tall = rng.uniform(1.2, 4.0) if kind == 0 else rng.uniform(0.8, 2.5)
        xy, d = strip.scatter(rng, (0.4, 1.2) if kind == 0 else (0.8, 2.0), 1.5)
        n = len(d)
        radius, height = rng.uniform(0.7, 1.8, n), tall * rng.uniform(0.6, 1.25, n)
        bushes(solids, rng, xy, ground_z(ground, road, xy, d), radius, height)
    spacing = {0: (5.0, 14.0), 1: (1.8, 4.0), 2: (5.0, 10.0)}[kind]
    deeper = Strip(road, strip.side, strip.others, strip.s, (strip.d[0] + 0.5, strip.d[1] + 3.0))
    xy, d = deeper.scatter(rng, spacing, 3.0)
    trees(solids, rng, xy, ground_z(ground, road, xy, d), FOREST_TREE if kind == 1 else STREET_TREE)
