"""Building fronts that are not flat walls: bays that step forward or back, a facade layer of piers and
floor bands around window openings, recessed doors, and an interior wall a few metres behind the facade.

A ray through a window opening meets nothing in the facade: it goes on into the building and returns from
the interior wall (or, where that is dark and porous, from nothing). A few buildings have glass panes that
return a ray now and then (92 % see-through). Coordinates are (s, d): metres along the road, and metres
beyond the back of its sidewalk on one side.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from lidar.sim.ground import Ground
from lidar.sim.layout import Road
from lidar.sim.parts import BUILDING, INTERIOR, WINDOW, TaggedSolidList

THICKNESS = 0.3  # metres, the facade layer
BASEMENT = 0.5  # walls reach this far below the ground


@dataclass(frozen=True)
class FacadeStyle:
    floor: tuple[float, float] = (3.0, 3.6)  # storey height (m)
    ground_floor: tuple[float, float] = (3.4, 4.5)
    window: tuple[float, float] = (0.9, 2.0)  # width
    pier: tuple[float, float] = (0.5, 1.6)  # wall between two windows
    sill: tuple[float, float] = (0.7, 1.0)  # above the floor
    window_height: tuple[float, float] = (1.2, 1.9)
    shopfront_prob: float = 0.5  # tall ground-floor windows with a low sill
    door_prob: float = 0.5  # per bay
    door_recess: tuple[float, float] = (0.3, 1.5)  # behind the facade layer
    cavity: tuple[float, float] = (2.0, 5.0)  # from the facade to the interior wall
    bay: tuple[float, float] = (4.0, 12.0)  # bay length; a bay steps forward or back with chance step_prob
    step_prob: float = 0.4
    step: tuple[float, float] = (-0.8, 1.5)  # metres (positive: further back)
    # a canopy over the sidewalk in front of a shopfront bay (shop awnings, entrance canopies): people walk
    # under them, so a pedestrian's column is not always empty above the head
    awning_prob: float = 0.0  # per shopfront bay
    awning_reach: tuple[float, float] = (1.2, 3.0)  # out from the facade (m), kept 0.5 m short of the curb
    awning_clearance: tuple[float, float] = (2.3, 3.0)  # its underside above the sidewalk (m)


URBAN_FACADE = FacadeStyle(awning_prob=0.7)
HOUSE_FACADE = FacadeStyle((2.6, 3.0), (2.7, 3.1), (0.9, 1.6), (1.0, 2.6), (0.8, 1.0), (1.0, 1.4), 0.0, 1.0)


@dataclass(frozen=True)
class Front:
    """Where a building stands: road side, along-road span, distance of its front and its depth (m)."""

    road: Road
    side: int
    s: tuple[float, float]
    setback: float
    depth: float

    def xy(self, s: np.ndarray, d: np.ndarray) -> np.ndarray:
        """(K,) along, (K,) beyond the sidewalk -> (K, 2)."""
        return self.road.outward(self.side, np.asarray(s, np.float64), np.asarray(d, np.float64))


def building(
    solids: TaggedSolidList,
    rng: np.random.Generator,
    front: Front,
    ground: Ground,
    floors: int,
    style: FacadeStyle,
) -> float:
    """A building of `floors` storeys made of bays -> the height of its highest bay above the ground (m)."""
    cuts = [front.s[0]]
    while front.s[1] - cuts[-1] > style.bay[1]:
        cuts.append(cuts[-1] + rng.uniform(*style.bay))
    cuts.append(front.s[1])
    xy = front.xy(np.array([(front.s[0] + front.s[1]) / 2]), np.array([front.setback]))
    z = float(ground.height_at(xy[:, 0], xy[:, 1])[0]) + front.road.curb
    look = _Look.draw(rng, style)
    tallest = 0.0
    for s0, s1 in itertools.pairwise(cuts):
        step = rng.uniform(*style.step) if rng.random() < style.step_prob else 0.0
        n = max(1, floors + (int(rng.integers(-1, 2)) if rng.random() < 0.3 else 0))
        bay = Front(front.road, front.side, (s0, s1), max(0.2, front.setback + step), front.depth)
        tallest = max(tallest, _bay(solids, rng, bay, z, n, look, style))
    return tallest


@dataclass(frozen=True)
class _Look:
    """What one building's bays share."""

    floor: float
    ground_floor: float
    window: float
    pier: float
    sill: float
    window_height: float
    shopfront: bool
    wall: float  # reflectivity
    interior: float
    interior_porosity: float
    cavity: float
    glass: bool

    @staticmethod
    def draw(rng: np.random.Generator, st: FacadeStyle) -> _Look:
        floor = rng.uniform(*st.floor)
        return _Look(
            floor,
            max(floor, rng.uniform(*st.ground_floor)),
            rng.uniform(*st.window),
            rng.uniform(*st.pier),
            rng.uniform(*st.sill),
            min(rng.uniform(*st.window_height), floor - rng.uniform(*st.sill) - 0.3),
            bool(rng.random() < st.shopfront_prob),
            rng.uniform(0.15, 0.6),
            rng.uniform(0.1, 0.4),
            rng.uniform(0.0, 0.8) if rng.random() < 0.4 else 0.0,
            rng.uniform(*st.cavity),
            bool(rng.random() < 0.4),
        )


