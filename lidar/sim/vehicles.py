"""VEHICLE shapes inside their label boxes: cars (sedan, hatchback, SUV, pickup, van) and large vehicles (box
truck, bus, semi-trailer), each composed of boxes and discs (docs/simulator.md).

A car: wheels (discs) in wheel arches, a lower body from the ground clearance to the bonnet, a bonnet lower
than the waist, a glass cabin (mostly see-through: `GLASS_POROSITY`) with pillars, seats behind the glass and
an opaque roof, a raked windscreen and rear window, mirrors, a narrower nose and tail, and retroreflective
tail lights at the back corners. The label box is drawn as annotators draw it: tight around the body and
enclosing its returns, range noise included (`ANNOTATION_MARGIN` beyond the bumpers, body sides and roof;
the tyres stand on its bottom), with the side mirrors standing out of its sides (annotation guides leave
them out: nuScenes' annotator instructions, "Do not include vehicle side view mirrors"). A body whose faces
were the label's would leave half its face returns outside the label, and a label around the mirrors would
teach boxes a mirror's width wider than real labels.
"""

from __future__ import annotations

import numpy as np

from lidar.sim import stats
from lidar.sim.raycast import SURFACE, SolidList
from lidar.sim.shapes import disc, parts, segment

PAINT = np.array([0.06, 0.12, 0.25, 0.35, 0.5, 0.7])  # car paint reflectivities: black .. white
LIGHT_DEPTH = 0.02  # metres: the rear lights fill the back of the label box, the body ends in front of them
GLASS_POROSITY = 0.8  # share of rays that pass through car glass
GLASS_REFL = (0.03, 0.08)  # the few returns glass gives are dark
TYRE_REFL = (0.03, 0.08)
NOSE = 0.12  # metres: the rounded nose and tail, at NOSE_WIDTH of the body's width
NOSE_WIDTH = 0.9
BANDS = 3  # the cabin as this many glass slices, each set back by the windscreen's and rear window's rake
ANNOTATION_MARGIN = 0.04  # metres from the body's front, back, sides and top to the label's faces

# Per car body (stats.SEDAN .. stats.VAN): ranges drawn uniformly per car. wheel: radius (m); clear: ground
# clearance (m); front, rear: axle from the bumper (share of the length); belt: the window sill (share of the
# height); drop: the bonnet below the sill (m); hood: the windscreen's foot from the front (share of the
# length); rake: the windscreen's run (m); back: the cabin's end from the back (share of the length);
# rear_rake: the rear window's run (m); panel: chance of a windowless back (vans).
CAR_SHAPE = {
    "wheel": ((0.30, 0.34), (0.29, 0.33), (0.35, 0.40), (0.38, 0.42), (0.32, 0.36)),
    "clear": ((0.13, 0.17), (0.13, 0.17), (0.19, 0.25), (0.21, 0.27), (0.15, 0.20)),
    "front": ((0.18, 0.21), (0.17, 0.20), (0.17, 0.20), (0.15, 0.18), (0.13, 0.16)),
    "rear": ((0.21, 0.25), (0.14, 0.18), (0.18, 0.22), (0.19, 0.23), (0.17, 0.21)),
    "belt": ((0.62, 0.68), (0.60, 0.66), (0.58, 0.64), (0.57, 0.62), (0.46, 0.52)),
    "drop": ((0.07, 0.15), (0.04, 0.10), (0.02, 0.08), (0.05, 0.10), (0.0, 0.05)),
    "hood": ((0.25, 0.31), (0.21, 0.26), (0.21, 0.25), (0.20, 0.24), (0.09, 0.14)),
    "rake": ((0.55, 0.75), (0.50, 0.70), (0.45, 0.60), (0.45, 0.60), (0.55, 0.80)),
    "back": ((0.17, 0.23), (0.02, 0.05), (0.02, 0.04), (0.33, 0.40), (0.01, 0.03)),
    "rear_rake": ((0.35, 0.55), (0.25, 0.40), (0.05, 0.15), (0.03, 0.08), (0.0, 0.05)),
    "panel": ((0.0, 0.0), (0.0, 0.0), (0.0, 0.0), (0.0, 0.0), (0.5, 0.5)),
}


def _draw(rng: np.random.Generator, kind: np.ndarray, name: str) -> np.ndarray:
    lo, hi = np.asarray(CAR_SHAPE[name]).T  # (5,) each
    return rng.uniform(lo[kind], hi[kind])


