"""Simulated against real scans: the same statistics of both, per sensor (`phim sim compare`).

Statistics, over all points of all scans of a row:
- points per scan, and the share of points per range bin (metres from the sensor, RANGE_EDGES);
- the share per height bin (metres above the ground under the sensor: z + mounting height, HEIGHT_EDGES);
- intensity: median, 90th percentile and the share per bin (INTENSITY_EDGES); none for Argoverse, whose
  conversion dropped intensities;
- the share of points on clutter: points on anything but the ground and the labelled targets, counted within
  the azimuths the labels cover (KITTI, Argoverse: the front camera's) and beyond EGO_RADIUS of the sensor.
  Simulated scans give it by construction (a point on a solid outside every label box). Real scans give an
  estimate: a point outside every label box and more than GROUND_RISE above the lowest point of its
  GROUND_CELL x GROUND_CELL metre cell. The estimate misses clutter in cells where no ground shows (a wall
  filling its cell) and counts steep ground (a ramp, a curb) as clutter; it is also applied to simulated
  scans (`clutter_est`) so that the two can be compared like for like;
- pedestrians' legs hidden: of the well-seen pedestrians (at least SEEN_POINTS points in the label box,
  within SEEN_RANGE metres), the share with no point in the lowest LEGS metres of the box: people seen
  over a parked car or a low wall, only their upper body showing.
"""

from __future__ import annotations

import enum
import itertools
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lidar.labels import AS_IS
from lidar.readers import read_labeled
from lidar.samples import SAMPLE_FRAMES, SAMPLES_DIR
from lidar.sim.sensors import Sensor, sensor_spec
from lidar.sim.simulate import SimConfig, Source, simulate_sources
from lidar.types import CLASS_NAMES, points_in_boxes

RANGE_EDGES = (0.0, 2.5, 10.0, 20.0, 30.0, 50.0, 80.0, math.inf)  # metres
HEIGHT_EDGES = (-math.inf, 0.3, 1.0, 2.0, 3.0, 5.0, math.inf)  # metres above the ground
INTENSITY_EDGES = (0.0, 0.02, 0.05, 0.1, 0.2, 0.4, 0.99, 1.01)
GROUND_CELL = 2.0  # metres
GROUND_RISE = 0.3  # metres above the cell's lowest point
EGO_RADIUS = 2.5  # metres (horizontal): nearer points are left out of the clutter share (the ego car)
PEDESTRIAN = CLASS_NAMES.index("PEDESTRIAN")
SEEN_POINTS, SEEN_RANGE, LEGS = 20, 50.0, 0.5  # a well-seen pedestrian; metres, metres


class RealSet(enum.StrEnum):
    KITTI = "kitti"  # HDL-64E, kitti_object/velodyne 000000-000005
    NUSCENES = "nuscenes"  # HDL-32E, one sweep
    ARGOVERSE = "argoverse"  # two stacked VLP-32C, three frames


@dataclass(frozen=True)
class RealSource:
    folder: str  # under the samples folder
    pattern: str
    height: float  # metres: the sensor above the ground
    sim: SimConfig  # the simulated sensor to compare with


REAL: dict[RealSet, RealSource] = {
    RealSet.KITTI: RealSource("kitti_object/velodyne", "*.bin", 1.73, SimConfig(sensor=Sensor.HDL64E)),
    RealSet.NUSCENES: RealSource(
        "nuscenes_sample", "*.pcd.bin", 1.84, SimConfig(sensor=Sensor.HDL32E, firings=1085, rate_hz=20.0)
    ),
    RealSet.ARGOVERSE: RealSource(
        "argoverse_kitti_format/velodyne", "*.bin", 1.95, SimConfig(sensor=Sensor.VLP32C_PAIR)
    ),
}
REAL_FOR: dict[Sensor, RealSet] = {REAL[r].sim.sensor: r for r in RealSet}


@dataclass(frozen=True)
class Cloud:
    """One scan made ready for the statistics."""

    points: np.ndarray  # (N, 4) float32 x, y, z, intensity in the sensor frame
    height: float  # metres: the sensor above the ground
    boxes: np.ndarray  # (M, 7) float32 label boxes of the targets
    fov: tuple[float, float] | None  # azimuths the labels cover (None: all around)
    clutter: np.ndarray | None  # (N,) bool, by construction (simulated scans)
    has_intensity: bool = True
    labels: np.ndarray | None = None  # (M,) int64 the boxes' classes (index into CLASS_NAMES)


@dataclass(frozen=True)
class Stats:
    name: str
    scans: int
    points: float  # per scan
    range_share: np.ndarray  # (len(RANGE_EDGES) - 1,)
    height_share: np.ndarray  # (len(HEIGHT_EDGES) - 1,)
    intensity_share: np.ndarray | None  # (len(INTENSITY_EDGES) - 1,)
    intensity_median: float | None
    intensity_p90: float | None
    clutter_est: float  # the estimate (both)
    clutter_true: float | None  # by construction (simulated scans only)
    pedestrians: int  # well-seen pedestrians
    legs_hidden: float | None  # the share of them with no point in their box's lowest LEGS metres


