"""`phim loadtest` and `phim replay` (typer commands, loaded by the `phim` command, phim/cli.py)."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated

import typer

from clients.connect import ConnectConfig, Transport
from clients.loadtest.config import Mode
from model.data.samples import KITTI_VELODYNE

TransportOpt = Annotated[Transport, typer.Option(help="http or zenoh")]
UrlOpt = Annotated[str, typer.Option(help="server HTTP address (over zenoh: model info, ending streams)")]
ConnectOpt = Annotated[str, typer.Option(help="zenoh endpoints to connect to, comma-separated")]
ZModeOpt = Annotated[str, typer.Option(help="zenoh session mode: client or peer")]
ZFileOpt = Annotated[Path | None, typer.Option(help="zenoh JSON5 config file (TLS, ...)")]
TimeoutOpt = Annotated[float, typer.Option(help="per-request timeout (s)")]


def connect_config(
    transport: Transport,
    url: str,
    zenoh_connect: str,
    zenoh_mode: str,
    zenoh_config: Path | None,
    timeout: float,
) -> ConnectConfig:
    return ConnectConfig(
        transport=transport,
        url=url,
        zenoh_connect=tuple(e.strip() for e in zenoh_connect.split(",") if e.strip()),
        zenoh_mode=zenoh_mode,
        zenoh_config_file=None if zenoh_config is None else str(zenoh_config),
        timeout_s=timeout,
    )


def _vehicles(vehicles: int, sweep: str | None) -> tuple[int, ...]:
    if not sweep:
        return (vehicles,)
    try:
        steps = tuple(int(v) for v in sweep.split(",") if v.strip())
    except ValueError:
        raise typer.BadParameter(
            f"--sweep {sweep!r}: expected comma-separated vehicle counts, e.g. 1,2,4,8"
        ) from None
    if not steps or min(steps) < 1:
        raise typer.BadParameter(f"--sweep {sweep!r}: expected positive vehicle counts")
    return steps


def _data(data: Path | None, synthetic: bool) -> Path | None:
    if synthetic:
        return None
    if data is not None:
        return data
    return KITTI_VELODYNE if KITTI_VELODYNE.is_dir() else None


def loadtest(
    transport: TransportOpt = Transport.HTTP,
    url: UrlOpt = "http://127.0.0.1:8080",
    zenoh_connect: ConnectOpt = "tcp/127.0.0.1:7447",
    zenoh_mode: ZModeOpt = "client",
    zenoh_config: ZFileOpt = None,
    vehicles: Annotated[int, typer.Option(min=1, help="simulated vehicles (streams)")] = 1,
    sweep: Annotated[str | None, typer.Option(help="vehicle counts to step through, e.g. 1,2,4,8")] = None,
    mode: Annotated[
        Mode,
        typer.Option(help="open: at sensor rate, latency from scheduled time; closed: send when answered"),
    ] = Mode.OPEN,
    duration: Annotated[float, typer.Option(min=0.1, help="seconds of sending per step")] = 10.0,
    turns_per_s: Annotated[float, typer.Option(min=0.01, help="sensor turns per second per vehicle")] = 10.0,
    sectors_per_turn: Annotated[int | None, typer.Option(help="default: the served model's")] = None,
    data: Annotated[
        Path | None, typer.Option(help=f"folder of scans [default: {KITTI_VELODYNE} if present]")
    ] = None,
    synthetic: Annotated[bool, typer.Option(help="synthetic turns instead of recorded scans")] = False,
    every: Annotated[int, typer.Option(min=1, help="keep every n-th point")] = 1,
    max_scans: Annotated[int, typer.Option(min=1, help="scans read from --data")] = 20,
    timeout: TimeoutOpt = 10.0,
    drain_timeout: Annotated[float, typer.Option(help="wait for replies after the last send (s)")] = 10.0,
    p99_bound_ms: Annotated[float, typer.Option(help="a step holds when p99 <= this")] = 25.0,
    keep_going: Annotated[bool, typer.Option(help="sweep on after a step that does not hold")] = False,
    json_path: Annotated[Path | None, typer.Option("--json", help="write the JSON report here")] = None,
    csv_path: Annotated[Path | None, typer.Option("--csv", help="write the CSV report here")] = None,
    plots: Annotated[Path | None, typer.Option(help="write PNG plots into this folder")] = None,
    progress: Annotated[bool, typer.Option(help="live progress on stderr")] = True,
    seed: int = 0,
) -> None:
    """Simulate vehicles streaming sectors to a server and report throughput and latency (open loop at sensor
    rate by default: latency from each sector's scheduled time)."""
    from clients.loadtest.config import LoadTestConfig, OutputConfig, SourceConfig
    from clients.loadtest.report import table
    from clients.loadtest.run import run_loadtest

    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    cfg = LoadTestConfig(
        connect=connect_config(transport, url, zenoh_connect, zenoh_mode, zenoh_config, timeout),
        source=SourceConfig(folder=_data(data, synthetic), max_scans=max_scans, every=every),
        mode=mode,
        vehicles=_vehicles(vehicles, sweep),
        duration_s=duration,
        turns_per_s=turns_per_s,
        sectors_per_turn=sectors_per_turn,
        drain_timeout_s=drain_timeout,
        p99_bound_ms=p99_bound_ms,
        stop_after_failure=not keep_going,
        seed=seed,
    )
    out = OutputConfig(json_path=json_path, csv_path=csv_path, plots_dir=plots, progress=progress)
    report = _or_exit(run_loadtest, cfg, out)
    typer.echo(table(report))


def replay(
    source: Annotated[
        Path, typer.Argument(help="folder of scans (KITTI .bin, nuScenes .pcd.bin, native .npz)")
    ],
    out: Annotated[Path, typer.Option(help="prediction file to write (JSON lines)")] = Path(
        "predictions.jsonl"
    ),
    frames: Annotated[Path | None, typer.Option(help="write a bird's-eye-view PNG per scan here")] = None,
    rate: Annotated[float, typer.Option(min=0, help="turns per second; 0: as fast as answered")] = 10.0,
    stream_id: Annotated[str, typer.Option(help="the stream the drive is sent as")] = "replay",
    transport: TransportOpt = Transport.HTTP,
    url: UrlOpt = "http://127.0.0.1:8080",
    zenoh_connect: ConnectOpt = "tcp/127.0.0.1:7447",
    zenoh_mode: ZModeOpt = "client",
    zenoh_config: ZFileOpt = None,
    timeout: TimeoutOpt = 10.0,
    every: Annotated[int, typer.Option(min=1, help="keep every n-th point")] = 1,
    max_scans: Annotated[int | None, typer.Option(help="replay at most this many scans")] = None,
) -> None:
    """Stream a recorded drive to a server and write its detections (and optional BEV frames)."""
    from clients.replay import ReplayConfig
    from clients.replay import replay as run_replay

    cfg = ReplayConfig(
        source=source,
        predictions=out,
        connect=connect_config(transport, url, zenoh_connect, zenoh_mode, zenoh_config, timeout),
        stream_id=stream_id,
        turns_per_s=rate,
        frames_dir=frames,
        max_scans=max_scans,
        every=every,
    )
    s = _or_exit(run_replay, cfg)
    typer.echo(
        f"replayed {s.scans} scans, {s.sectors} sectors: {s.ok} answered with detections, {s.errors} errors, "
        f"{s.late_sectors} sent late; predictions in {out}"
        + (f", {len(s.frames)} frames in {frames}" if frames else "")
    )


def _or_exit(fn, *args):
    """Run; a client error or missing data ends the command with its message and exit code 2."""
    from clients.base import ClientError
    from phim.process import tune_malloc

    tune_malloc()  # sector-sized buffers stay on the heap: encoding a 30k-point sector 0.5 -> 0.08 ms

    try:
        return fn(*args)
    except (ClientError, FileNotFoundError, ValueError) as e:
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(code=2) from None
