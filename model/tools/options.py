"""The options of the model commands (model info, bench model/ops, train, eval, diagnose), each defined once
with its PHIM_ environment variable; the defaults that differ by command are arguments."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import click

from lidar.selection import ClassMap, Split, parse_class_map
from model.config import CONFIGS, Engine, Precision
from phim.options import EnumValue

Decorator = Callable[[Callable[..., Any]], Callable[..., Any]]


def config_option(default: str) -> Decorator:
    return click.option(
        "--config",
        envvar="PHIM_CONFIG",
        type=click.Choice(list(CONFIGS)),
        default=default,
        show_default=True,
        show_envvar=True,
        help="Model config.",
    )


def device_option(default: str = "auto") -> Decorator:
    return click.option(
        "--device",
        envvar="PHIM_DEVICE",
        default=default,
        show_default=True,
        show_envvar=True,
        help="auto (cuda if present), cpu, cuda or cuda:N.",
    )


def checkpoint_option(default: str | None) -> Decorator:
    return click.option(
        "--checkpoint",
        envvar="PHIM_CHECKPOINT",
        default=default,
        show_default=default is not None,
        show_envvar=True,
        help="Weights: a checkpoint file, or 'default' (the shipped model)"
        + ("." if default else " [default: fresh, untrained weights]."),
    )


def data_option(split: Split) -> Decorator:
    """--data; a folder spec is checked now (syntax, and that the folder holds what its kind needs: usage
    errors), a custom:DIR folder for `split` (training: ImageSets/train.txt, evaluation: val.txt)."""

    def check(ctx: click.Context, param: click.Parameter, spec: str) -> str:
        from lidar.datasets import DataKind, list_scan_paths, parse_data_spec

        try:
            parsed = parse_data_spec(spec)
            if parsed.kind is not DataKind.SIM:
                list_scan_paths(parsed, split)
        except (ValueError, FileNotFoundError) as e:
            raise click.BadParameter(str(e)) from None
        return spec

    return click.option(
        "--data",
        envvar="PHIM_DATA",
        default="sim",
        show_default=True,
        show_envvar=True,
        callback=check,
        help="Data: sim, kitti:DIR, nuscenes:DIR, native:DIR, custom:DIR (OpenPCDet's custom layout; "
        f"ImageSets/{split.value}.txt when present, else every scan) or samples[:DIR] (the real samples; "
        "eval only).",
    )


def _parse_class_map(ctx: click.Context, param: click.Parameter, text: str) -> ClassMap:
    try:
        return parse_class_map(text)
    except ValueError as e:
        raise click.BadParameter(str(e)) from None


class_map_option: Decorator = click.option(
    "--class-map",
    "class_map",
    envvar="PHIM_CLASS_MAP",
    default="",
    show_envvar=True,
    callback=_parse_class_map,
    help="custom:DIR only: label class -> VEHICLE, PEDESTRIAN, CYCLIST or IGNORE, e.g. "
    "'Car=VEHICLE,Truck=VEHICLE,Pedestrian=PEDESTRIAN,Cyclist=CYCLIST,*=IGNORE' (*=IGNORE drops every class "
    "not named; without it such a class is an error). VEHICLE, PEDESTRIAN, CYCLIST (any case) map to "
    "themselves.",
)
threads_option = click.option(
    "--threads",
    envvar="PHIM_THREADS",
    type=click.IntRange(min=0),
    default=0,
    show_default=True,
    show_envvar=True,
    help="Torch CPU threads (0: torch's default).",
)


def points_option(kitti_first: bool, fallback: str = "a synthetic turn") -> Decorator:
    """--points; without it the command runs on KITTI 000000 where present (`kitti_first`), else on
    `fallback` (`model.tools.cli.load_turn`)."""
    default = f"KITTI 000000 if present, else {fallback}" if kitti_first else fallback
    return click.option(
        "--points",
        type=click.Path(exists=True, dir_okay=False, path_type=Path),
        help=f"A KITTI-style float32 (N, 4) .bin scan [default: {default}].",
    )


held_out_seed_option = click.option(
    "--seed",
    type=int,
    default=7,
    show_default=True,
    help="Sim stream of the held-out scans (training uses 0).",
)


engine_option: Decorator = click.option(
    "--engine",
    envvar="PHIM_ENGINE",
    type=EnumValue(Engine),
    default=Engine.EAGER.value,
    show_default=True,
    show_envvar=True,
    help="eager (the reference) or graph (the fixed-shape step, compiled).",
)


precision_option: Decorator = click.option(
    "--precision",
    envvar="PHIM_PRECISION",
    type=EnumValue(Precision),
    default=Precision.FP32.value,
    show_default=True,
    show_envvar=True,
    help="fp32, or bf16 (autocast: matmuls and convs in bfloat16; meant for CUDA, slow on CPUs without AMX).",
)


refiner_option: Decorator = click.option(
    "--refiner/--no-refiner",
    default=True,
    show_default=True,
    help="Run the checkpoint's box refiner after each step, where it has one; --no-refiner: the detector "
    "alone.",
)