def above_ground(points: np.ndarray) -> np.ndarray:
    """(N, >=3) -> (N,) bool: more than GROUND_RISE above the lowest point of its GROUND_CELL cell."""
    cell = np.floor(points[:, :2] / GROUND_CELL).astype(np.int64)  # (N, 2)
    _, key = np.unique(cell, axis=0, return_inverse=True)
    key = key.reshape(-1)
    lowest = np.full(int(key.max(initial=-1)) + 1, np.inf, np.float32)
    np.minimum.at(lowest, key, points[:, 2])
    return points[:, 2] > lowest[key] + GROUND_RISE


def _counted(cloud: Cloud) -> np.ndarray:
    """(N,) bool: the points the clutter share counts (within the labels' azimuths, beyond EGO_RADIUS)."""
    x, y = cloud.points[:, 0], cloud.points[:, 1]
    keep = np.hypot(x, y) > EGO_RADIUS
    if cloud.fov is not None:
        az = np.arctan2(y, x)
        keep &= (az >= cloud.fov[0]) & (az <= cloud.fov[1])
    return keep


def clutter_counts(cloud: Cloud) -> tuple[int, int, int]:
    """Counted points, estimated clutter among them, clutter by construction among them (0 when unknown)."""
    counted = _counted(cloud)
    p = cloud.points
    outside = (
        ~points_in_boxes(p[:, :3], cloud.boxes).any(axis=1) if len(cloud.boxes) else np.ones(len(p), bool)
    )
    estimate = counted & outside & above_ground(p)
    true = 0 if cloud.clutter is None else int((counted & cloud.clutter).sum())
    return int(counted.sum()), int(estimate.sum()), true


def legs_hidden_counts(cloud: Cloud) -> tuple[int, int]:
    """Well-seen pedestrians of a scan, and how many of them have no point in their box's lowest LEGS m."""
    if cloud.labels is None:
        return 0, 0
    peds = cloud.boxes[cloud.labels == PEDESTRIAN]  # (P, 7)
    inside = points_in_boxes(cloud.points[:, :3], peds)  # (N, P)
    seen = (inside.sum(axis=0) >= SEEN_POINTS) & (np.hypot(peds[:, 0], peds[:, 1]) <= SEEN_RANGE)
    low = cloud.points[:, 2, None] < (peds[:, 2] - peds[:, 5] / 2 + LEGS)[None]  # (N, P)
    hidden = seen & ~(inside & low).any(axis=0)
    return int(seen.sum()), int(hidden.sum())


def _share(values: np.ndarray, edges: tuple[float, ...]) -> np.ndarray:
    counts = np.histogram(values, bins=np.asarray(edges))[0]
    return counts / max(int(counts.sum()), 1)


def cloud_stats(name: str, clouds: list[Cloud]) -> Stats:
    """The statistics of `clouds` together (see the module docstring)."""
    pts = np.concatenate([c.points for c in clouds])  # (N, 4)
    up = np.concatenate([c.points[:, 2] + c.height for c in clouds])
    counts = np.array([clutter_counts(c) for c in clouds]).sum(axis=0)  # (3,)
    seen, hidden = np.array([legs_hidden_counts(c) for c in clouds]).sum(axis=0)
    lit = all(c.has_intensity for c in clouds)
    known = all(c.clutter is not None for c in clouds)
    return Stats(
        name=name,
        scans=len(clouds),
        points=len(pts) / len(clouds),
        range_share=_share(np.linalg.norm(pts[:, :3], axis=1), RANGE_EDGES),
        height_share=_share(up, HEIGHT_EDGES),
        intensity_share=_share(pts[:, 3], INTENSITY_EDGES) if lit else None,
        intensity_median=float(np.median(pts[:, 3])) if lit else None,
        intensity_p90=float(np.percentile(pts[:, 3], 90)) if lit else None,
        clutter_est=counts[1] / max(counts[0], 1),
        clutter_true=counts[2] / max(counts[0], 1) if known else None,
        pedestrians=int(seen),
        legs_hidden=hidden / seen if seen else None,
    )


def sim_clouds(cfg: SimConfig, seeds: range, fov: tuple[float, float] | None = None) -> list[Cloud]:
    """Simulated scans of a fixed `cfg` (one sensor, its preset height), clutter by construction."""
    height = sensor_spec(cfg.sensor, cfg.height).height
    clouds = []
    for seed in seeds:
        scan, source = simulate_sources(seed, cfg)
        inside = points_in_boxes(scan.points[:, :3], scan.gt.boxes).any(axis=1)
        clutter = (source == Source.SOLID) & ~inside
        clouds.append(Cloud(scan.points, height, scan.gt.boxes, fov, clutter, labels=scan.gt.labels))
    return clouds


