"""`phim train`."""

from __future__ import annotations

import logging
from pathlib import Path

import click

from lidar.selection import ClassMap, Split
from model.tools.options import (
    class_map_option,
    config_option,
    data_option,
    device_option,
    threads_option,
)
from model.train.loss import LossConfig  # imports torch: `phim train --help` takes about a second


def _int(name: str, default: int, minimum: int, help_text: str):
    return click.option(
        name, type=click.IntRange(minimum), default=default, show_default=True, help=help_text
    )


@click.command()
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), required=True, help="Run directory.")
@config_option("tiny")
@data_option(Split.TRAIN)
@class_map_option
@_int("--steps", 6000, 1, "Optimizer steps (the one-cycle schedule spans them).")
@_int("--batch-size", 1, 1, "Scans per step and process.")
@click.option("--lr", type=float, default=3e-3, show_default=True, help="Peak learning rate (one-cycle).")
@click.option(
    "--weight-decay",
    type=click.FloatRange(0),
    default=0.05,
    show_default=True,
    help="AdamW weight decay on weight matrices and kernels (none on biases, norms, Mamba's A_log and D).",
)
@click.option("--seed", type=int, default=0, show_default=True, help="Sim stream and augmentation seed.")
@_int("--workers", 1, 0, "Data-loader processes per training process.")
@_int("--checkpoint-every", 200, 1, "Steps between checkpoints.")
@_int("--log-every", 10, 1, "Steps between metrics.csv rows.")
@click.option("--resume", is_flag=True, help="Continue the run in --out.")
@click.option(
    "--init", default="", help="Start from this checkpoint's weights ('default': the shipped model)."
)
@click.option(
    "--direction-weight",
    type=float,
    default=LossConfig.direction_weight,
    show_default=True,
    help="Weight of the direction classifier's loss (axis_direction heading code).",
)
@click.option(
    "--point-features",
    type=click.IntRange(3, 5),
    default=None,
    help="Point columns the model reads (x, y, z, intensity, elongation); 3 drops intensity. Default: the "
    "config's own (an --init checkpoint reading more starts without those columns' weights).",
)
@device_option()
@threads_option
@click.option("--progress/--no-progress", default=True, show_default=True, help="Show a progress bar.")
@click.option(
    "--max-minutes",
    type=click.FloatRange(0),
    default=0.0,
    show_default=True,
    help="Save and stop after this many minutes; --resume continues (0: no limit).",
)
def train_cmd(
    out: Path,
    config: str,
    data: str,
    class_map: ClassMap,
    steps: int,
    batch_size: int,
    lr: float,
    weight_decay: float,
    seed: int,
    workers: int,
    checkpoint_every: int,
    log_every: int,
    resume: bool,
    init: str,
    direction_weight: float,
    point_features: int | None,
    device: str,
    threads: int,
    progress: bool,
    max_minutes: float,
) -> None:
    """Train a model (streaming, as the paper trains); torchrun runs the same command with DDP."""
    import torch

    from lidar.custom import CustomDataError
    from lidar.sources import scan_source
    from model.checkpoint import checkpoint_path
    from model.train.loop import TrainConfig, train

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if threads:
        torch.set_num_threads(threads)
    try:
        cfg = TrainConfig(
            config=config,
            data=data,
            class_map=str(class_map),
            steps=steps,
            batch_size=batch_size,
            lr=lr,
            weight_decay=weight_decay,
            seed=seed,
            workers=workers,
            checkpoint_every=checkpoint_every,
            log_every=log_every,
            init=str(checkpoint_path(init)) if init else "",
            loss=LossConfig(direction_weight=direction_weight),
            point_features=point_features or 0,
        )
        scan_source(cfg.data, cfg.seed, classes=class_map)  # custom:DIR: every label file parses
    except ValueError as e:
        raise click.BadParameter(str(e), param_hint="--data / --class-map / --init") from None
    try:
        path = train(cfg, out, resume=resume, device=device, progress=progress, max_minutes=max_minutes)
    except CustomDataError as e:  # a points file found bad when read (NaN, intensity range)
        raise click.ClickException(str(e)) from None
    click.echo(f"model: {path}")
