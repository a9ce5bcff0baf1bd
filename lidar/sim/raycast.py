"""Vectorized ray casting of a spinning LiDAR through solids (yawed boxes, vertical cylinders).

Ray (f, b) is firing f at azimuth -pi + (f + 0.5) * 2pi / F (plus beam b's azimuth offset, if any) and beam b
at elevation `elevations[b]` (descending); its index is f * B + b, which is firing order. It starts at the
origin, or at `Rays.origin[f]` when the sensor moves during the turn. Each solid is culled to the firings
inside its azimuth span and the beams inside its elevation span (widened by the offsets and by how far the
sensor moves), so only those ray/solid pairs are tested (no Python loop over rays or solids).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from functools import cached_property

import numpy as np

BOX, CYLINDER = 0, 1
# what a ray does at a porous solid's surface (`Solids.material`): OPAQUE solids stop every ray; a ray that a
# VOLUME solid (foliage) stops returns from a leaf inside it; a SURFACE solid (glass, a wire mesh, spokes)
# lets rays through at random and returns from its face
OPAQUE, VOLUME, SURFACE = 0, 1, 2
# a porous solid (foliage) returns from a leaf at a random depth inside it, exponential with this mean (m),
# as real crowns and hedges give a volume of returns rather than a surface
VOLUME_DEPTH = 0.4


@dataclass(frozen=True)
class Solids:
    """Vertical prisms in the sensor frame: boxes rotated about z, and vertical cylinders."""

    kind: np.ndarray  # (P,) int8 BOX or CYLINDER
    centre: np.ndarray  # (P, 2) float64 x, y
    z: np.ndarray  # (P, 2) float64 bottom, top
    half: np.ndarray  # (P, 2) float64 box: half length, half width; cylinder: radius, radius
    yaw: np.ndarray  # (P,) float64 box heading (cylinder: 0)
    reflectivity: np.ndarray  # (P,) float64 in [0, 1]
    porosity: np.ndarray  # (P,) float64 chance that a ray passes through (foliage, spokes, glass)
    material: np.ndarray  # (P,) int8 OPAQUE, VOLUME or SURFACE

    def __len__(self) -> int:
        return int(self.kind.shape[0])

    def select(self, keep: np.ndarray) -> Solids:
        return Solids(*(getattr(self, f.name)[keep] for f in fields(self)))


@dataclass(frozen=True)
class Rays:
    """The firing pattern of one turn: F firings x B beams."""

    azimuth: np.ndarray  # (F,) float64, increasing from -pi
    elevation: np.ndarray  # (B,) float64 radians, descending
    azimuth_offset: np.ndarray | None = None  # (B,) float64 radians added to each beam's azimuth
    origin: np.ndarray | None = None  # (F, 3) float64 where each firing starts; None: the origin

    @staticmethod
    def spinning(
        firings: int,
        elevations_deg: np.ndarray,
        azimuth_offset_deg: np.ndarray | None = None,
        origin: np.ndarray | None = None,
    ) -> Rays:
        az = -math.pi + (np.arange(firings) + 0.5) * (2 * math.pi / firings)
        offset = (
            None if azimuth_offset_deg is None else np.radians(np.asarray(azimuth_offset_deg, np.float64))
        )
        return Rays(az, np.radians(np.asarray(elevations_deg, np.float64)), offset, origin)

    @property
    def count(self) -> int:
        return len(self.azimuth) * len(self.elevation)

    def directions(self, f: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(Q,) firing and beam indices -> unit directions dx, dy, dz, each (Q,) float32."""
        ce, se = np.cos(self.elevation).astype(np.float32), np.sin(self.elevation).astype(np.float32)
        if self.azimuth_offset is None:
            ca, sa = np.cos(self.azimuth).astype(np.float32), np.sin(self.azimuth).astype(np.float32)
            return ce[b] * ca[f], ce[b] * sa[f], se[b]
        ray = f * len(self.elevation) + b  # (Q,)
        return self._horizontal_directions[0][ray], self._horizontal_directions[1][ray], se[b]

    @cached_property
    def _horizontal_directions(self) -> tuple[np.ndarray, np.ndarray]:
        """(R,) float32 x, y of every ray's unit direction (with azimuth offsets: one table, not trig per
        ray/solid pair)."""
        offset = np.zeros(len(self.elevation)) if self.azimuth_offset is None else self.azimuth_offset
        az = (self.azimuth[:, None] + offset[None, :]).reshape(-1)  # (R,)
        ce = np.tile(np.cos(self.elevation), len(self.azimuth))  # (R,)
        return (ce * np.cos(az)).astype(np.float32), (ce * np.sin(az)).astype(np.float32)

    @cached_property
    def _starts(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        o = np.zeros((len(self.azimuth), 3)) if self.origin is None else self.origin
        return o[:, 0].astype(np.float32), o[:, 1].astype(np.float32), o[:, 2].astype(np.float32)

    def starts(self, f: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(Q,) firing indices -> where their rays start: x, y, z (Q,) float32 each (zeros: the origin)."""
        if self.origin is None:
            zero = np.zeros(len(f), np.float32)
            return zero, zero, zero
        x, y, z = self._starts
        return x[f], y[f], z[f]

    def reach(self) -> tuple[np.ndarray, float, float, float]:
        """The culling margins: the middle of the rays' starts (3,), how far they lie from it (horizontal,
        vertical, metres) and the largest azimuth offset (radians)."""
        az = 0.0 if self.azimuth_offset is None else float(np.abs(self.azimuth_offset).max(initial=0.0))
        if self.origin is None:
            return np.zeros(3), 0.0, 0.0, az
        o = self.origin
        mid = (o.min(axis=0) + o.max(axis=0)) / 2  # (3,)
        d = o - mid
        return mid, float(np.hypot(d[:, 0], d[:, 1]).max()), float(np.abs(d[:, 2]).max()), az


@dataclass(frozen=True)
class Hits:
    """The nearest solid hit of some rays."""

    ray: np.ndarray  # (H,) int64 ray index f * B + b
    t: np.ndarray  # (H,) float32 range (metres)
    cos: np.ndarray  # (H,) float32 |cos| of the incidence angle
    solid: np.ndarray  # (H,) int64 index into the Solids


def _box_footprint(s: Solids) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Box solids -> azimuth half-open span (lo, hi) around the centre direction, rho_min, rho_max."""
    c, sn = np.cos(s.yaw), np.sin(s.yaw)  # (P,)
    signs = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]], np.float64)  # (4, 2)
    lx, ly = signs[None, :, 0] * s.half[:, None, 0], signs[None, :, 1] * s.half[:, None, 1]  # (P, 4)
    cx = s.centre[:, None, 0] + lx * c[:, None] - ly * sn[:, None]  # (P, 4) corners
    cy = s.centre[:, None, 1] + lx * sn[:, None] + ly * c[:, None]
    mid = np.arctan2(s.centre[:, 1], s.centre[:, 0])  # (P,)
    rel = np.angle(np.exp(1j * (np.arctan2(cy, cx) - mid[:, None])))  # (P, 4) in (-pi, pi]
    ox = -(s.centre[:, 0] * c + s.centre[:, 1] * sn)  # sensor in the box frame
    oy = s.centre[:, 0] * sn - s.centre[:, 1] * c
    gap = np.maximum(np.abs(np.stack([ox, oy], 1)) - s.half, 0.0)  # (P, 2)
    rho_min = np.hypot(gap[:, 0], gap[:, 1])
    rho_max = np.hypot(cx, cy).max(axis=1)
    return mid + rel.min(axis=1), mid + rel.max(axis=1), rho_min, rho_max


