"""`phim train-refiner`: train the box refiner on a frozen detector and write detector + refiner."""

from __future__ import annotations

import logging
import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import click

from lidar.selection import ClassMap, Split
from lidar.sources import scan_source
from model.config import RefineConfig
from model.tools.options import checkpoint_option, class_map_option, data_option, threads_option
from model.train.refine import MATCH_IOU, Proposals


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
    threads: int,
) -> None:
    """Train the box refiner on the detector's own boxes (the detector is frozen): on simulated scans, or on
    the training scans of --data (at most --scans of them)."""
    import dataclasses

    import torch

    from model.checkpoint import read_checkpoint, resolve_checkpoint, save_checkpoint
    from model.detector import PHiM
    from model.train.refine import fit

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if threads:
        torch.set_num_threads(threads)
    detector, path = resolve_checkpoint(checkpoint)
    cfg = dataclasses.replace(detector.cfg, refine=RefineConfig(points=points, context=context, flip=flip))
    torch.manual_seed(0)  # the refiner's initial weights
    model = PHiM(cfg)
    weights = {k: v for k, v in detector.state_dict().items() if not k.startswith("refiner.")}
    model.load_state_dict(weights, strict=False)
    if data != "sim":  # one pass over the files (a second stream would read the same scans)
        seeds, scans = seeds[:1], min(scans, len(scan_source(data, 0, classes=class_map)))
    jobs = [(path, cfg.refine, data, class_map, s, scans) for s in seeds]
    with ProcessPoolExecutor(len(jobs), mp_context=multiprocessing.get_context("spawn")) as pool:
        boxes = Proposals.cat(list(pool.map(_stream_proposals, jobs)))
    on_objects = int((boxes.iou >= MATCH_IOU).sum())
    click.echo(f"{len(boxes)} boxes from {len(seeds)} x {scans} scans of {data}, {on_objects} on objects")
    fit(model.refiner, boxes, epochs, lr)
    meta = read_checkpoint(path)["meta"] | {
        "refiner": {
            "detector": path.name,
            "data": data,
            "seeds": list(seeds),
            "scans": scans,
            "epochs": epochs,
            "lr": lr,
        }
    }
    save_checkpoint(out, model, meta)
    click.echo(f"model: {out}")


def _stream_proposals(job: tuple[Path, RefineConfig, str, ClassMap, int, int]) -> Proposals:
    """In a worker process of one thread: the detector's proposals on `scans` scans of `data` (the simulator:
    stream `seed`)."""
    import torch

    from model.checkpoint import load_checkpoint
    from model.train.refine import proposals

    path, cfg, data, classes, seed, scans = job
    torch.set_num_threads(1)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    return proposals(
        load_checkpoint(path), cfg, scan_source(data, seed, shuffle=False, classes=classes), scans
    )
