"""`phim loadtest` and `phim replay` (click commands, loaded by the `phim` command, phim/cli.py).

Exit codes: 0 the run completed (and held its thresholds), 1 it failed (a client error, a threshold broken),
2 usage (bad options, missing input)."""

from __future__ import annotations

import dataclasses
import json
import logging
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import click

from clients.loadtest.config import Mode
from clients.options import connect_config, connection_options, every_option
from lidar.samples import KITTI_VELODYNE
from phim.options import EnumValue, json_option
from phim.progress import note

if TYPE_CHECKING:
    from clients.loadtest.config import LoadTestConfig, SourceConfig

T = TypeVar("T")
NewFile = click.Path(dir_okay=False, path_type=Path)
Folder = click.Path(file_okay=False, path_type=Path)


def _vehicles(vehicles: int, sweep: str | None) -> tuple[int, ...]:
    if not sweep:
        return (vehicles,)
    try:
        steps = tuple(int(v) for v in sweep.split(",") if v.strip())
    except ValueError:
        raise click.BadParameter(
            f"{sweep!r}: expected comma-separated vehicle counts, e.g. 1,2,4,8", param_hint="--sweep"
        ) from None
    if not steps or min(steps) < 1:
        raise click.BadParameter(f"{sweep!r}: expected positive vehicle counts", param_hint="--sweep")
    return steps


def _data(data: Path | None, synthetic: bool) -> Path | None:
    if synthetic:
        return None
    if data is not None:
        return data
    if KITTI_VELODYNE.is_dir():
        return KITTI_VELODYNE
    note(
        "loadtest",
        f"the real samples' KITTI scans are not at {KITTI_VELODYNE} (PHIM_SAMPLES_DIR; README, Quick start): "
        "sending synthetic scans instead (--data DIR: scans of your own; --synthetic says so and is quiet)",
    )
    return None


