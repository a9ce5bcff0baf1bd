"""`phim sim` (one simulated scan: a summary line and a bird's-eye-view PNG), `phim sim compare` (simulated
against real scans) and `phim bench sim`."""

from __future__ import annotations

import json
import statistics
import time
from pathlib import Path

import click
import numpy as np

from lidar.sim.sensors import Sensor
from lidar.sim.simulate import SimConfig, simulate
from lidar.types import CLASS_NAMES, LEVEL_1, LEVEL_2, LabeledScan
from phim.options import EnumValue, json_option

sensor_option = click.option(
    "--sensor",
    "sensors",
    type=EnumValue(Sensor),
    multiple=True,
    help="Sensor preset; repeat it to draw one of them per seed [default: hdl64e].",
)


varied_option = click.option(
    "--varied",
    is_flag=True,
    help="Draw the sensor side per seed (SimConfig.varied(): height, beam errors, noise, intensity, motion); "
    "--sensor limits the presets drawn.",
)


def _config(sensors: tuple[Sensor, ...], varied: bool = False) -> SimConfig:
    if varied:
        return SimConfig.varied(**({"sensors": tuple(sensors)} if sensors else {}))
    if not sensors:
        return SimConfig()
    if len(sensors) == 1:
        return SimConfig(sensor=sensors[0])
    return SimConfig(sensors=tuple(sensors))


def summary(scan: LabeledScan, seconds: float) -> str:
    """One line: points, boxes per class, LEVEL_1 / LEVEL_2 / empty boxes, time."""
    gt = scan.gt
    per_class = " ".join(f"{name} {int((gt.labels == i).sum())}" for i, name in enumerate(CLASS_NAMES))
    hit = gt.num_points > 0
    l1, l2 = int((hit & (gt.difficulty == LEVEL_1)).sum()), int((hit & (gt.difficulty == LEVEL_2)).sum())
    return (
        f"{scan.name}: {len(scan.points)} points, boxes {per_class} "
        f"(LEVEL_1 {l1}, LEVEL_2 {l2}, no points {int((~hit).sum())}), {seconds * 1e3:.0f} ms"
    )


def draw_scan(path: Path, scan: LabeledScan, extent_m: float = 50.0) -> Path:
    """BEV PNG: points coloured by height, label boxes coloured by class (LEVEL_2 dashed, empty dotted)."""
    from lidar.pictures import CLASS_COLOURS, bev_axes, box_corners, save_figure

    plt, fig, ax = bev_axes(scan.points, extent_m)
    gt = scan.gt
    for corners, label, n, level in zip(
        box_corners(gt.boxes), gt.labels, gt.num_points, gt.difficulty, strict=True
    ):
        ring = np.vstack([corners, corners[:1]])
        style = ":" if n == 0 else ("--" if level == LEVEL_2 else "-")
        ax.plot(ring[:, 0], ring[:, 1], color=CLASS_COLOURS[CLASS_NAMES[label].lower()], lw=1.0, ls=style)
    for i, name in enumerate(CLASS_NAMES):
        ax.plot([], [], color=CLASS_COLOURS[name.lower()], label=f"{name} {int((gt.labels == i).sum())}")
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title(f"{scan.name}: {len(scan.points)} points (LEVEL_2 dashed, no points dotted)", fontsize=9)
    return save_figure(plt, fig, path)


@click.group(invoke_without_command=True)
@click.option("--seed", type=int, default=0, show_default=True, help="Scene seed.")
@sensor_option
@varied_option
@click.option(
    "--png", type=click.Path(dir_okay=False, path_type=Path), help="Write the bird's-eye view here."
)
@click.option("--extent", type=click.FloatRange(1.0), default=50.0, show_default=True, help="Half width (m).")
@click.pass_context
def sim_cmd(
    ctx: click.Context, seed: int, sensors: tuple[Sensor, ...], varied: bool, png: Path | None, extent: float
) -> None:
    """Simulate one LiDAR turn through a random street scene and summarize it."""
    if ctx.invoked_subcommand is not None:
        return
    start = time.perf_counter()
    scan = simulate(seed, _config(sensors, varied))
    click.echo(summary(scan, time.perf_counter() - start))
    if png is not None:
        click.echo(f"wrote {draw_scan(png, scan, extent)}")