def body_kinds(rng: np.random.Generator, large: np.ndarray, trailers: bool = True) -> np.ndarray:
    """(K,) bool large -> (K,) body types: cars by `stats.CAR_BODIES`, large ones by `stats.LARGE_BODIES`
    (without trailers: box trucks and buses only)."""
    car = rng.choice(len(stats.CAR_BODIES), len(large), p=stats.CAR_BODIES)
    share = np.asarray(stats.LARGE_BODIES if trailers else stats.LARGE_BODIES[:2])
    big = stats.BOX_TRUCK + rng.choice(len(share), len(large), p=share / share.sum())
    return np.where(large, big, car)


def body_boxes(boxes: np.ndarray) -> np.ndarray:
    """(K, 7) label boxes -> (K, 7) the boxes the bodies fill: `ANNOTATION_MARGIN` inside every face but the
    bottom."""
    inner = np.array(boxes, np.float64)
    inner[:, 3:5] -= 2 * ANNOTATION_MARGIN
    inner[:, 5] -= ANNOTATION_MARGIN
    inner[:, 2] -= ANNOTATION_MARGIN / 2
    return inner


def vehicle_solids(solids: SolidList, rng: np.random.Generator, boxes: np.ndarray, kind: np.ndarray) -> None:
    """Every vehicle of the label boxes `boxes` (K, 7) as its body type `kind` (K,) says, inside its
    `body_boxes`."""
    boxes = body_boxes(boxes)
    paint = rng.choice(PAINT, len(boxes)) * rng.uniform(0.8, 1.2, len(boxes))
    car = kind <= stats.VAN
    _cars(solids, rng, boxes[car], kind[car], paint[car])
    for k, build in ((stats.BOX_TRUCK, _box_truck), (stats.BUS, _bus), (stats.TRAILER, _trailer)):
        sel = kind == k
        if sel.any():
            build(solids, rng, boxes[sel], paint[sel])


def _lights(solids: SolidList, b: np.ndarray, z: np.ndarray, half_width: np.ndarray) -> None:
    """Retroreflective tail lights at the back corners, 0.3 m wide, their outer edge at `half_width`."""
    back = -b[:, 3] / 2
    for side in (-1.0, 1.0):
        segment(
            solids,
            b,
            (back + LIGHT_DEPTH, back),
            (z - 0.08, z + 0.08),
            0.3,
            1.0,
            across=side * (half_width - 0.15),
        )


def _wheels(
    solids: SolidList,
    rng: np.random.Generator,
    b: np.ndarray,
    axles: list[np.ndarray],
    r: np.ndarray,
    wb: np.ndarray,
    tyre: float,
) -> None:
    """Two wheels per axle (along positions (K,) each), their outer faces at the body's sides."""
    base, k = b[:, 2] - b[:, 5] / 2, len(b)
    refl = rng.uniform(*TYRE_REFL, k)
    for axle in axles:
        for side in (-1.0, 1.0):
            disc(solids, b, axle, side * (wb / 2 - tyre / 2), base, r, tyre, refl)


