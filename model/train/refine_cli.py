"""`phim train-refiner`: train the box refiner on a frozen detector and write detector + refiner."""

from __future__ import annotations

import dataclasses
import itertools
import logging
import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING

import click

from lidar.selection import ClassMap, Split
from lidar.sources import scan_source
from lidar.types import CLASS_NAMES
from model.config import RefineConfig
from model.tools.options import checkpoint_option, class_map_option, data_option, threads_option
from model.train.refine import MATCH_IOU, Proposals

if TYPE_CHECKING:
    from model.detector import PHiM

# one proposal worker's task: checkpoint, refiner config, data, class map, sim stream, its first scan and
# how many, per class whether every heatmap cell is a box, and how many of the checkpoint's refiner stages
# refine the boxes first
Job = tuple[Path, RefineConfig, str, ClassMap, int, int, int, tuple[bool, ...], int]


@click.command()
@checkpoint_option("default")
@click.option(
    "--out", type=click.Path(dir_okay=False, path_type=Path), required=True, help="Checkpoint to write."
)
@click.option(
    "--seed",
    "seeds",
    type=int,
    multiple=True,
    default=(28, 29),
    show_default=True,
    help="Sim streams (repeat; file data: one pass in file order, whatever the seeds).",
)
@data_option(Split.TRAIN)
@class_map_option
@click.option("--scans", type=click.IntRange(1), default=800, show_default=True, help="Scans per stream.")
@click.option("--epochs", type=click.IntRange(1), default=8, show_default=True, help="Passes over the boxes.")
@click.option("--lr", type=float, default=2e-3, show_default=True, help="Peak learning rate (one-cycle).")
@click.option(
    "--points",
    type=click.IntRange(1),
    default=RefineConfig.points,
    show_default=True,
    help="Points the refiner reads per box.",
)
@click.option(
    "--context/--no-context",
    default=RefineConfig.context,
    show_default=True,
    help="A second per-point layer reading the pooled feature (RefineConfig.context).",
)
@click.option(
    "--flip/--no-flip",
    default=RefineConfig.flip,
    show_default=True,
    help="Also predict whether a box points the wrong way, and turn it (RefineConfig.flip).",
)
@click.option(
    "--stages",
    type=click.IntRange(1),
    default=RefineConfig.stages,
    show_default=True,
    help="Refiners applied in turn, each fitted on the boxes of the ones before (RefineConfig.stages).",
)
@click.option(
    "--keep/--no-keep",
    default=False,
    show_default=True,
    help="Keep the refiner stages the checkpoint has (the same points, context and flip) and fit only the "
    "stages after them.",
)
@click.option(
    "--fit-every-cell",
    "fit_every_cell",
    type=click.Choice(CLASS_NAMES, case_sensitive=False),
    multiple=True,
    help="A class (repeat) whose every heatmap cell above the score threshold is a box to fit on, as the "
    "refiner reads it at work (RefineConfig.every_cell). Default: none, the heatmaps' 3 x 3 local maxima of "
    "every class.",
)
@click.option(
    "--workers",
    type=click.IntRange(0),
    default=0,
    show_default=True,
    help="Processes that read the scans for a stage's boxes (0: one per stream). More than the streams split "
    "each stream's scans into runs: the same boxes in the same order, so the same refiner.",
)
@threads_option
def train_refiner_cmd(
    checkpoint: str,
    out: Path,
    seeds: tuple[int, ...],
    data: str,
    class_map: ClassMap,
    scans: int,
    epochs: int,
    lr: float,
    points: int,
    context: bool,
    flip: bool,
    stages: int,
    keep: bool,
    fit_every_cell: tuple[str, ...],
    workers: int,
    threads: int,
) -> None:
    """Train the box refiner on the detector's own boxes (the detector is frozen): on simulated scans, or on
    the training scans of --data (at most --scans of them). Each stage of a cascade is fitted in turn, on
    the boxes the stages before it refined (one more pass over the scans a stage); --out holds the stages
    fitted so far after each."""
    import torch

    from model.checkpoint import read_checkpoint, resolve_checkpoint
    from model.detector import PHiM

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if threads:
        torch.set_num_threads(threads)
    detector, path = resolve_checkpoint(checkpoint)
    refine = RefineConfig(points=points, context=context, flip=flip, stages=stages)
    kept = _kept_stages(detector.cfg.refine, refine) if keep else 0
    cfg = dataclasses.replace(detector.cfg, refine=refine)
    torch.manual_seed(0)  # the refiner's initial weights
    model = PHiM(cfg)
    weights = {k: v for k, v in detector.state_dict().items() if keep or not k.startswith("refiner.")}
    model.load_state_dict(weights, strict=False)  # the detector, and with --keep the fitted stages
    if data != "sim":  # one pass over the files (a second stream would read the same scans)
        seeds, scans = seeds[:1], min(scans, len(scan_source(data, 0, classes=class_map)))
    meta = read_checkpoint(path)["meta"] | {
        "refiner": {
            "detector": path.name,
            "data": data,
            "seeds": list(seeds),
            "scans": scans,
            "epochs": epochs,
            "lr": lr,
            "stages_kept": kept,
            "fit_every_cell": list(fit_every_cell),
        }
    }
    cells = tuple(name in fit_every_cell for name in CLASS_NAMES)
    runs = scan_runs(scans, -(-workers // len(seeds)))  # ceil: every worker has a run
    jobs = [
        (path, refine, data, class_map, s, first, count, cells, 0) for s in seeds for first, count in runs
    ]
    click.echo(f"the refiner learns from the boxes of {len(seeds)} x {scans} scans of {data}")
    _fit_stages(model, kept, jobs, out, meta, epochs, lr)
    click.echo(f"model: {out}")


def _fit_stages(
    model: PHiM, kept: int, jobs: list[Job], out: Path, meta: dict, epochs: int, lr: float
) -> None:
    """Fit the refiner's stages after the first `kept`, each on the boxes of the scans of `jobs` as the
    stages before it return them (a later stage's read from `out`, which is written after each stage)."""
    from model.checkpoint import save_checkpoint
    from model.train.refine import fit

    if kept:
        save_checkpoint(out, model, meta)
    for k, stage in enumerate(model.refiner.chain()):
        if k < kept:
            continue
        stage_jobs = [(out if k else job[0], *job[1:8], k) for job in jobs]
        with ProcessPoolExecutor(len(jobs), mp_context=multiprocessing.get_context("spawn")) as pool:
            boxes = Proposals.cat(list(pool.map(_stream_proposals, stage_jobs)))
        on_objects = int((boxes.iou >= MATCH_IOU).sum())
        click.echo(f"stage {k + 1}: {len(boxes)} boxes, {on_objects} on objects")
        fit(stage, boxes, epochs, lr)
        save_checkpoint(out, model, meta)


def _kept_stages(have: RefineConfig | None, want: RefineConfig) -> int:
    """--keep: how many fitted stages the checkpoint's refiner gives the one asked for."""
    if have is None:
        raise click.BadParameter("the checkpoint has no refiner to keep", param_hint="--keep")
    if dataclasses.replace(have, stages=want.stages) != want:
        raise click.BadParameter(
            f"the checkpoint's refiner ({have}) differs from the one asked for ({want}) in more than its "
            "stages",
            param_hint="--keep",
        )
    if have.stages >= want.stages:
        raise click.BadParameter(
            f"the checkpoint's refiner has {have.stages} stages; --stages {want.stages} adds none",
            param_hint="--keep",
        )
    return have.stages


def _stream_proposals(job: Job) -> Proposals:
    """In a worker process of one thread: the detector's proposals on `scans` scans of `data` (the simulator:
    stream `seed`) from scan `first` on, refined by the checkpoint's first `refined` refiner stages."""
    import torch

    from model.checkpoint import load_checkpoint
    from model.train.refine import proposals

    path, cfg, data, classes, seed, first, scans, every_cell, refined = job
    torch.set_num_threads(1)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    source = scan_source(data, seed, shuffle=False, classes=classes)
    return proposals(load_checkpoint(path), cfg, source, range(first, first + scans), refined, every_cell)


def scan_runs(scans: int, parts: int) -> list[tuple[int, int]]:
    """Scans 0 .. scans - 1 cut into at most `parts` (at least one) contiguous runs of near-equal length,
    in order: (first, count) each."""
    parts = max(parts, 1)
    bounds = [scans * i // parts for i in range(parts + 1)]
    return [(a, b - a) for a, b in itertools.pairwise(bounds) if b > a]