def _spans(s: Solids) -> tuple[np.ndarray, ...]:
    """(P,) azimuth lo, hi (radians, lo may be < -pi, hi > pi), elevation lo, hi (radians)."""
    box = s.kind == BOX
    az_lo, az_hi, rho_min, rho_max = _box_footprint(s)
    dist = np.hypot(s.centre[:, 0], s.centre[:, 1])  # cylinders
    mid = np.arctan2(s.centre[:, 1], s.centre[:, 0])
    half = np.arcsin(np.clip(s.half[:, 0] / np.maximum(dist, 1e-9), 0.0, 1.0))
    az_lo, az_hi = np.where(box, az_lo, mid - half), np.where(box, az_hi, mid + half)
    rho_min = np.where(box, rho_min, np.maximum(dist - s.half[:, 0], 0.0))
    rho_max = np.where(box, rho_max, dist + s.half[:, 0])
    around = rho_min <= 1e-9  # the sensor is inside the footprint: every azimuth
    az_lo, az_hi = np.where(around, -math.pi, az_lo), np.where(around, math.pi, az_hi)
    z0, z1 = s.z[:, 0], s.z[:, 1]
    el_hi = np.arctan2(z1, np.where(z1 > 0, rho_min, rho_max))
    el_lo = np.arctan2(z0, np.where(z0 < 0, rho_min, rho_max))
    return az_lo, az_hi, el_lo, el_hi


def _inflated(s: Solids, mid: np.ndarray, grow: float, grow_z: float) -> Solids:
    """The solids moved by -mid (3,) and grown by `grow` metres sideways and `grow_z` up and down: every ray
    that starts within that reach of `mid` and hits a solid also passes through its moved, grown copy as seen
    from the origin."""
    if grow == 0 and grow_z == 0 and not mid.any():
        return s
    z = s.z - mid[2] + np.array([-grow_z, grow_z])
    return replace(s, centre=s.centre - mid[:2], z=z, half=s.half + grow)