def _bay(
    solids: TaggedSolidList,
    rng: np.random.Generator,
    f: Front,
    z: float,
    floors: int,
    look: _Look,
    style: FacadeStyle,
) -> float:
    """One bay: piers, floor bands, sills or a recessed door per window slot, the interior wall -> height."""
    length = f.s[1] - f.s[0]
    n = max(1, int((length - look.pier) // (look.window + look.pier)))
    pier = min(look.pier, length / (2 * n + 1))
    window = (length - pier) / n - pier
    top = z + look.ground_floor + (floors - 1) * look.floor + rng.uniform(0.3, 1.2)
    levels = z + look.ground_floor + look.floor * np.arange(floors - 1)  # floors above the ground floor
    sills = np.concatenate([[z + (0.4 if look.shopfront else look.sill)], levels + look.sill])  # (floors,)
    heads = sills + look.window_height  # window tops
    if look.shopfront:
        heads[0] = z + look.ground_floor - 0.5
    solids.tag = BUILDING
    d0, deep = f.setback, THICKNESS + look.cavity
    cols = f.s[0] + pier / 2 + np.arange(n + 1) * (window + pier)  # (n + 1,) pier centres
    depth = np.where(
        (np.arange(n + 1) == 0) | (np.arange(n + 1) == n), deep, THICKNESS
    )  # ends close the sides
    solids.boxes(f.xy(cols, d0 + depth / 2), z - BASEMENT, top, pier, depth, f.road.yaw, look.wall)
    mid = np.full(floors, (f.s[0] + f.s[1]) / 2)
    upper = np.concatenate([sills[1:], [top]])  # each band: a window head up to the next sill
    solids.boxes(
        f.xy(mid, np.full(floors, d0 + THICKNESS / 2)), heads, upper, length, THICKNESS, f.road.yaw, look.wall
    )
    slots = f.s[0] + pier + window / 2 + np.arange(n) * (window + pier)  # (n,) window centres
    door = np.zeros(n, bool)
    if rng.random() < style.door_prob:
        door[int(rng.integers(n))] = True
    ds = slots[~door]
    solids.boxes(
        f.xy(ds, np.full(len(ds), d0 + THICKNESS / 2)),
        z - BASEMENT,
        sills[0],
        window,
        THICKNESS,
        f.road.yaw,
        look.wall,
    )
    recess = d0 + THICKNESS + rng.uniform(*style.door_recess)
    ds = slots[door]
    solids.boxes(
        f.xy(ds, np.full(len(ds), recess)), z - 0.1, heads[0], window, 0.1, f.road.yaw, rng.uniform(0.1, 0.4)
    )
    if look.shopfront and rng.random() < style.awning_prob:
        _awning(solids, rng, f, z, style)
    _interior(solids, rng, f, (z, top), d0 + deep, look)
    return top - z


def _awning(
    solids: TaggedSolidList, rng: np.random.Generator, f: Front, z: float, style: FacadeStyle
) -> None:
    """A canopy in front of a bay: a thin roof out over the sidewalk and a valance hanging at its edge."""
    reach = min(rng.uniform(*style.awning_reach), f.setback + f.road.sidewalk - 0.5)
    if reach <= f.setback:
        return  # the facade stands too far back for it to reach the sidewalk
    low = z + rng.uniform(*style.awning_clearance)
    along, length = np.array([(f.s[0] + f.s[1]) / 2]), f.s[1] - f.s[0] - 0.2
    refl = rng.uniform(0.15, 0.5)
    roof = f.xy(along, np.array([f.setback - reach / 2]))
    solids.boxes(roof, low, low + 0.1, length, reach, f.road.yaw, refl)
    valance = rng.uniform(0.2, 0.4)
    edge = f.xy(along, np.array([f.setback - reach + 0.03]))
    solids.boxes(edge, low - valance, low + 0.1, length, 0.06, f.road.yaw, refl)


def _interior(
    solids: TaggedSolidList,
    rng: np.random.Generator,
    f: Front,
    z: tuple[float, float],
    back: float,
    look: _Look,
) -> None:
    """The interior wall from `back` to the building's rear, and the glass panes of a glazed building."""
    rear = max(back + 1.0, f.setback + f.depth)
    mid = np.array([(f.s[0] + f.s[1]) / 2])
    length = f.s[1] - f.s[0]
    solids.tag = INTERIOR
    centre = f.xy(mid, np.array([(back + rear) / 2]))
    solids.boxes(
        centre, z[0] - BASEMENT, z[1], length, rear - back, f.road.yaw, look.interior, look.interior_porosity
    )
    if look.glass:
        solids.tag = WINDOW
        pane = f.xy(mid, np.array([f.setback + THICKNESS / 2]))
        solids.boxes(pane, z[0], z[1], length, 0.02, f.road.yaw, rng.uniform(0.05, 0.15), 0.92)