def real_clouds(which: RealSet, samples: Path = SAMPLES_DIR) -> list[Cloud]:
    """The real scans of a sample set, in the sensor's frame (FileNotFoundError when they are missing)."""
    src = REAL[which]
    paths = sorted((samples / src.folder).glob(src.pattern))
    if not paths:
        raise FileNotFoundError(f"{samples / src.folder}: no {src.pattern} scans (the real LiDAR samples)")
    frame = SAMPLE_FRAMES.get(src.folder.split("/")[0], AS_IS)
    clouds = []
    for path in paths:
        scan = read_labeled(path, frame=frame)
        points = scan.points[:, :4]
        lit = which != RealSet.ARGOVERSE
        clouds.append(Cloud(points, src.height, scan.gt.boxes, scan.label_fov, None, lit, scan.gt.labels))
    return clouds


def compare(sensors: tuple[Sensor, ...], seeds: int, samples: Path = SAMPLES_DIR) -> list[Stats]:
    """Rows: per sensor the simulated scans (seeds 0..N-1), then the real ones where a sample set has that
    sensor and the samples are there. A real set's label azimuths also bound the simulated clutter share."""
    rows = []
    for sensor in sensors:
        which = REAL_FOR.get(sensor)
        real = None
        if which is not None and (samples / REAL[which].folder).is_dir():
            real = real_clouds(which, samples)
        cfg = REAL[which].sim if which is not None else SimConfig(sensor=sensor)
        fov = None if real is None else real[0].fov
        rows.append(cloud_stats(f"sim {sensor}", sim_clouds(cfg, range(seeds), fov)))
        if real is not None:
            rows.append(cloud_stats(f"real {which}", real))
    return rows


def _cells(values: np.ndarray) -> list[str]:
    return [f"{v:.3f}" for v in values]


def _edges(edges: tuple[float, ...]) -> list[str]:
    return [f"{lo:g}-{hi:g}" for lo, hi in itertools.pairwise(edges)]


def format_tables(rows: list[Stats]) -> str:
    """Three Markdown tables: points and ranges; heights; intensity, clutter and pedestrians' legs."""
    head = ["source", "scans"]
    t1 = [[*head, "points/scan", *[f"r {e} m" for e in _edges(RANGE_EDGES)]]]
    t2 = [[*head, *[f"h {e} m" for e in _edges(HEIGHT_EDGES)]]]
    lit_head = ["median", "p90", *[f"i {e}" for e in _edges(INTENSITY_EDGES)]]
    t3 = [[*head, *lit_head, "clutter", "clutter est.", "pedestrians seen", "legs hidden"]]
    for s in rows:
        first = [s.name, str(s.scans)]
        t1.append([*first, f"{s.points:,.0f}", *_cells(s.range_share)])
        t2.append([*first, *_cells(s.height_share)])
        if s.intensity_share is None:
            lit = ["n/a"] * (2 + len(INTENSITY_EDGES) - 1)
        else:
            lit = [f"{s.intensity_median:.3f}", f"{s.intensity_p90:.3f}", *_cells(s.intensity_share)]
        true = "n/a" if s.clutter_true is None else f"{s.clutter_true:.3f}"
        legs = "n/a" if s.legs_hidden is None else f"{s.legs_hidden:.3f}"
        t3.append([*first, *lit, true, f"{s.clutter_est:.3f}", str(s.pedestrians), legs])
    return "\n\n".join(_markdown(t) for t in (t1, t2, t3))


def _markdown(table: list[list[str]]) -> str:
    lines = ["| " + " | ".join(row) + " |" for row in table]
    lines.insert(1, "|" + "---|" * len(table[0]))
    return "\n".join(lines)


def draw_side_by_side(
    path: Path, left: Cloud, right: Cloud, titles: tuple[str, str], extent_m: float = 40.0
) -> Path:
    """A PNG of two bird's-eye views side by side (points coloured by height above the ground, label boxes
    red), e.g. a simulated and a real scan of a similar street."""
    from lidar.pictures import _pyplot, box_corners, save_figure

    plt = _pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(12, 6.2))
    for ax, cloud, title in zip(axes, (left, right), titles, strict=True):
        p = cloud.points
        ax.set_facecolor("black")
        up = np.clip(p[:, 2] + cloud.height, 0.0, 3.0)
        ax.scatter(p[:, 0], p[:, 1], c=up, s=0.15, cmap="viridis", linewidths=0, rasterized=True)
        for corners in box_corners(cloud.boxes):
            ring = np.vstack([corners, corners[:1]])
            ax.plot(ring[:, 0], ring[:, 1], color="tab:red", lw=0.8)
        ax.set_xlim(-extent_m, extent_m)
        ax.set_ylim(-extent_m, extent_m)
        ax.set_aspect("equal")
        ax.set_title(f"{title}: {len(p):,} points", fontsize=9)
        ax.tick_params(labelsize=7)
    return save_figure(plt, fig, path)