@sim_cmd.command("compare")
@click.option(
    "--seeds", type=click.IntRange(1), default=10, show_default=True, help="Simulated scans per sensor."
)
@click.option(
    "--sensor",
    "sensors",
    type=EnumValue(Sensor),
    multiple=True,
    help="Sensor preset (repeatable) [default: those with real samples: hdl64e, hdl32e, vlp32c-pair].",
)
@click.option(
    "--samples",
    type=click.Path(file_okay=False, path_type=Path),
    default=None,
    help="The real LiDAR samples [default: lidar.samples.SAMPLES_DIR]; missing: simulated rows only.",
)
@click.option(
    "--png",
    type=click.Path(dir_okay=False, path_type=Path),
    help="Also draw simulated HDL-64E scan --png-seed beside real KITTI scan --png-frame here.",
)
@click.option("--png-seed", type=int, default=24, show_default=True, help="Simulated seed of the picture.")
@click.option("--png-frame", type=click.IntRange(0, 5), default=5, show_default=True, help="KITTI frame.")
def compare_cmd(
    seeds: int,
    sensors: tuple[Sensor, ...],
    samples: Path | None,
    png: Path | None,
    png_seed: int,
    png_frame: int,
) -> None:
    """Simulated scans against the real samples: ranges, heights, intensity, clutter, pedestrians seen
    only above their legs (Markdown tables)."""
    from lidar.samples import SAMPLES_DIR
    from lidar.sim.compare import (
        REAL,
        REAL_FOR,
        RealSet,
        compare,
        draw_side_by_side,
        format_tables,
        real_clouds,
        sim_clouds,
    )
    from phim.progress import Progress, note

    root = SAMPLES_DIR if samples is None else samples
    chosen = sensors or tuple(REAL_FOR)
    missing = [REAL[REAL_FOR[s]].folder for s in chosen if s in REAL_FOR]
    missing = [folder for folder in missing if not (root / folder).is_dir()]
    if missing and samples is not None:  # asked for these samples: they must be there
        raise click.BadParameter(f"{root}: no {', '.join(missing)} in it", param_hint="--samples")
    if missing:
        note(
            "sim compare",
            f"the real samples are not all in {root} (PHIM_SAMPLES_DIR; README, Quick start): no real rows "
            f"for {', '.join(missing)}, simulated rows only there",
        )
    Progress("sim compare")(
        f"simulating {seeds} scans per sensor ({len(chosen)} sensors) and reading the real ones"
    )
    click.echo(format_tables(compare(chosen, seeds, root)))
    if png is not None:
        real = real_clouds(RealSet.KITTI, root)[png_frame]
        sim = sim_clouds(REAL[RealSet.KITTI].sim, range(png_seed, png_seed + 1))[0]
        titles = (f"simulated HDL-64E, seed {png_seed}", f"real KITTI {png_frame:06d}")
        click.echo(f"wrote {draw_side_by_side(png, sim, real, titles)}")


@click.command()
@click.option(
    "--seeds", type=click.IntRange(1), default=20, show_default=True, help="Timed scans, seeds 1..N."
)
@sensor_option
@varied_option
@json_option
def bench_sim_cmd(seeds: int, sensors: tuple[Sensor, ...], varied: bool, as_json: bool) -> None:
    """Simulator throughput, single-threaded: scans per second over N seeds."""
    cfg = _config(sensors, varied)
    simulate(0, cfg)
    seconds, points, boxes = [], [], []
    for seed in range(1, seeds + 1):
        start = time.perf_counter()
        scan = simulate(seed, cfg)
        seconds.append(time.perf_counter() - start)
        points.append(len(scan.points))
        boxes.append(np.bincount(scan.gt.labels, minlength=len(CLASS_NAMES)))
    per_class = np.mean(boxes, axis=0)
    result = {
        "sensor": ("varied:" if varied else "")
        + (",".join(s.value for s in sensors) or ("all" if varied else Sensor.HDL64E.value)),
        "scans": seeds,
        "scans_per_s": seeds / sum(seconds),
        "mean_ms": 1e3 * statistics.fmean(seconds),
        "p50_ms": 1e3 * statistics.median(seconds),
        "max_ms": 1e3 * max(seconds),
        "mean_points": statistics.fmean(points),
        **{f"mean_{name.lower()}": float(per_class[i]) for i, name in enumerate(CLASS_NAMES)},
    }
    if as_json:
        click.echo(json.dumps(result))
        return
    for key, value in result.items():
        click.echo(f"{key:>18}  {value:.1f}" if isinstance(value, float) else f"{key:>18}  {value}")
