"""The road surface: a gentle plane plus long smooth bumps and the crossfall (camber) of the sensor's road,
with painted lane lines; rays are cast onto it by a few Newton steps from the plane's intersection
(vectorized over all rays)."""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from lidar.sim.raycast import Rays

LINE_HALF_WIDTH = 0.075  # metres, painted lane line
DASH, DASH_PERIOD = 3.0, 9.0  # metres painted per period of a dashed line
ASPHALT = (0.08, 0.2)  # reflectivity range of the road surface
PAINT = 0.75
NEWTON_STEPS = 3
MAX_RESIDUAL = 0.02  # metres; a ray whose Newton iteration did not settle is no ground return
CROWN_ROUNDING = 0.5  # metres: the crown of a cambered road is rounded over about this lateral distance


@dataclass(frozen=True)
class Ground:
    height: float  # sensor height above the ground under it (the ground at x = y = 0 is z = -height)
    slope: np.ndarray  # (2,) dz/dx, dz/dy
    amplitude: np.ndarray  # (K,) bump amplitudes (m)
    wave: np.ndarray  # (K, 2) wave vectors (rad/m)
    phase: np.ndarray  # (K,)
    asphalt: float  # reflectivity of the road surface
    lines: np.ndarray  # (L, 8) per road: origin x, y, direction x, y, lane width, lanes, gap from, gap to (m)
    # (C, 7) cambered roads: origin x, y, direction x, y, crossfall (drop per metre from the centre line),
    # lateral offsets of the right and left curbs (m; the drop stops growing there)
    crowns: np.ndarray = field(default_factory=lambda: np.zeros((0, 7)))

    def _bumps(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(n,) x, y -> relief height (n,) (bumps minus the camber drop) and its gradient d/dx, d/dy (n,)
        each, in the dtype of x."""
        h, gx, gy = self._camber(x, y)
        for a, (kx, ky), p in zip(
            self.amplitude.tolist(), self.wave.tolist(), self.phase.tolist(), strict=True
        ):
            arg = kx * x + ky * y + p  # Python floats keep float32 arrays float32
            h += a * np.sin(arg)
            c = a * np.cos(arg)
            gx += c * kx
            gy += c * ky
        return h, gx, gy

    def _camber(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(n,) x, y -> minus the camber drop (n,): fall * (sqrt(lat^2 + a^2) - a), lateral offsets clipped to
        the curbs, and its gradient (n,) each."""
        h, gx, gy = np.zeros_like(x), np.zeros_like(x), np.zeros_like(x)
        a2 = CROWN_ROUNDING**2
        for ox, oy, ux, uy, fall, right, left in self.crowns.tolist():
            lat = np.clip(-(x - ox) * uy + (y - oy) * ux, right, left)
            root = np.sqrt(lat * lat + a2)
            h -= fall * (root - CROWN_ROUNDING)
            inside = (lat > right) & (lat < left)
            dlat = np.where(inside, -fall * lat / root, 0.0).astype(x.dtype)  # d h / d lateral
            gx -= dlat * uy
            gy += dlat * ux
        return h, gx, gy

    def _relief(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """(n,) x, y -> the relief height of `_bumps` without its gradient (n,)."""
        h = np.zeros_like(x)
        for ox, oy, ux, uy, fall, right, left in self.crowns.tolist():
            lat = np.clip(-(x - ox) * uy + (y - oy) * ux, right, left)
            h -= fall * (np.sqrt(lat * lat + CROWN_ROUNDING**2) - CROWN_ROUNDING)
        for a, (kx, ky), p in zip(
            self.amplitude.tolist(), self.wave.tolist(), self.phase.tolist(), strict=True
        ):
            h += a * np.sin(kx * x + ky * y + p)
        return h

    @cached_property
    def _relief_origin(self) -> float:
        """The relief height under the sensor (x = y = 0)."""
        return float(self._relief(np.zeros(1), np.zeros(1))[0])

    def height_at(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """(n,) x, y in the sensor frame -> (n,) ground z."""
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        base = self._relief_origin
        return -self.height + self.slope[0] * x + self.slope[1] * y + self._relief(x, y) - base

    def cast(self, rays: Rays, range_max: float, nearer: np.ndarray) -> np.ndarray:
        """(R,) float32 range to the ground of every ray (index f * B + b), inf where it does not reach it
        or cannot reach it before `nearer` (R,) (the range of its nearest solid, inf if none)."""
        f, b = np.divmod(np.arange(rays.count), len(rays.elevation))
        dx, dy, dz = rays.directions(f, b)  # (R,) each
        ox, oy, oz = (np.asarray(v, np.float64) for v in rays.starts(f))  # (R,) each: a moving sensor
        sx, sy = float(self.slope[0]), float(self.slope[1])
        rise = sx * dx + sy * dy - dz  # > 0: the ray meets the plane
        above = self.height + oz - sx * ox - sy * oy  # (R,) the start's height above the plane
        offset = above + self._relief_origin  # (R,)
        reach = np.maximum(-self.crowns[:, 5], self.crowns[:, 6])
        crown = float((self.crowns[:, 4] * reach).sum())  # the most the camber can rise
        lowest = self.height - 2 * float(np.abs(self.amplitude).sum()) - crown  # the ground is no closer
        with np.errstate(divide="ignore"):
            t_plane = np.where(rise > 1e-4, above / rise, np.inf).astype(np.float32)
            t_low = np.where(rise > 1e-4, (lowest + above - self.height) / rise, np.inf)
        idx = np.flatnonzero((t_plane < 1.5 * range_max) & (t_low < nearer))  # (n,) rays worth refining
        dx, dy, t, rise = dx[idx], dy[idx], t_plane[idx], rise[idx]
        ox, oy, offset = ox[idx], oy[idx], offset[idx]
        for _ in range(NEWTON_STEPS):
            h, gx, gy = self._bumps(ox + t * dx, oy + t * dy)
            residual = offset - t * rise - h  # ray height above the ground
            t = t - residual / np.minimum(-rise - gx * dx - gy * dy, -1e-4)
        residual = offset - t * rise - self._bumps(ox + t * dx, oy + t * dy)[0]
        out = np.full(rays.count, np.inf, np.float32)
        ok = (np.abs(residual) < MAX_RESIDUAL) & (t > 0)
        out[idx[ok]] = t[ok]
        return out

    def reflectivity(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """(n,) hit points on the road -> (n,) reflectivity: asphalt, or paint on a lane line (solid centre
        line, dashed lines between lanes, none where another road crosses)."""
        refl = np.full(x.shape, self.asphalt, np.float32)
        for ox, oy, ux, uy, lane_width, lanes, gap_lo, gap_hi in self.lines.tolist():
            s = (x - ox) * ux + (y - oy) * uy  # along the road
            lateral = -(x - ox) * uy + (y - oy) * ux
            k = np.round(lateral / lane_width)  # nearest line: 0 the centre line
            on = (np.abs(lateral - k * lane_width) < LINE_HALF_WIDTH) & (np.abs(k) <= lanes)
            on &= ~((s > gap_lo) & (s < gap_hi)) & ((k == 0) | (np.mod(s, DASH_PERIOD) < DASH))
            refl[on] = PAINT
        return refl
