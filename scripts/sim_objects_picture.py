"""Simulated and real objects side by side: docs/pictures/sim-objects-vs-real.png.

A car and a pedestrian at about 10 m and 30 m: the real ones cut from the KITTI scans in the shared samples
with their labels, the simulated ones made by the simulator (lidar/sim) in the same label box and cast
with the HDL-64E preset on a flat street, noise and dropout as in `simulate`. Each row shows one object's
points in its box frame from above and from the side (intensity as colour); the box is drawn dashed.

    .venv/bin/python scripts/sim_objects_picture.py [--out docs/pictures/sim-objects-vs-real.png]
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lidar.readers import read_labeled
from lidar.samples import SAMPLES_DIR
from lidar.sim import Sensor, SimConfig, sensor_spec, stats
from lidar.sim.ground import Ground
from lidar.sim.people import PLAIN, pedestrian_solids
from lidar.sim.raycast import Rays, SolidList
from lidar.sim.scene import Scene
from lidar.sim.simulate import cast_scene
from lidar.sim.vehicles import vehicle_solids

HEIGHT = 1.73  # KITTI's sensor above the road
MARGIN = 0.3  # metres around the box that a panel shows


@dataclass(frozen=True)
class Pick:
    """A labelled object of a KITTI scan and how to simulate one like it."""

    title: str
    scan: str  # file name under kitti_object/velodyne
    index: int  # which box of the scan
    body: int | None  # vehicle body type; None: a pedestrian


PICKS = (
    Pick("car, 13.5 m", "000003.bin", 0, stats.HATCHBACK),
    Pick("car, 34.8 m", "000002.bin", 0, stats.SEDAN),
    Pick("pedestrian, 8.9 m", "000000.bin", 0, None),
    Pick("pedestrian, 24.8 m", "000005.bin", 0, None),
)


def _real(pick: Pick) -> tuple[np.ndarray, np.ndarray]:
    scan = read_labeled(SAMPLES_DIR / "kitti_object" / "velodyne" / pick.scan)
    return scan.points[:, :4], scan.gt.boxes[pick.index].astype(np.float64)


def _simulated(pick: Pick, box: np.ndarray, seed: int) -> np.ndarray:
    """The object in the real label box, on a flat street at the real box's bottom, cast like `simulate`."""
    bottom = box[2] - box[5] / 2
    ground = Ground(-bottom, np.zeros(2), np.zeros(0), np.zeros((0, 2)), np.zeros(0), 0.15, np.zeros((0, 8)))
    rng = np.random.default_rng(seed)
    solids = SolidList()
    if pick.body is None:
        pedestrian_solids(solids, rng, box[None], np.array([PLAIN]))
    else:
        vehicle_solids(solids, rng, box[None], np.array([pick.body]))
    cfg = SimConfig()
    rays = Rays.spinning(cfg.firings, sensor_spec(Sensor.HDL64E).elevations_deg)
    scene = Scene((), ground, solids.build(), box[None], np.zeros(1, np.int64))
    points, _ = cast_scene(rng, scene, rays, cfg)
    return points


def _in_frame(points: np.ndarray, box: np.ndarray) -> np.ndarray:
    """Points near the box, ground left out -> (N, 4) along, across, height above the box bottom and
    intensity."""
    c, s = math.cos(box[6]), math.sin(box[6])
    d = points[:, :2] - box[:2]
    u, v = d[:, 0] * c + d[:, 1] * s, -d[:, 0] * s + d[:, 1] * c
    up = points[:, 2] - (box[2] - box[5] / 2)
    near = (np.abs(u) < box[3] / 2 + MARGIN) & (np.abs(v) < box[4] / 2 + MARGIN) & (up > 0.08)
    near &= up < box[5] + MARGIN
    return np.stack([u, v, up, points[:, 3]], 1)[near]


def _panel(ax, p: np.ndarray, box: np.ndarray, side: bool, title: str) -> None:
    x, y = (p[:, 0], p[:, 2]) if side else (p[:, 0], p[:, 1])
    ax.scatter(x, y, c=p[:, 3], s=4, cmap="viridis", vmin=0, vmax=0.6, linewidths=0)
    hl, other = box[3] / 2, (box[5] if side else box[4] / 2)
    xs = [-hl, hl, hl, -hl, -hl]
    ys = [0, 0, other, other, 0] if side else [-other, -other, other, other, -other]
    ax.plot(xs, ys, "r--", lw=0.8)
    ax.set_aspect("equal")
    ax.set_xlim(-hl - MARGIN, hl + MARGIN)
    ax.set_ylim(-0.1, box[5] + 0.2) if side else ax.set_ylim(-box[4] / 2 - MARGIN, box[4] / 2 + MARGIN)
    ax.set_title(f"{title} ({len(p)} pts)", fontsize=7)
    ax.tick_params(labelsize=6)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("docs/pictures/sim-objects-vs-real.png"))
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(PICKS), 4, figsize=(10, 2.2 * len(PICKS)), dpi=90)
    for row, pick in enumerate(PICKS):
        points, box = _real(pick)
        real = _in_frame(points, box)
        sim = _in_frame(_simulated(pick, box, args.seed + row), box)
        _panel(axes[row, 0], sim, box, False, f"sim {pick.title}, top")
        _panel(axes[row, 1], sim, box, True, f"sim {pick.title}, side")
        _panel(axes[row, 2], real, box, False, f"KITTI {pick.scan} {pick.title}, top")
        _panel(axes[row, 3], real, box, True, f"KITTI {pick.scan}, side")
    fig.suptitle(
        "Simulated (left) and real KITTI (right) objects in the same label box; colour: intensity", fontsize=9
    )
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
