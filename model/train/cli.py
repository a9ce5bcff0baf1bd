"""`phim train`."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated

import typer

from model.config import CONFIGS
from model.train.loss import LossConfig

log = logging.getLogger("phim.train")

DataOpt = Annotated[str, typer.Option("--data", help="sim, kitti:DIR, nuscenes:DIR or native:DIR")]
DeviceOpt = Annotated[str, typer.Option("--device", help="auto (cuda if present), cpu, cuda, cuda:1")]
CheckpointOpt = Annotated[str, typer.Option("--checkpoint", help="a checkpoint file, or 'default'")]
HeldOutSeedOpt = Annotated[int, typer.Option(help="sim stream of the held-out scans")]


def train_cmd(
    out: Annotated[Path, typer.Option("--out", help="run directory (checkpoints, metrics.csv)")],
    config: Annotated[str, typer.Option("--config", help=f"model config: {', '.join(CONFIGS)}")] = "tiny",
    data: DataOpt = "sim",
    steps: Annotated[int, typer.Option(help="optimizer steps (the one-cycle schedule spans them)")] = 6000,
    batch_size: Annotated[int, typer.Option(help="scans per step and process")] = 1,
    lr: Annotated[float, typer.Option(help="peak learning rate of the one-cycle schedule")] = 3e-3,
    seed: Annotated[int, typer.Option(help="sim stream and augmentation seed (eval uses 7)")] = 0,
    workers: Annotated[int, typer.Option(help="data-loader processes per training process")] = 1,
    checkpoint_every: Annotated[int, typer.Option(help="steps between checkpoints")] = 200,
    log_every: Annotated[int, typer.Option(help="steps between metrics.csv rows")] = 10,
    resume: Annotated[bool, typer.Option("--resume", help="continue the run in --out")] = False,
    init: Annotated[
        str, typer.Option(help="start from this checkpoint's weights ('default': the shipped model)")
    ] = "",
    direction_weight: Annotated[
        float, typer.Option(help="weight of the direction classifier's loss (axis_direction heading code)")
    ] = LossConfig.direction_weight,
    device: DeviceOpt = "auto",
    threads: Annotated[int, typer.Option(help="torch CPU threads (0: torch's default)")] = 0,
    progress: Annotated[bool, typer.Option(help="show a progress bar")] = True,
    max_minutes: Annotated[
        float,
        typer.Option(help="save and stop after this many minutes; --resume continues (0: no limit)", min=0),
    ] = 0.0,
) -> None:
    """Train a model (streaming, as the paper trains); torchrun runs the same command with DDP."""
    import torch

    from model.checkpoint import checkpoint_path
    from model.train.loop import TrainConfig, train
    from phim.process import tune_malloc

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    tune_malloc()
    if threads:
        torch.set_num_threads(threads)
    cfg = TrainConfig(
        config=config,
        data=data,
        steps=steps,
        batch_size=batch_size,
        lr=lr,
        seed=seed,
        workers=workers,
        checkpoint_every=checkpoint_every,
        log_every=log_every,
        init=str(checkpoint_path(init)) if init else "",
        loss=LossConfig(direction_weight=direction_weight),
    )
    path = train(cfg, out, resume=resume, device=device, progress=progress, max_minutes=max_minutes)
    typer.echo(f"model: {path}")