@click.command()
@connection_options
@click.option("--vehicles", type=click.IntRange(1), default=1, show_default=True, help="Simulated vehicles.")
@click.option("--sweep", help="Vehicle counts to step through, e.g. 1,2,4,8 (instead of --vehicles).")
@click.option(
    "--mode",
    type=EnumValue(Mode),
    default=Mode.OPEN.value,
    show_default=True,
    help="open: at sensor rate, latency from each scheduled time; closed: send when answered.",
)
@click.option(
    "--duration",
    type=click.FloatRange(0.1),
    default=10.0,
    show_default=True,
    help="Seconds measured per step.",
)
@click.option(
    "--warmup",
    type=click.FloatRange(0),
    default=0.0,
    show_default=True,
    help="Seconds per step sent the same way before measuring, not counted.",
)
@click.option(
    "--window-s",
    type=click.FloatRange(0.1),
    help="Measure in windows of this many seconds until the last 3 agree (instead of --duration).",
)
@click.option(
    "--stability-pct",
    type=click.FloatRange(0),
    default=10.0,
    show_default=True,
    help="Windows agree when each is within this % of their mean (sectors answered/s and p99).",
)
@click.option(
    "--max-windows",
    type=click.IntRange(3),
    default=10,
    show_default=True,
    help="Windows at most; a step not stable by then fails.",
)
@click.option(
    "--max-p99-ms",
    type=click.FloatRange(0),
    envvar="PHIM_LOADTEST_MAX_P99_MS",
    show_envvar=True,
    help="Threshold: a step passes when its p99 <= this. Any threshold given sets the exit code "
    "[without one: 25 ms and no errors judge the steps, exit code 0].",
)
@click.option(
    "--max-error-rate",
    type=click.FloatRange(0, 1),
    envvar="PHIM_LOADTEST_MAX_ERROR_RATE",
    show_envvar=True,
    help="Threshold: a step passes when the fraction of its sectors answered with an error or lost <= this.",
)
@click.option(
    "--turns-per-s", type=click.FloatRange(0.01), default=10.0, show_default=True, help="Sensor rate."
)
@click.option("--sectors-per-turn", type=click.IntRange(1), help="[default: the served model's]")
@click.option(
    "--data",
    type=click.Path(exists=True, path_type=Path),
    help="A folder of scans (KITTI .bin, nuScenes .pcd.bin, .npz) [default: the KITTI samples if present].",
)
@click.option("--synthetic", is_flag=True, help="Synthetic turns instead of recorded scans.")
@every_option
@click.option(
    "--max-scans", type=click.IntRange(1), default=20, show_default=True, help="Scans read from --data."
)
@click.option(
    "--drain-timeout", type=click.FloatRange(0), default=10.0, show_default=True, help="Wait for replies (s)."
)
@click.option("--keep-going", is_flag=True, help="Sweep on after a step that does not hold.")
@json_option
@click.option("--out", type=NewFile, help="Write the JSON report to this file.")
@click.option("--csv", "csv_path", type=NewFile, help="Write the CSV report to this file.")
@click.option("--plots", type=Folder, help="Write PNG plots into this folder.")
@click.option("--progress/--no-progress", default=True, show_default=True, help="Live progress on stderr.")
@click.option("--seed", type=int, default=0, show_default=True, help="Vehicle start offsets and scan choice.")
@click.option(
    "--stream-prefix",
    default="loadtest",
    show_default=True,
    help="Stream IDs are PREFIX-<tag>-<vehicle> (a --token covers the streams its prefix starts).",
)
@click.option(
    "--stream-tag",
    help="The <tag> of the stream IDs [default: random per step, so reruns never meet streams a server still "
    "holds]; fixed, the IDs (and their workers, --workers auto) are the same every run. Not with --sweep.",
)
def loadtest(
    vehicles: int,
    sweep: str | None,
    data: Path | None,
    synthetic: bool,
    every: int,
    max_scans: int,
    keep_going: bool,
    as_json: bool,
    out: Path | None,
    csv_path: Path | None,
    plots: Path | None,
    progress: bool,
    **options: Any,
) -> None:
    """Simulated vehicles streaming to a server: throughput and latency (open loop at sensor rate by
    default: latency from each sector's scheduled time). Exit code 1 when a threshold given is broken."""
    from clients.loadtest.config import OutputConfig, SourceConfig
    from clients.loadtest.report import table, to_json
    from clients.loadtest.run import run_loadtest

    if sweep and options["stream_tag"]:
        raise click.BadParameter("a sweep's steps need their own stream IDs", param_hint="--stream-tag")
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    source = SourceConfig(folder=_data(data, synthetic), max_scans=max_scans, every=every)
    cfg = _loadtest_config(source, _vehicles(vehicles, sweep), not keep_going, **options)
    files = OutputConfig(json_path=out, csv_path=csv_path, plots_dir=plots, progress=progress)
    report = _or_exit(run_loadtest, cfg, files)
    click.echo(json.dumps(to_json(report)) if as_json else table(report))
    if report.exit_code:
        raise SystemExit(report.exit_code)


def _loadtest_config(
    source: SourceConfig,
    vehicles: tuple[int, ...],
    stop_after_failure: bool,
    mode: Mode,
    duration: float,
    warmup: float,
    window_s: float | None,
    stability_pct: float,
    max_windows: int,
    max_p99_ms: float | None,
    max_error_rate: float | None,
    turns_per_s: float,
    sectors_per_turn: int | None,
    drain_timeout: float,
    seed: int,
    stream_prefix: str,
    stream_tag: str | None,
    **connection: Any,
) -> LoadTestConfig:
    """The loadtest options -> a LoadTestConfig. Thresholds: those given, enforced; none given: the
    defaults (p99 <= 25 ms, no errors) judge which steps held, and the exit code stays 0."""
    from clients.loadtest.config import LoadTestConfig, Thresholds, WindowConfig

    given = max_p99_ms is not None or max_error_rate is not None
    return LoadTestConfig(
        connect=connect_config(**connection),
        source=source,
        mode=mode,
        vehicles=vehicles,
        duration_s=duration,
        warmup_s=warmup,
        windows=None if window_s is None else WindowConfig(window_s, stability_pct, max_windows),
        thresholds=Thresholds(max_p99_ms, max_error_rate, enforced=True) if given else Thresholds(),
        turns_per_s=turns_per_s,
        sectors_per_turn=sectors_per_turn,
        drain_timeout_s=drain_timeout,
        stop_after_failure=stop_after_failure,
        seed=seed,
        stream_prefix=stream_prefix,
        stream_tag=stream_tag,
    )


