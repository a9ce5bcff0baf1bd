"""PEDESTRIAN and CYCLIST shapes inside their label boxes (docs/simulator.md).

A pedestrian is articulated: two legs from the hips to the feet (toes ahead), a torso whose chest leans ahead
of the hips, two arms swinging against the legs, a head; standing or walking at any phase of the stride,
which the label box's length gives (the box is tight: the stride fills it). Some carry a backpack or a bag
at the side, or push a stroller (an unlabelled object ahead of the box). A cyclist is a rider on a bicycle
(spoked wheels and a frame, mostly see-through) or on a motorcycle (solid), pedalling or with feet on the
pegs.
"""

from __future__ import annotations

import math

import numpy as np

from lidar.sim import stats
from lidar.sim.parts import FURNITURE, TaggedSolidList
from lidar.sim.raycast import SURFACE, SolidList
from lidar.sim.shapes import disc, limb, offset, parts, segment

PLAIN, BACKPACK, HANDBAG, STROLLER = range(4)  # what a pedestrian carries
CARRIES = (0.6, 0.2, 0.15, 0.05)  # their shares
STANDING = 0.3  # share of pedestrians standing still
STRIDE = 0.37  # metres: the largest reach of a foot ahead of the hips for a 1.75 m walker
TOE, HEEL, BAG_DEPTH, SIDE_BAG = 0.2, 0.08, 0.15, 0.12  # metres, for a 1.75 m person
BICYCLE, MOTORCYCLE = 0, 1


def _clothes(rng: np.random.Generator, k: int) -> np.ndarray:
    return rng.uniform(0.05, 0.5, k)


