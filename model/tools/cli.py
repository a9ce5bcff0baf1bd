"""`phim model ...`, `phim bench model` and `phim bench ops` commands."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Annotated

import torch
import typer

from model.config import CONFIGS, ScanImpl, get_config
from model.data.samples import KITTI_000000
from model.data.synthetic import synthetic_turn
from model.device import pick_device
from model.sectors import load_kitti_bin
from phim.process import tune_malloc

ConfigOpt = Annotated[str, typer.Option("--config", help=f"model config: {', '.join(CONFIGS)}")]
PointsOpt = Annotated[
    Path | None,
    typer.Option("--points", help="a KITTI-style float32 (N,4) .bin scan; default: KITTI 000000 if present"),
]


def _load_turn(points: Path | None, fallback_kitti: bool) -> tuple[torch.Tensor, str]:
    if points is not None:
        return load_kitti_bin(str(points)), str(points)
    if fallback_kitti and KITTI_000000.is_file():
        return load_kitti_bin(str(KITTI_000000)), str(KITTI_000000)
    return torch.from_numpy(synthetic_turn(seed=0)), "synthetic_turn(seed=0)"


def info(
    config: ConfigOpt = "paper",
    points: PointsOpt = None,
    as_json: Annotated[bool, typer.Option("--json", help="print JSON only")] = False,
) -> None:
    """Parameter count and measured GFLOPs of a config (FLOPs counted on a real forward)."""
    from model.tools.info import model_info

    tune_malloc()
    turn, source = _load_turn(points, fallback_kitti=False)
    result = model_info(get_config(config), turn).to_dict()
    result["input"] = source
    if as_json:
        typer.echo(json.dumps(result))
        return
    for key, value in result.items():
        typer.echo(f"{key:>24}  {value}")


def bench_model_cmd(
    config: ConfigOpt = "tiny",
    points: PointsOpt = None,
    device: Annotated[str, typer.Option(help="auto, cpu, cuda, cuda:N")] = "auto",
    batch: Annotated[int, typer.Option(help="streams per forward")] = 1,
    turns: Annotated[int, typer.Option(help="timed turns")] = 10,
    threads: Annotated[int, typer.Option(help="torch CPU threads (0: leave as is)")] = 0,
    checkpoint: Annotated[
        str | None, typer.Option(help="weights to load: a file, or 'default' (default: fresh init)")
    ] = None,
    scan: Annotated[ScanImpl | None, typer.Option(help="selective scan (default: the config's)")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="print JSON only")] = False,
) -> None:
    """Time one sector at a time of a scan, with the sector buffer loaded."""
    from model.checkpoint import checkpoint_path, load_checkpoint
    from model.detector import PHiM
    from model.tools.bench import bench_model

    logging.basicConfig(level=logging.WARNING)
    tune_malloc()
    if threads:
        torch.set_num_threads(threads)
    dev = pick_device(device)
    cfg = get_config(config)
    model = load_checkpoint(checkpoint_path(checkpoint), cfg, dev) if checkpoint else PHiM(cfg).to(dev)
    if scan is not None:
        model.set_scan(scan)
    turn, source = _load_turn(points, fallback_kitti=True)
    result = bench_model(model, turn, batch=batch, turns=turns).to_dict()
    result["input"] = source
    if as_json:
        typer.echo(json.dumps(result))
        return
    typer.echo(f"input: {source}")
    for key in ("config", "device", "scan", "threads", "batch", "points_per_sector", "iterations"):
        typer.echo(f"{key:>24}  {result[key]}")
    typer.echo("\n| metric | value |\n|---|---|")
    for key in ("p50_ms", "p90_ms", "mean_ms", "per_sector_p50_ms", "peak_mem_mb", "full_turn_peak_mem_mb"):
        typer.echo(f"| {key} | {result[key]} |")


def bench_ops_cmd(
    config: ConfigOpt = "paper",
    points: PointsOpt = None,
    device: Annotated[str, typer.Option(help="auto, cpu, cuda, cuda:N")] = "cpu",
    checkpoint: Annotated[
        str | None, typer.Option(help="weights to load: a file, or 'default' (default: fresh init)")
    ] = None,
    rows: Annotated[int, typer.Option(help="functions to list, most ops first")] = 25,
    as_json: Annotated[bool, typer.Option("--json", help="print JSON only")] = False,
) -> None:
    """Torch ops (kernel launches on a GPU), views and host syncs of one streaming step, by model function."""
    from model.checkpoint import checkpoint_path, load_checkpoint
    from model.detector import PHiM
    from model.tools.op_count import count_ops

    logging.basicConfig(level=logging.WARNING)
    tune_malloc()
    dev = pick_device(device)
    cfg = get_config(config)
    model = load_checkpoint(checkpoint_path(checkpoint), cfg, dev) if checkpoint else PHiM(cfg).to(dev)
    turn, source = _load_turn(points, fallback_kitti=True)
    report = count_ops(model.eval(), turn)
    if as_json:
        typer.echo(json.dumps(report.to_dict() | {"input": source}))
        return
    typer.echo(f"input: {source}; config {report.config}, device {report.device}, scan {report.scan}")
    typer.echo("\n| where | ops | views | host syncs |\n|---|---|---|---|")
    for r in report.rows[:rows]:
        typer.echo(f"| {r.where} | {r.ops} | {r.views} | {r.syncs} |")
    typer.echo(f"| **all** | **{report.ops}** | {report.views} | **{report.syncs}** |")
    typer.echo(f"| all but the selective scan | **{report.ops_outside_scan}** | | |")
    if report.cuda_kernels is not None:
        typer.echo(f"| CUDA kernels launched | {report.cuda_kernels} | | |")