@click.command()
@click.argument("source", type=click.Path(exists=True, path_type=Path))
@click.option(
    "--out",
    type=NewFile,
    default="predictions.jsonl",
    show_default=True,
    help="The prediction file (JSON lines).",
)
@click.option("--frames", type=Folder, help="Write a bird's-eye-view PNG per scan into this folder.")
@click.option(
    "--min-score",
    type=click.FloatRange(0.0, 1.0),
    help="Ask for the boxes scored at least this in every reply (0: all) [default: the server's min_score, "
    "GET /v1/model].",
)
@click.option(
    "--rate", type=click.FloatRange(0), default=10.0, show_default=True, help="Turns/s; 0: at once."
)
@click.option("--stream-id", default="replay", show_default=True, help="The stream the drive is sent as.")
@click.option(
    "--topic",
    help="ROS 2 recordings: the sensor_msgs/msg/PointCloud2 topic to replay (default: the only one).",
)
@click.option(
    "--intensity-scale",
    type=click.FloatRange(min=0, min_open=True),
    default=1.0,
    show_default=True,
    help="ROS 2 recordings: multiply intensity by this (1/255 = 0.00392 for drivers publishing 0..255).",
)
@click.option(
    "--mcap",
    "mcap_out",
    type=NewFile,
    help="Also write the replayed points and the boxes as an MCAP file (Foxglove PointCloud + SceneUpdate).",
)
@connection_options
@every_option
@click.option("--max-scans", type=click.IntRange(1), help="Replay at most this many scans.")
@json_option
def replay(
    source: Path,
    out: Path,
    frames: Path | None,
    min_score: float | None,
    rate: float,
    stream_id: str,
    topic: str | None,
    intensity_scale: float,
    mcap_out: Path | None,
    every: int,
    max_scans: int | None,
    as_json: bool,
    **connection: Any,
) -> None:
    """Stream a recorded drive to a server and write its detections (SOURCE: a folder of scans: KITTI .bin,
    nuScenes .pcd.bin, native .npz; one scan file; or a ROS 2 recording of PointCloud2 messages, one per
    turn: a rosbag2 folder (MCAP or sqlite3 storage), a .mcap or a .db3 file)."""
    from clients.replay import ReplayConfig
    from clients.replay import replay as run_replay

    cfg = ReplayConfig(
        source=source,
        predictions=out,
        connect=connect_config(**connection),
        stream_id=stream_id,
        turns_per_s=rate,
        frames_dir=frames,
        max_scans=max_scans,
        every=every,
        topic=topic,
        intensity_scale=intensity_scale,
        mcap=mcap_out,
        min_score=min_score,
    )
    s = _or_exit(run_replay, cfg)
    if as_json:
        click.echo(json.dumps(dataclasses.asdict(s), default=str))
        return
    click.echo(
        f"replayed {s.scans} scans, {s.sectors} sectors: {s.ok} answered with detections, {s.errors} errors, "
        f"{s.late_sectors} sent late; predictions in {out}"
        + (f", {len(s.frames)} frames in {frames}" if frames else "")
        + (f", {s.scenes} scenes in {mcap_out}" if mcap_out else "")
    )


def _or_exit(fn: Callable[..., T], *args: Any) -> T:
    """Run; input that cannot be used ends the command with exit code 2, a client error with 1."""
    from clients.base import ClientError

    try:
        return fn(*args)
    except (FileNotFoundError, ValueError) as e:
        raise click.BadParameter(str(e)) from None
    except ClientError as e:
        click.echo(f"error: {e}", err=True)
        raise SystemExit(1) from None