def _cars(
    solids: SolidList, rng: np.random.Generator, b: np.ndarray, kind: np.ndarray, paint: np.ndarray
) -> None:
    """Cars of body types `kind` (K,) in boxes `b` (K, 7), as the module docstring describes."""
    k = len(b)
    if k == 0:
        return
    base, length, w, h, _ = parts(b)
    d = {name: _draw(rng, kind, name) for name in CAR_SHAPE}
    half, top = length / 2, base + h
    mirror = rng.uniform(0.08, 0.12, k)  # beyond the body's sides
    wb = w  # the body's width
    r, clear = np.minimum(d["wheel"], 0.3 * h), base + d["clear"]
    af, ar = half - d["front"] * length, -half + d["rear"] * length  # axles
    ra = r + 0.05  # wheel arch
    belt = base + d["belt"] * h
    hood = belt - d["drop"]
    ws = half - d["hood"] * length  # the windscreen's foot
    pickup = kind == stats.PICKUP
    ce = -half + d["back"] * length  # the cabin's end
    floor = np.maximum(clear + 0.1, belt - 0.45)  # a pickup's bed
    split = np.clip(np.where(pickup, ce - 0.1, (af + ar) / 2), ar + ra + 0.05, af - ra - 0.05)
    tail = -half + LIGHT_DEPTH
    rear_top = np.where(pickup, floor, hood)
    arch = base + 2 * r + 0.04
    lower = (  # (front, rear, bottom, top) along the body below the bonnet line, which rises to the cowl
        (half - NOSE, af + ra, clear, hood - 0.06),
        (af + ra, af - ra, arch, hood - 0.03),
        (af - ra, split, clear, hood),
        (split, ar + ra, clear, rear_top),
        (ar + ra, ar - ra, arch, rear_top),
        (ar - ra, tail + NOSE, clear, rear_top),
    )
    for front, rear, lo, hi in lower:
        segment(solids, b, (front, rear), (lo, hi), wb, paint)
    for u in (af, ar):  # dark wheel-arch liners between the wheels
        segment(solids, b, (u + ra, u - ra), (clear, arch), wb - 0.5, 0.05)
    segment(solids, b, (half, half - NOSE), (clear + 0.08, hood - 0.12), NOSE_WIDTH * wb, paint)
    tail_top = np.where(pickup, belt, belt - 0.04)
    segment(solids, b, (tail + NOSE, tail), (clear + 0.08, tail_top), NOSE_WIDTH * wb, paint)
    waist_end = np.where(pickup, ce - 0.1, tail + NOSE)
    segment(solids, b, (ws, waist_end), (hood, belt), wb, paint)  # from the windscreen back, to the sill
    _bed(solids, b[pickup], (ce - 0.1)[pickup], floor[pickup], belt[pickup], wb[pickup], paint[pickup])
    _cabin(solids, rng, b, (ws, d["rake"], ce, d["rear_rake"]), (belt, top), wb, paint, d["panel"])
    for side in (-1.0, 1.0):  # mirrors stand out of the body's (and the label box's) sides
        segment(
            solids,
            b,
            (ws - 0.05, ws - 0.25),
            (belt, belt + 0.14),
            mirror,
            paint,
            across=side * (wb + mirror) / 2,
        )
    _wheels(solids, rng, b, [af, ar], r, wb, 0.22)
    _lights(solids, b, base + d["clear"] + rng.uniform(0.4, 0.6, k), NOSE_WIDTH * wb / 2)


def _cabin(
    solids: SolidList,
    rng: np.random.Generator,
    b: np.ndarray,
    line: tuple[np.ndarray, ...],
    z: tuple[np.ndarray, np.ndarray],
    wb: np.ndarray,
    paint: np.ndarray,
    panel: np.ndarray,
) -> None:
    """The glass cabin from the sill to the roof: BANDS slices whose front follows the raked windscreen and
    whose back the rear window, opaque pillars at their corners (listed first: they win ties with the glass),
    seats behind the glass, a roof on top; a windowless back behind the B pillar with chance `panel`."""
    ws, rake, ce, rear_rake = line
    belt, top = z
    k = len(b)
    roof = top - 0.05
    gw = 0.92 * wb
    side = gw / 2 - 0.04
    front_u, back_u = ws - rake, ce + rear_rake  # the roof's ends
    mid = (front_u + back_u) / 2  # the B pillar
    glass_refl = rng.uniform(*GLASS_REFL, k)
    windowless = rng.random(k) < panel
    for j in range(BANDS):
        z0, z1 = belt + (roof - belt) * j / BANDS, belt + (roof - belt) * (j + 1) / BANDS
        f = ws - rake * (j + 0.5) / BANDS
        r = ce + rear_rake * (j + 0.5) / BANDS
        for s in (-1.0, 1.0):
            segment(solids, b, (f, f - 0.1), (z0, z1), 0.09, paint, across=s * side)  # A pillar
            segment(solids, b, (r + 0.2, r), (z0, z1), 0.09, paint, across=s * side)  # C pillar
        segment(solids, b, (f, r), (z0, z1), gw, glass_refl, GLASS_POROSITY, material=SURFACE)
    for s in (-1.0, 1.0):
        segment(solids, b, (mid + 0.06, mid - 0.06), (belt, roof), 0.09, paint, across=s * side)
    panel_b = b[windowless]
    segment(
        solids,
        panel_b,
        (mid[windowless], back_u[windowless]),
        (belt[windowless], roof[windowless]),
        gw[windowless],
        paint[windowless],
    )
    seat = rng.uniform(0.05, 0.15, k)
    segment(solids, b, (front_u - 0.35, front_u - 0.5), (belt - 0.05, belt + 0.3), 0.8 * wb, seat)
    segment(solids, b, (back_u + 0.4, back_u + 0.25), (belt - 0.05, belt + 0.25), 0.8 * wb, seat)
    segment(solids, b, (front_u, back_u), (roof, top), gw, paint)


