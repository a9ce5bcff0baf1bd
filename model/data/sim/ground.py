"""The road surface: a gentle plane plus long smooth bumps, with painted lane lines; rays are cast onto it by
a few Newton steps from the plane's intersection (vectorized over all rays)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from model.data.sim.raycast import Rays

LINE_HALF_WIDTH = 0.075  # metres, painted lane line
DASH, DASH_PERIOD = 3.0, 9.0  # metres painted per period of a dashed line
ASPHALT = (0.08, 0.2)  # reflectivity range of the road surface
PAINT = 0.75
NEWTON_STEPS = 3
MAX_RESIDUAL = 0.02  # metres; a ray whose Newton iteration did not settle is no ground return


@dataclass(frozen=True)
class Ground:
    height: float  # sensor height above the ground under it (the ground at x = y = 0 is z = -height)
    slope: np.ndarray  # (2,) dz/dx, dz/dy
    amplitude: np.ndarray  # (K,) bump amplitudes (m)
    wave: np.ndarray  # (K, 2) wave vectors (rad/m)
    phase: np.ndarray  # (K,)
    asphalt: float  # reflectivity of the road surface
    lines: np.ndarray  # (L, 8) per road: origin x, y, direction x, y, lane width, lanes, gap from, gap to (m)

    def _bumps(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(n,) x, y -> bump height (n,) and its gradient d/dx, d/dy (n,) each, in the dtype of x."""
        h, gx, gy = np.zeros_like(x), np.zeros_like(x), np.zeros_like(x)
        for a, (kx, ky), p in zip(
            self.amplitude.tolist(), self.wave.tolist(), self.phase.tolist(), strict=True
        ):
            arg = kx * x + ky * y + p  # Python floats keep float32 arrays float32
            h += a * np.sin(arg)
            c = a * np.cos(arg)
            gx += c * kx
            gy += c * ky
        return h, gx, gy

    def height_at(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """(n,) x, y in the sensor frame -> (n,) ground z."""
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        base = float((self.amplitude * np.sin(self.phase)).sum())
        return -self.height + self.slope[0] * x + self.slope[1] * y + self._bumps(x, y)[0] - base

    def cast(self, rays: Rays, range_max: float, nearer: np.ndarray) -> np.ndarray:
        """(R,) float32 range to the ground of every ray (index f * B + b), inf where it does not reach it
        or cannot reach it before `nearer` (R,) (the range of its nearest solid, inf if none)."""
        f, b = np.divmod(np.arange(rays.count), len(rays.elevation))
        dx, dy, dz = rays.directions(f, b)  # (R,) each
        sx, sy = float(self.slope[0]), float(self.slope[1])
        rise = sx * dx + sy * dy - dz  # > 0: the ray meets the plane
        offset = self.height + float((self.amplitude * np.sin(self.phase)).sum())
        lowest = self.height - 2 * float(np.abs(self.amplitude).sum())  # the ground is no closer
        with np.errstate(divide="ignore"):
            t_plane = np.where(rise > 1e-4, self.height / rise, np.inf).astype(np.float32)
            t_low = np.where(rise > 1e-4, lowest / rise, np.inf)
        idx = np.flatnonzero((t_plane < 1.5 * range_max) & (t_low < nearer))  # (n,) rays worth refining
        dx, dy, dz, t, rise = dx[idx], dy[idx], dz[idx], t_plane[idx], rise[idx]
        for _ in range(NEWTON_STEPS):
            h, gx, gy = self._bumps(t * dx, t * dy)
            residual = offset - t * rise - h  # ray height above the ground
            t = t - residual / np.minimum(-rise - gx * dx - gy * dy, -1e-4)
        residual = offset - t * rise - self._bumps(t * dx, t * dy)[0]
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