def _extent(a: np.ndarray, front: np.ndarray, back: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Length of a walker whose feet reach `a` ahead and behind the hips, torso `front`/`back` of them."""
    return np.maximum(a + TOE * s, front) + np.maximum(a + HEEL * s, back)


def pedestrian_sizes(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3) tight label sizes (length from the pose, width from the shoulders and what is carried,
    height from `stats.PEDESTRIAN`) and (n,) what each carries."""
    h = stats.PEDESTRIAN.draw(rng, n)[:, 2]
    s = h / 1.75
    carry = rng.choice(len(CARRIES), n, p=CARRIES)
    walking = rng.random(n) >= STANDING
    a = np.where(walking, STRIDE * s * np.abs(np.sin(rng.uniform(0, math.pi, n))), rng.uniform(0, 0.05, n))
    back = 0.12 * s + (carry == BACKPACK) * BAG_DEPTH
    length = _extent(a, 0.2 * s, back, s)
    width = rng.uniform(0.36, 0.46, n) * s + 0.2 * s + (carry == HANDBAG) * SIDE_BAG
    return np.column_stack([length, width, h]), carry


def pedestrian_solids(
    solids: SolidList, rng: np.random.Generator, boxes: np.ndarray, carry: np.ndarray | None = None
) -> None:
    """Every pedestrian of `boxes` (K, 7), carrying `carry` (K,) (None: drawn): the stride and the body fill
    the box."""
    k = len(boxes)
    if k == 0:
        return
    carry = rng.choice(len(CARRIES), k, p=CARRIES) if carry is None else carry
    base, length, w, h, _ = parts(boxes)
    s = h / 1.75
    depth, lean = rng.uniform(0.2, 0.26, k) * s, rng.uniform(0.05, 0.1, k)
    bag = (carry == BACKPACK) * BAG_DEPTH
    front, back = lean + depth / 2, np.maximum(depth / 2, depth / 2 + bag - lean)  # from the hips
    fit = np.minimum(1.0, length / _extent(np.zeros(k), front, back, s))  # a box too short: squeeze
    depth, lean, bag, s_u = depth * fit, lean * fit, bag * fit, s * fit
    front, back = lean + depth / 2, np.maximum(depth / 2, depth / 2 + bag - lean)  # from the hips
    a = _stride(length, front, back, s_u)
    centre = (np.maximum(a + HEEL * s_u, back) - np.maximum(a + TOE * s_u, front)) / 2  # hips, along
    side = np.where(rng.random(k) < 0.5, -1.0, 1.0)  # the side of a bag, and the leg ahead
    handbag = (carry == HANDBAG) * SIDE_BAG
    across = -side * handbag / 2  # hips, across
    arm = 0.045 * s
    shoulders = np.maximum(w - handbag - 4 * arm, 0.2)
    hip, chest, neck = base + 0.5 * h, base + 0.62 * h, base + 0.83 * h
    clothes, skin = _clothes(rng, k), rng.uniform(0.2, 0.4, k)
    legs = rng.uniform(0.6, 1.0, k) * clothes
    for leg in (-1.0, 1.0):  # leg +1 reaches ahead on the `side` side
        foot = centre + leg * a
        v = across + leg * side * 0.1 * s
        limb(solids, boxes, (centre, v, hip), (foot, v, base + 0.08), 0.07 * s_u, legs, 5)
        _foot(solids, boxes, (foot, v), s_u, np.where((leg < 0) & (a > 0.1), 0.06, 0.0), legs)
        hand = centre + lean / 2 - 0.5 * leg * a  # arms swing against the legs
        va = across + leg * side * (shoulders / 2 + arm)
        pushing = carry == STROLLER
        hand = np.where(pushing, length / 2 - arm, hand)
        hand_z = np.where(pushing, base + 0.55 * h, base + 0.47 * h)
        limb(solids, boxes, (centre + lean, va, neck - 0.03), (hand, va, hand_z), arm, clothes, 4)
    hips = (centre + depth / 2, centre - depth / 2)
    segment(solids, boxes, hips, (hip, chest), shoulders * 0.85, clothes, across=across)
    chest_span = (centre + lean + depth / 2, centre + lean - depth / 2)
    segment(solids, boxes, chest_span, (chest, neck), shoulders, clothes, across=across)
    head = offset(boxes, centre + lean, across)
    solids.cylinders(head, neck, base + h, np.minimum(0.1 * s, depth / 2 + 0.02), skin)
    at = (centre + lean - depth / 2, side * (w / 2 - handbag / 2))
    _carried(solids, rng, boxes, carry, at, (chest, neck, bag))


def _stride(length: np.ndarray, front: np.ndarray, back: np.ndarray, s: np.ndarray) -> np.ndarray:
    """(K,) how far each foot reaches from the hips so that the walker's extent fills `length`
    (bisection; 0 where even standing fills it)."""
    lo, hi = np.zeros(len(length)), np.full(len(length), 0.6)
    for _ in range(20):
        mid = (lo + hi) / 2
        over = _extent(mid, front, back, s) > length
        lo, hi = np.where(over, lo, mid), np.where(over, mid, hi)
    return lo


def _foot(
    solids: SolidList,
    boxes: np.ndarray,
    at: tuple[np.ndarray, np.ndarray],
    s: np.ndarray,
    heel_up: np.ndarray,
    refl: np.ndarray,
) -> None:
    """A foot whose ankle is `at` (along, across): toes ahead on the ground, the heel behind raised by
    `heel_up` (the foot behind pushing off)."""
    foot, v = at
    base = boxes[:, 2] - boxes[:, 5] / 2
    ball = foot + 0.06 * s
    segment(solids, boxes, (foot + TOE * s, ball), (base, base + 0.08), 0.1, refl, across=v)
    heel = (base + heel_up, base + 0.08 + heel_up)
    segment(solids, boxes, (ball, foot - HEEL * s), heel, 0.1, refl, across=v)


def _carried(
    solids: SolidList,
    rng: np.random.Generator,
    boxes: np.ndarray,
    carry: np.ndarray,
    at: tuple[np.ndarray, np.ndarray],
    z: tuple[np.ndarray, np.ndarray, np.ndarray],
) -> None:
    """Backpacks on the back of the chest (`at[0]`), bags at the side (`at[1]` across), strollers ahead."""
    base, length, _, h, _ = parts(boxes)
    rear, side = at
    chest, neck, depth = z
    b = carry == BACKPACK
    refl = rng.uniform(0.1, 0.5, len(boxes))
    segment(solids, boxes[b], (rear[b], rear[b] - depth[b]), (chest[b] - 0.05, neck[b] - 0.05), 0.3, refl[b])
    g = carry == HANDBAG
    z_bag = (base[g] + 0.3 * h[g], base[g] + 0.5 * h[g])
    segment(solids, boxes[g], (0.15, -0.15), z_bag, SIDE_BAG - 0.01, refl[g], across=side[g])
    p = carry == STROLLER
    if not p.any():
        return
    tagged = isinstance(solids, TaggedSolidList)
    tag = solids.tag if tagged else 0
    if tagged:
        solids.tag = FURNITURE  # the stroller is not part of the pedestrian's label
    sb, front = boxes[p], length[p] / 2
    segment(solids, sb, (front + 0.95, front + 0.3), (base[p] + 0.3, base[p] + 0.9), 0.5, refl[p])
    handle = (base[p] + 0.5, base[p] + 0.55 * h[p])  # clear of the pedestrian's own box
    segment(solids, sb, (front + 0.3, front + 0.1), handle, 0.45, 0.2, 0.7, material=SURFACE)
    for u in (0.4, 0.85):
        for s in (-1.0, 1.0):
            disc(solids, sb, front + u, s * 0.22, base[p], 0.1, 0.04, 0.1)
    if tagged:
        solids.tag = tag


def cyclist_sizes(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3) label sizes and (n,) kinds: bicycles (`stats.CYCLIST`) or motorcycles (`stats.MOTORCYCLE`)."""
    kind = (rng.random(n) < stats.MOTORCYCLE_SHARE).astype(np.int64)
    size = np.where(kind[:, None] == MOTORCYCLE, stats.MOTORCYCLE.draw(rng, n), stats.CYCLIST.draw(rng, n))
    return size, kind


def cyclist_solids(
    solids: SolidList, rng: np.random.Generator, boxes: np.ndarray, kind: np.ndarray | None = None
) -> None:
    """Every cyclist of `boxes` (K, 7): a rider on a bicycle or a motorcycle (`kind` (K,), None: bicycles)."""
    kind = np.zeros(len(boxes), np.int64) if kind is None else kind
    for k, build in ((BICYCLE, _bicycle), (MOTORCYCLE, _motorcycle)):
        sel = kind == k
        if sel.any():
            build(solids, rng, boxes[sel])


def _rider(
    solids: SolidList,
    rng: np.random.Generator,
    b: np.ndarray,
    seat: tuple[np.ndarray, np.ndarray],
    feet: tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]],
    grip: tuple[np.ndarray, np.ndarray, np.ndarray],
    head_r: np.ndarray,
) -> None:
    """Legs from the seat (along, z) to the feet ((along, z) per side), a torso leaning from the hips to the
    shoulders ahead of them, arms to the grips (along, half width, z), a head (a helmet for motorcyclists)."""
    k = len(b)
    base, length, w, h, _ = parts(b)
    su, sz = seat
    clothes = _clothes(rng, k)
    for i, s in enumerate((-1.0, 1.0)):
        fu, fz = feet[i]
        knee_u, knee_z = np.maximum(su, fu) + 0.18, (sz + fz) / 2 + 0.12
        limb(solids, b, (su, s * 0.1, sz), (knee_u, s * 0.12, knee_z), 0.075, clothes, 3)
        limb(solids, b, (knee_u, s * 0.12, knee_z), (fu, s * 0.12, fz), 0.06, clothes, 3)
    shoulder_z = base + h - 2 * head_r - 0.05
    shoulder_u = np.minimum(su + 0.4, grip[0] - 0.15)
    torso_w = np.minimum(rng.uniform(0.38, 0.45, k), w - 0.12)
    for j in range(3):
        f = (j + 0.5) / 3
        u = su + (shoulder_u - su) * f
        z = (sz + (shoulder_z - sz) * j / 3, sz + (shoulder_z - sz) * (j + 1) / 3)
        segment(solids, b, (u + 0.11, u - 0.11), z, torso_w, clothes)
    gu, gw, gz = grip
    for s in (-1.0, 1.0):
        limb(
            solids,
            b,
            (shoulder_u, s * (torso_w / 2 + 0.03), shoulder_z - 0.03),
            (gu, s * gw, gz),
            0.045,
            clothes,
            3,
        )
    head = offset(b, np.minimum(shoulder_u + 0.06, length / 2 - head_r))
    solids.cylinders(head, shoulder_z + 0.05, base + h, head_r, rng.uniform(0.2, 0.5, k))


def _bicycle(solids: SolidList, rng: np.random.Generator, b: np.ndarray) -> None:
    """Spoked wheels (mostly see-through), a thin frame, a handlebar, a rider pedalling at a random phase."""
    k = len(b)
    base, length, w, _h, _ = parts(b)
    r = np.minimum(0.34, length * 0.19)
    for u in (length / 2 - r, -length / 2 + r):
        disc(solids, b, u, 0.0, base, r, 0.05, rng.uniform(0.2, 0.4, k), 0.6, SURFACE)
    frame = rng.uniform(0.3, 0.6, k)
    segment(
        solids,
        b,
        (length / 2 - r, -length / 2 + r),
        (base + r, base + r + 0.35),
        0.05,
        frame,
        0.6,
        material=SURFACE,
    )
    bar, grip = length / 2 - r - 0.05, base + rng.uniform(0.95, 1.1, k)
    bar_w = np.minimum(rng.uniform(0.5, 0.6, k), w)
    segment(solids, b, (bar + 0.04, bar - 0.04), (grip - 0.04, grip), bar_w, 0.4)
    seat_u, seat_z = -0.12 * length, base + rng.uniform(0.9, 1.0, k)
    crank_u, crank_z, phase = -0.03 * length, base + 0.3, rng.uniform(0, 2 * math.pi, k)
    feet = tuple(
        (crank_u + s * 0.17 * np.cos(phase), crank_z + s * 0.17 * np.sin(phase)) for s in (-1.0, 1.0)
    )
    _rider(
        solids, rng, b, (seat_u, seat_z + 0.05), feet, (bar - 0.05, bar_w / 2 - 0.04, grip), np.full(k, 0.1)
    )


def _motorcycle(solids: SolidList, rng: np.random.Generator, b: np.ndarray) -> None:
    """Solid wheels, an engine and tank, a fairing, a seat; the rider sits upright, feet on the pegs, with a
    helmet."""
    k = len(b)
    base, length, w, _h, _ = parts(b)
    r = np.full(k, 0.31)
    paint = rng.uniform(0.1, 0.6, k)
    for u in (length / 2 - r, -length / 2 + r):
        disc(solids, b, u, 0.0, base, r, 0.15, 0.06)
    segment(solids, b, (0.25 * length, -0.15 * length), (base + 0.3, base + 0.8), 0.4, paint)  # engine, tank
    segment(solids, b, (length / 2 - 0.15, 0.25 * length), (base + 0.55, base + 1.1), 0.45, paint)  # fairing
    segment(solids, b, (-0.15 * length, -0.4 * length), (base + 0.6, base + 0.8), 0.3, paint)  # seat, tail
    bar, grip = 0.28 * length, base + rng.uniform(0.95, 1.05, k)
    bar_w = np.minimum(rng.uniform(0.7, 0.8, k), w)
    segment(solids, b, (bar + 0.04, bar - 0.04), (grip - 0.04, grip), bar_w, 0.3)
    seat_u = -0.15 * length
    feet = tuple((-0.02 * length, base + 0.35) for _ in range(2))
    _rider(
        solids, rng, b, (seat_u, base + 0.85), feet, (bar - 0.05, bar_w / 2 - 0.04, grip), np.full(k, 0.14)
    )