def _bed(
    solids: SolidList,
    b: np.ndarray,
    front: np.ndarray,
    floor: np.ndarray,
    top: np.ndarray,
    wb: np.ndarray,
    paint: np.ndarray,
) -> None:
    """A pickup's open bed from `front` to the back: the floor (the lower body's top), side walls and a
    tailgate up to the sill."""
    back = -b[:, 3] / 2 + LIGHT_DEPTH + NOSE
    for side in (-1.0, 1.0):
        segment(solids, b, (front, back), (floor, top), 0.08, paint, across=side * (wb / 2 - 0.04))
    segment(solids, b, (back + 0.06, back), (floor, top), wb, paint)


def _glass_band(
    solids: SolidList, rng: np.random.Generator, b: np.ndarray, span: tuple, z: tuple, width: np.ndarray
) -> None:
    """Glass from span[1] to span[0] along the heading, z[0] to z[1] high."""
    refl = rng.uniform(*GLASS_REFL, len(b))
    segment(solids, b, span, z, width, refl, GLASS_POROSITY, material=SURFACE)


def _box_truck(solids: SolidList, rng: np.random.Generator, b: np.ndarray, paint: np.ndarray) -> None:
    """A cab (windscreen and side windows above its sill) lower than the cargo box behind it, the box on a
    chassis with dual rear wheels, tail lights at the bottom of the box."""
    k = len(b)
    base, length, w, h, _ = parts(b)
    half, tail = length / 2, -length / 2 + LIGHT_DEPTH
    mirror = rng.uniform(0.12, 0.2, k)  # beyond the body's sides
    wb = w
    r = rng.uniform(0.45, 0.52, k)
    cab_end = half - np.minimum(2.3, 0.3 * length)
    cab_top = base + np.maximum(h * rng.uniform(0.7, 0.85, k), 2.2)
    sill = base + rng.uniform(1.3, 1.6, k)
    af, ar = half - 1.2, -half + 0.25 * length
    arch = base + 2 * r + 0.05
    segment(solids, b, (half, af + r + 0.05), (base + 0.35, sill), wb, paint)
    segment(solids, b, (af + r + 0.05, cab_end), (arch, sill), wb, paint)
    for s in (-1.0, 1.0):
        segment(
            solids, b, (half, half - 0.12), (sill, cab_top - 0.1), 0.12, paint, across=s * (wb / 2 - 0.06)
        )
    segment(solids, b, (half - 0.6, half - 1.3), (sill - 0.1, sill + 0.5), 0.8 * wb, 0.1)  # seats
    _glass_band(solids, rng, b, (half, cab_end), (sill, cab_top - 0.1), wb)
    segment(solids, b, (half, cab_end), (cab_top - 0.1, cab_top), wb, paint)
    deck = base + rng.uniform(0.9, 1.15, k)
    segment(solids, b, (cab_end - 0.15, tail), (deck, base + h), wb, paint)
    segment(solids, b, (cab_end, tail), (base + 0.4, deck), 0.9, 0.05)  # chassis rails
    segment(solids, b, (tail + 0.1, tail), (base + 0.45, base + 0.6), wb, 0.3)  # underrun bar
    for s in (-1.0, 1.0):
        segment(
            solids, b, (half - 1.4, half - 1.7), (sill, sill + 0.5), mirror, 0.3, across=s * (wb + mirror) / 2
        )
    _wheels(solids, rng, b, [af, ar], r, wb, 0.45)
    _lights(solids, b, deck - 0.1, wb / 2)