def ray_pairs(s: Solids, rays: Rays) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Candidate pairs: (Q,) solid index, firing index, beam index (firings and beams in the solid's span)."""
    firings = len(rays.azimuth)
    mid, grow, grow_z, az_margin = rays.reach()
    az_lo, az_hi, el_lo, el_hi = _spans(_inflated(s, mid, grow, grow_z))
    az_lo, az_hi = az_lo - az_margin, az_hi + az_margin
    step = 2 * math.pi / firings
    f0 = np.ceil((az_lo + math.pi) / step - 0.5 - 1e-9).astype(np.int64)  # (P,)
    f1 = np.floor((az_hi + math.pi) / step - 0.5 + 1e-9).astype(np.int64)
    nf = np.clip(f1 - f0 + 1, 0, firings)
    neg = -rays.elevation  # ascending
    b0 = np.searchsorted(neg, -el_hi - 1e-9, side="left")
    nb = np.searchsorted(neg, -el_lo + 1e-9, side="right") - b0
    counts = nf * np.maximum(nb, 0)  # (P,)
    solid = np.repeat(np.arange(len(s)), counts)  # (Q,)
    local = np.arange(int(counts.sum())) - np.repeat(np.cumsum(counts) - counts, counts)  # (Q,)
    nbq = nb[solid]
    f = (f0[solid] + local // nbq) % firings
    b = b0[solid] + local % nbq
    return solid, f, b


def _box_walls(
    s: Solids, solid: np.ndarray, cx: np.ndarray, cy: np.ndarray, dx: np.ndarray, dy: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Box pairs (centres cx, cy relative to the ray's start): entry, exit (Q,) of each ray through the
    footprint, |cos| (Q,) against the entry wall."""
    hl, hw = s.half[solid, 0].astype(np.float32), s.half[solid, 1].astype(np.float32)
    c, sn = np.cos(s.yaw[solid]).astype(np.float32), np.sin(s.yaw[solid]).astype(np.float32)
    lx, ly = dx * c + dy * sn, -dx * sn + dy * c  # direction in the box frame
    ox, oy = -(cx * c + cy * sn), cx * sn - cy * c  # sensor in the box frame
    with np.errstate(divide="ignore", invalid="ignore"):
        ix = 1 / np.where(np.abs(lx) < 1e-12, np.float32(1e-12), lx)
        iy = 1 / np.where(np.abs(ly) < 1e-12, np.float32(1e-12), ly)
        tx0, tx1 = (-hl - ox) * ix, (hl - ox) * ix
        ty0, ty1 = (-hw - oy) * iy, (hw - oy) * iy
    txn, tyn = np.minimum(tx0, tx1), np.minimum(ty0, ty1)
    t_out = np.minimum(np.maximum(tx0, tx1), np.maximum(ty0, ty1))
    return np.maximum(txn, tyn), t_out, np.where(txn >= tyn, np.abs(lx), np.abs(ly))


def _cylinder_wall(
    s: Solids, solid: np.ndarray, cx: np.ndarray, cy: np.ndarray, dx: np.ndarray, dy: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cylinder pairs (centres cx, cy relative to the ray's start): entry, exit (Q,) of each ray through the
    disc |t d - c| <= r, |cos| (Q,) at entry."""
    r = s.half[solid, 0].astype(np.float32)
    a = dx * dx + dy * dy
    b = dx * cx + dy * cy
    disc = b * b - a * (cx * cx + cy * cy - r * r)
    root = np.sqrt(np.maximum(disc, 0))
    t_in = np.where(disc >= 0, (b - root) / a, np.inf).astype(np.float32)
    t_out = np.where(disc >= 0, (b + root) / a, -np.inf).astype(np.float32)
    with np.errstate(invalid="ignore"):  # rays that miss: inf - inf
        cos = np.abs((t_in * dx - cx) * dx + (t_in * dy - cy) * dy) / r
    return t_in, t_out, np.nan_to_num(cos, nan=0.0, posinf=0.0)


def _horizontal(
    s: Solids, solid: np.ndarray, cx: np.ndarray, cy: np.ndarray, dx: np.ndarray, dy: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Entry, exit (Q,) of each ray through its solid's footprint, and |cos| (Q,) against the entry wall."""
    t_in, t_out, cos = (np.empty(len(solid), np.float32) for _ in range(3))
    box = s.kind[solid] == BOX
    for sel, walls in ((box, _box_walls), (~box, _cylinder_wall)):
        i = np.flatnonzero(sel)
        t_in[i], t_out[i], cos[i] = walls(s, solid[i], cx[i], cy[i], dx[i], dy[i])
    return t_in, t_out, cos


def cast_solids(s: Solids, rays: Rays, range_min: float, rng: np.random.Generator) -> Hits:
    """The nearest hit of every ray that hits a solid (porous solids let rays through at random)."""
    solid, f, b = ray_pairs(s, rays)
    dx, dy, dz = rays.directions(f, b)  # (Q,) each
    ox, oy, oz = rays.starts(f)  # (Q,) each
    cx = s.centre[solid, 0].astype(np.float32) - ox  # (Q,) solid centres relative to the ray's start
    cy = s.centre[solid, 1].astype(np.float32) - oy
    t_in, t_out, cos = _horizontal(s, solid, cx, cy, dx, dy)
    with np.errstate(divide="ignore", invalid="ignore"):
        iz = 1 / np.where(np.abs(dz) < 1e-12, np.float32(1e-12), dz)
        tz0 = (s.z[solid, 0].astype(np.float32) - oz) * iz
        tz1 = (s.z[solid, 1].astype(np.float32) - oz) * iz
    tzn, tzf = np.minimum(tz0, tz1), np.maximum(tz0, tz1)
    cos = np.where(tzn > t_in, np.abs(dz), cos)
    t_in, t_out = np.maximum(t_in, tzn), np.minimum(t_out, tzf)
    hit = (t_in <= t_out) & (t_in >= range_min)
    porous = s.porosity[solid[hit]]
    keep = np.flatnonzero(hit)[rng.random(len(porous)) >= porous]  # (H0,)
    ray = f[keep] * len(rays.elevation) + b[keep]
    t = t_in[keep]
    inside = np.flatnonzero(s.material[solid[keep]] == VOLUME)  # foliage: the leaf a ray meets lies inside
    depth = rng.exponential(VOLUME_DEPTH, len(inside)).astype(np.float32)
    t[inside] += np.minimum(depth, t_out[keep][inside] - t[inside])
    return nearest(ray, t, cos[keep], solid[keep], rays.count)


def nearest(ray: np.ndarray, t: np.ndarray, cos: np.ndarray, solid: np.ndarray, n_rays: int) -> Hits:
    """Keep each ray's nearest hit among many: (H0,) arrays -> Hits, one per ray, sorted by ray."""
    best = np.full(n_rays, np.inf, np.float32)
    np.minimum.at(best, ray, t)
    winner = np.full(n_rays, -1, np.int64)
    first = np.flatnonzero(t == best[ray])
    winner[ray[first[::-1]]] = first[::-1]  # ties: the first listed hit wins
    rays_hit = np.flatnonzero(winner >= 0)
    w = winner[rays_hit]
    return Hits(rays_hit, t[w], cos[w], solid[w])


Num = float | np.ndarray  # a scalar, or one value per solid of a batch


def material_of(porosity: np.ndarray, material: Num | None) -> np.ndarray:
    """(K,) porosity, a material (scalar, (K,) or None: VOLUME where porous, else OPAQUE) -> (K,) int8."""
    if material is None:
        return np.where(porosity > 0, VOLUME, OPAQUE).astype(np.int8)
    return np.broadcast_to(np.asarray(material, np.int8), porosity.shape).copy()


class SolidList:
    """Collects solids in batches (values broadcast to one per solid), then builds `Solids`."""

    def __init__(self) -> None:
        self._parts: list[tuple[np.ndarray, ...]] = []

    def _add(
        self,
        kind: int,
        centre: np.ndarray,
        z: tuple[Num, Num],
        half: tuple[Num, Num],
        yaw: Num,
        refl: Num,
        porosity: Num,
        material: Num | None,
    ) -> None:
        centre = np.asarray(centre, np.float64).reshape(-1, 2)  # (K, 2)
        n = len(centre)
        col = [np.broadcast_to(np.asarray(a, np.float64), (n,)) for a in (*z, *half, yaw, refl, porosity)]
        kinds = np.full(n, kind, np.int8)
        mat = material_of(col[-1], material)
        self._parts.append((kinds, centre, np.stack(col[:2], 1), np.stack(col[2:4], 1), *col[4:], mat))

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
        """(K, 2) centres; bottom, top, length, width, heading, reflectivity, porosity, material: scalars or
        (K,); material None: VOLUME where porous, else OPAQUE."""
        half = (np.asarray(length) / 2, np.asarray(width) / 2)
        self._add(BOX, centre, (z0, z1), half, yaw, refl, porosity, material)

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
        """(K, 2) centres; bottom, top, radius, reflectivity, porosity, material: scalars or (K,)."""
        self._add(CYLINDER, centre, (z0, z1), (radius, radius), 0.0, refl, porosity, material)

    def build(self) -> Solids:
        if not self._parts:
            empty2 = np.zeros((0, 2))
            zeros = (np.zeros(0) for _ in range(3))
            return Solids(np.zeros(0, np.int8), empty2, empty2, empty2, *zeros, np.zeros(0, np.int8))
        return Solids(*(np.concatenate(cols) for cols in zip(*self._parts, strict=True)))
