"""`phim model info`, `phim bench model`, `engines`, `refiner` and `ops` (torch is imported when a command
runs)."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import TYPE_CHECKING

import click

from model.config import Engine, Precision, ScanImpl, get_config
from model.tools.options import (
    checkpoint_option,
    config_option,
    device_option,
    engine_option,
    points_option,
    precision_option,
    refiner_option,
    threads_option,
)
from phim.options import EnumValue, json_option
from phim.progress import Progress, note

if TYPE_CHECKING:
    import torch

    from model.detector import PHiM


def load_turn(
    points: Path | None, fallback_kitti: bool, command: str = "bench", scene: bool = False
) -> tuple[torch.Tensor, str]:
    """The scan to run on: `points`, else KITTI 000000 when asked and present, else a synthetic turn
    (`scene`: a simulated street scan instead, which has objects to detect). Falling back from KITTI is
    said on stderr."""
    import torch

    from lidar.samples import KITTI_000000
    from lidar.synthetic import synthetic_turn
    from model.sectors import load_kitti_bin

    if points is not None:
        return load_kitti_bin(str(points)), str(points)
    if fallback_kitti and KITTI_000000.is_file():
        return load_kitti_bin(str(KITTI_000000)), str(KITTI_000000)
    source = "simulate(seed=3)" if scene else "synthetic_turn(seed=0)"
    if fallback_kitti:
        note(
            command,
            f"the real samples' KITTI scan is not at {KITTI_000000} (PHIM_SAMPLES_DIR; README, Quick start): "
            f"running on {source} instead (--points FILE: a scan of your own)",
        )
    if scene:
        from lidar.sim.simulate import simulate

        return torch.from_numpy(simulate(seed=3).points), source
    return torch.from_numpy(synthetic_turn(seed=0)), source


def load_model(
    config: str | None, checkpoint: str | None, device: str, threads: int = 0, refiner: bool = True
) -> PHiM:
    """A fresh model of `config` (no checkpoint) or the weights of `checkpoint` (of `config`, or of any
    config with None), on `device`; without its box refiner unless `refiner`."""
    import torch

    from model.checkpoint import checkpoint_path, load_checkpoint
    from model.detector import PHiM
    from model.device import pick_device

    if threads:
        torch.set_num_threads(threads)
    dev, cfg = pick_device(device), get_config(config) if config else None
    if checkpoint:
        model = load_checkpoint(checkpoint_path(checkpoint), cfg, dev)
    else:
        assert cfg is not None, "a fresh model needs a config"
        model = PHiM(cfg).to(dev)
    if not refiner:
        model.drop_refiner()
    return model


@click.command()
@config_option("paper")
@points_option(kitti_first=False)
@json_option
def info(config: str, points: Path | None, as_json: bool) -> None:
    """Parameter count and measured GFLOPs of a config (FLOPs counted on a real forward)."""
    from model.tools.info import model_info

    progress = Progress("model info")
    progress("importing torch and the model")
    turn, source = load_turn(points, fallback_kitti=False, command="model info")
    result = model_info(get_config(config), turn, progress).to_dict() | {"input": source}
    if as_json:
        click.echo(json.dumps(result))
        return
    for key, value in result.items():
        click.echo(f"{key:>24}  {value}")


@click.command()
@config_option("tiny")
@points_option(kitti_first=True)
@device_option()
@click.option("--batch", type=click.IntRange(1), default=1, show_default=True, help="Streams per forward.")
@click.option("--turns", type=click.IntRange(1), default=10, show_default=True, help="Timed turns.")
@threads_option
@checkpoint_option(None)
@click.option("--scan", type=EnumValue(ScanImpl), help="Selective scan [default: the config's].")
@engine_option
@precision_option
@refiner_option
@click.option(
    "--sector-points",
    type=click.IntRange(0),
    default=0,
    show_default=True,
    help="graph: pad every sector to this many points (one capacity bucket, one compile, as a server "
    "pads to its --sector-points); 0: each sector's own bucket.",
)
@click.option(
    "--bev-crop/--whole-map",
    default=True,
    show_default=True,
    help="graph: the BEV backbone and head on a crop around each new sector once a stream has run a "
    "turn (docs/model.md), or on the whole map every step.",
)
@json_option
def bench_model_cmd(
    config: str,
    points: Path | None,
    device: str,
    batch: int,
    turns: int,
    threads: int,
    checkpoint: str | None,
    scan: ScanImpl | None,
    engine: Engine,
    precision: Precision,
    refiner: bool,
    sector_points: int,
    bev_crop: bool,
    as_json: bool,
) -> None:
    """Per-sector latency, sector buffer loaded: one sector at a time of a scan (fresh weights by default)."""
    from model.tools.bench import bench_model

    logging.basicConfig(level=logging.WARNING)
    progress = Progress("bench model")
    progress(f"loading the model ({checkpoint or config})")
    model = load_model(config, checkpoint, device, threads, refiner)
    if scan is not None:
        model.set_scan(scan)
    turn, source = load_turn(points, fallback_kitti=True, command="bench model")
    result = bench_model(
        model,
        turn,
        batch,
        turns,
        engine=engine,
        precision=precision,
        sector_points=sector_points,
        bev_crop=bev_crop,
        progress=progress,
    )
    result = result.to_dict()
    result |= {"input": source}
    if as_json:
        click.echo(json.dumps(result))
        return
    click.echo(f"input: {source}")
    keys = (
        "config",
        "device",
        "engine",
        "precision",
        "scan",
        "refiner",
        "threads",
        "batch",
        "points_per_sector",
        "iterations",
    )
    for key in keys:
        click.echo(f"{key:>24}  {result[key]}")
    click.echo("\n| metric | value |\n|---|---|")
    for key in ("p50_ms", "p90_ms", "mean_ms", "per_sector_p50_ms", "peak_mem_mb", "full_turn_peak_mem_mb"):
        click.echo(f"| {key} | {result[key]} |")


@click.command()
@config_option("tiny")
@points_option(kitti_first=True)
@device_option()
@threads_option
@checkpoint_option(None)
@click.option(
    "--engines",
    default="eager,graph",
    show_default=True,
    help="Comma-separated engines (eager, graph); the others' ratios are to the first's.",
)
@click.option("--rounds", type=click.IntRange(1), default=10, show_default=True, help="Timed turns of each.")
@click.option("--scan", type=EnumValue(ScanImpl), help="The eager engine's scan [default: the config's].")
@precision_option
@refiner_option
@json_option
def bench_engines_cmd(
    config: str,
    points: Path | None,
    device: str,
    threads: int,
    checkpoint: str | None,
    engines: str,
    rounds: int,
    scan: ScanImpl | None,
    precision: Precision,
    refiner: bool,
    as_json: bool,
) -> None:
    """Engines against each other in one process, alternating turns: p50s and their ratios."""
    from model.tools.bench import compare_engines

    names = [e.strip() for e in engines.split(",")]
    if len(names) < 2 or len(set(names)) != len(names) or not set(names) <= {e.value for e in Engine}:
        raise click.BadParameter(
            f"{engines!r}: expected two or more different engines of {[e.value for e in Engine]}",
            param_hint="--engines",
        )
    logging.basicConfig(level=logging.WARNING)
    progress = Progress("bench engines")
    progress(f"loading the model ({checkpoint or config})")
    model = load_model(config, checkpoint, device, threads, refiner)
    if scan is not None:  # the graph engine has its own segmented scan
        model.set_scan(scan)
    turn, source = load_turn(points, fallback_kitti=True, command="bench engines")
    engine_list = [Engine(n) for n in names]
    result = compare_engines(
        model, turn, engine_list, rounds, precision=precision, progress=progress
    ).to_dict()
    result |= {"input": source}
    if as_json:
        click.echo(json.dumps(result))
        return
    click.echo(
        f"input: {source}; {result['config']} on {result['device']}, {result['threads']} threads, "
        f"eager scan {result['scan']}, refiner {'on' if result['refiner'] else 'off'}"
    )
    base = result["engines"][0]
    click.echo(f"\n| engine | p50 ms | p90 ms | p50 / {base} | per round (min-max) |\n|---|---|---|---|---|")
    for e in result["engines"]:
        per = result["round_ratios"][e]
        click.echo(
            f"| {e} | {result['p50_ms'][e]} | {result['p90_ms'][e]} | {result['ratio_p50'][e]} "
            f"| {min(per):.3f}-{max(per):.3f} |"
        )


@click.command()
@points_option(kitti_first=True, fallback="a simulated street scan")
@device_option()
@threads_option
@checkpoint_option("default")
@click.option("--repeats", type=click.IntRange(1), default=30, show_default=True, help="Timed runs of each.")
@click.option(
    "--streams", type=click.IntRange(1), default=1, show_default=True, help="A batch of this many streams."
)
@json_option
def bench_refiner_cmd(
    points: Path | None, device: str, threads: int, checkpoint: str, repeats: int, streams: int, as_json: bool
) -> None:
    """The box refiner on a whole turn's boxes, as after every step (for a batch of streams with that turn,
    its points on the host as a server holds them): the lookups, the PointNet, all of it."""
    from model.tools.bench import bench_refiner

    logging.basicConfig(level=logging.WARNING)
    progress = Progress("bench refiner")
    progress(f"loading the model ({checkpoint})")
    model = load_model(None, checkpoint, device, threads).eval()
    turn, source = load_turn(points, fallback_kitti=True, command="bench refiner", scene=True)
    try:
        result = bench_refiner(model, turn, repeats, streams, progress).to_dict() | {"input": source}
    except ValueError as e:
        raise click.BadParameter(str(e), param_hint="--checkpoint") from e
    if result["boxes"] == 0:  # nothing was refined: its times would be the cost of doing nothing
        raise click.ClickException(f"the detector found no boxes in {source}: nothing to time (--points)")
    if as_json:
        click.echo(json.dumps(result))
        return
    click.echo(
        f"input: {source} ({result['points']} points, {result['boxes']} boxes, {result['points_per_box']} "
        f"points read per box, {result['stages']} stages) x {streams} streams; {result['config']} on "
        f"{result['device']}, {result['threads']} threads"
    )
    click.echo("\n| part | p50 ms |\n|---|---|")
    for part in ("lookup", "pointnet", "refine"):
        name = part if part == "refine" else f"{part} (a stage)"
        click.echo(f"| {name} | {result[part + '_p50_ms']} |")


@click.command()
@config_option("paper")
@points_option(kitti_first=True)
@device_option("cpu")
@checkpoint_option(None)
@click.option("--rows", type=click.IntRange(1), default=25, show_default=True, help="Functions to list.")
@engine_option
@json_option
def bench_ops_cmd(
    config: str,
    points: Path | None,
    device: str,
    checkpoint: str | None,
    rows: int,
    engine: Engine,
    as_json: bool,
) -> None:
    """Torch ops and host syncs of one streaming step (kernel launches on a GPU), by model function."""
    from model.tools.op_count import count_ops

    logging.basicConfig(level=logging.WARNING)
    progress = Progress("bench ops")
    progress(f"loading the model ({checkpoint or config})")
    model = load_model(config, checkpoint, device)
    turn, source = load_turn(points, fallback_kitti=True, command="bench ops")
    progress("counting the torch ops and host syncs of one streaming step")
    report = count_ops(model.eval(), turn, engine)
    if as_json:
        click.echo(json.dumps(report.to_dict() | {"input": source}))
        return
    click.echo(
        f"input: {source}; config {report.config}, engine {report.engine}, device {report.device}, "
        f"scan {report.scan}"
    )
    click.echo("\n| where | ops | views | host syncs |\n|---|---|---|---|")
    for r in report.rows[:rows]:
        click.echo(f"| {r.where} | {r.ops} | {r.views} | {r.host_syncs} |")
    click.echo(f"| **all** | **{report.ops}** | {report.views} | **{report.host_syncs}** |")
    click.echo(f"| all but the selective scan | **{report.ops_outside_scan}** | | |")
    if report.cuda_kernels is not None:
        click.echo(f"| CUDA kernels launched | {report.cuda_kernels} | | |")