def _bus(solids: SolidList, rng: np.random.Generator, b: np.ndarray, paint: np.ndarray) -> None:
    """A bus: a lower body with wheel arches, a band of windows (pillars every 1.3 m, seats behind them), a
    roof band, an opaque back with tail lights."""
    k = len(b)
    base, length, w, h, _ = parts(b)
    half, tail = length / 2, -length / 2 + LIGHT_DEPTH
    mirror = rng.uniform(0.12, 0.18, k)  # beyond the body's sides
    wb = w
    r = rng.uniform(0.48, 0.52, k)
    af, ar = half - 2.6, -half + 3.1
    ra, clear = r + 0.06, base + 0.3
    belt = base + h * rng.uniform(0.32, 0.38, k)
    roof = base + h * rng.uniform(0.84, 0.9, k)
    arch = base + 2 * r + 0.05
    for front, rear, lo in (
        (half, af + ra, clear),
        (af + ra, af - ra, arch),
        (af - ra, ar + ra, clear),
        (ar + ra, ar - ra, arch),
        (ar - ra, tail + 0.3, clear),
    ):
        segment(solids, b, (front, rear), (lo, belt), wb, paint)
    segment(solids, b, (tail + 0.3, tail), (clear, base + h), wb, paint)  # the back
    n = int(np.ceil(length.max() / 1.3))
    for i in range(n):  # window pillars along both sides, up to the back
        u = half - 0.8 - 1.3 * i
        ok = u - 0.08 > tail + 0.3
        for s in (-1.0, 1.0):
            span, z = (u[ok] + 0.08, u[ok] - 0.08), (belt[ok], roof[ok])
            segment(solids, b[ok], span, z, 0.1, paint[ok], across=s * (wb[ok] / 2 - 0.05))
    segment(solids, b, (half - 1.5, tail + 0.5), (belt, belt + 0.55), 0.85 * wb, 0.1)  # seat backs
    _glass_band(solids, rng, b, (half, tail + 0.3), (belt, roof), wb)
    segment(solids, b, (half, tail + 0.3), (roof, base + h), wb, paint)
    for s in (-1.0, 1.0):
        segment(
            solids,
            b,
            (half - 0.05, half - 0.35),
            (roof - 0.6, roof - 0.2),
            mirror,
            0.3,
            across=s * (wb + mirror) / 2,
        )
    segment(solids, b, (af, ar), (base + 0.2, clear), wb - 1.0, 0.05)  # underfloor
    _wheels(solids, rng, b, [af, ar], r, wb, 0.3)
    _lights(solids, b, clear + 0.6, wb / 2)


def _trailer(solids: SolidList, rng: np.random.Generator, b: np.ndarray, paint: np.ndarray) -> None:
    """A parked semi-trailer: a cargo box on a high deck, two or three rear axles, landing legs near the
    front, retroreflective tape along the sides and tail lights at the back."""
    k = len(b)
    base, length, w, h, _ = parts(b)
    half, tail = length / 2, -length / 2 + LIGHT_DEPTH
    deck = base + rng.uniform(1.1, 1.3, k)
    segment(solids, b, (half, tail), (deck, base + h), w, paint)
    segment(solids, b, (half - 0.5, tail), (deck - 0.3, deck), 1.0, 0.05)  # chassis rails
    for s in (-1.0, 1.0):
        segment(solids, b, (half - 2.3, half - 2.5), (base, deck - 0.3), 0.15, 0.2, across=s * 0.8)  # legs
        segment(
            solids,
            b,
            (half - 0.3, tail + 0.3),
            (deck + 0.05, deck + 0.1),
            0.02,
            1.0,
            across=s * (w / 2 - 0.01),
        )
    r = np.full(k, 0.5)
    axles = [-half + 1.4 + 1.3 * i for i in range(2)]
    _wheels(solids, rng, b, axles, r, w, 0.5)
    segment(solids, b, (tail + 0.1, tail), (base + 0.45, base + 0.6), w, 0.3)  # underrun bar
    _lights(solids, b, deck - 0.1, w / 2)


def utility_trailer_solids(solids: SolidList, rng: np.random.Generator, b: np.ndarray) -> None:
    """Small parked trailers (not labelled: hard negatives the size of a car's lower half): a drawbar at the
    front, a bed with low sides (a closed box with chance 0.3), one axle in the middle."""
    k = len(b)
    if k == 0:
        return
    base, length, w, h, _ = parts(b)
    half = length / 2
    bar = half - rng.uniform(0.9, 1.2, k)  # the bed starts behind the drawbar
    r = rng.uniform(0.22, 0.3, k)
    deck = base + 2 * r + 0.05
    refl = rng.uniform(0.1, 0.5, k)
    segment(solids, b, (half, bar), (deck - 0.15, deck - 0.05), 0.12, 0.3)  # drawbar
    segment(solids, b, (bar, -half), (deck, deck + 0.05), w - 0.3, refl)  # floor
    for s in (-1.0, 1.0):
        segment(solids, b, (bar, -half), (deck, base + h), 0.05, refl, across=s * (w / 2 - 0.175))
    segment(solids, b, (bar, bar - 0.05), (deck, base + h), w - 0.3, refl)
    segment(solids, b, (-half + 0.05, -half), (deck, base + h), w - 0.3, refl)
    covered = rng.random(k) < 0.3  # a box trailer
    z = (deck[covered], (base + h)[covered])
    segment(solids, b[covered], (bar[covered], -half[covered]), z, (w - 0.3)[covered], refl[covered])
    mid = (bar - half) / 2
    for s in (-1.0, 1.0):
        disc(solids, b, mid, s * (w / 2 - 0.08), base, r, 0.16, 0.05)
