"""Building blocks for objects inside their label boxes: segments along the heading, wheels as discs, limbs as
stacks of short vertical cylinders. Positions are in each object's frame: `along` its heading (+ the front),
`across` to its left; heights are absolute z (the sensor frame). Every helper takes K objects at once."""

from __future__ import annotations

import numpy as np

from lidar.sim.raycast import Num, SolidList

DISC_CORNER = 0.7  # a disc is two crossed boxes: +-radius one way, +-0.7 radius the other (an octagon)


def parts(boxes: np.ndarray) -> tuple[np.ndarray, ...]:
    """(K, 7) boxes -> (K,) each: bottom z, length, width, height, yaw."""
    return boxes[:, 2] - boxes[:, 5] / 2, boxes[:, 3], boxes[:, 4], boxes[:, 5], boxes[:, 6]


def offset(boxes: np.ndarray, along: Num, across: Num = 0.0) -> np.ndarray:
    """(K, 7) boxes, metres along each heading and to its left (scalars or (K,)) -> (K, 2) points."""
    c, s = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
    return boxes[:, :2] + np.stack([along * c - across * s, along * s + across * c], 1)


def segment(
    solids: SolidList,
    boxes: np.ndarray,
    span: tuple[Num, Num],
    z: tuple[Num, Num],
    width: Num,
    refl: Num,
    porosity: Num = 0.0,
    across: Num = 0.0,
    material: Num | None = None,
) -> None:
    """One box per object, from span[1] to span[0] metres along its heading (front > rear)."""
    front, rear = span
    centre = offset(boxes, (np.asarray(front) + rear) / 2, across)
    length = np.asarray(front) - rear
    solids.boxes(centre, z[0], z[1], length, width, boxes[:, 6], refl, porosity, material)


def disc(
    solids: SolidList,
    boxes: np.ndarray,
    along: Num,
    across: Num,
    bottom: Num,
    radius: Num,
    width: Num,
    refl: Num,
    porosity: Num = 0.0,
    material: Num | None = None,
) -> None:
    """A wheel standing on `bottom`, its axle across the heading: two crossed boxes, round enough at LiDAR
    resolution (a corner lies 0.99 radius from the hub)."""
    r = np.asarray(radius)
    for long, high in ((DISC_CORNER, 1.0), (1.0, DISC_CORNER)):
        span = (along + long * r, along - long * r)
        z = (bottom + (1 - high) * r, bottom + (1 + high) * r)
        segment(solids, boxes, span, z, width, refl, porosity, across, material)


def limb(
    solids: SolidList,
    boxes: np.ndarray,
    start: tuple[Num, Num, Num],
    end: tuple[Num, Num, Num],
    radius: Num,
    refl: Num,
    pieces: int = 4,
) -> None:
    """A slanted limb from `start` to `end` ((along, across, z) each, scalars or (K,)) as `pieces` short
    vertical cylinders stacked along the line."""
    k = len(boxes)
    t0 = np.arange(pieces) / pieces  # (n,) where each piece starts along the limb
    s = [np.broadcast_to(np.asarray(v, np.float64), (k,)) for v in start]
    e = [np.broadcast_to(np.asarray(v, np.float64), (k,)) for v in end]
    mid = [a[:, None] + (b - a)[:, None] * (t0 + 0.5 / pieces) for a, b in zip(s, e, strict=True)]  # (K, n)
    za = s[2][:, None] + (e[2] - s[2])[:, None] * t0  # (K, n) piece ends in z
    zb = za + (e[2] - s[2])[:, None] / pieces
    rep = np.repeat(boxes, pieces, axis=0)  # (K*n, 7)
    centre = offset(rep, mid[0].reshape(-1), mid[1].reshape(-1))
    r = np.broadcast_to(np.asarray(radius, np.float64), (k,))
    refl_k = np.broadcast_to(np.asarray(refl, np.float64), (k,))
    lo, hi = np.minimum(za, zb).reshape(-1), np.maximum(za, zb).reshape(-1)
    solids.cylinders(centre, lo, hi, np.repeat(r, pieces), np.repeat(refl_k, pieces))
