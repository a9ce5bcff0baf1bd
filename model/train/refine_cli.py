"""`phim train-refiner`: train the box refiner on a frozen detector and write detector + refiner."""

from __future__ import annotations

import logging
import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import click

from model.config import RefineConfig
from model.tools.options import checkpoint_option, threads_option
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
    help="Sim streams (repeat).",
)
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
@threads_option
def train_refiner_cmd(
    checkpoint: str,
    out: Path,
    seeds: tuple[int, ...],
    scans: int,
    epochs: int,
    lr: float,
    points: int,
    threads: int,
) -> None:
    """Train the box refiner on the detector's own boxes on simulated scans (the detector is frozen)."""
    import dataclasses

    import torch

    from model.checkpoint import read_checkpoint, resolve_checkpoint, save_checkpoint
    from model.detector import PHiM
    from model.train.refine import fit

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if threads:
        torch.set_num_threads(threads)
    detector, path = resolve_checkpoint(checkpoint)
    cfg = dataclasses.replace(detector.cfg, refine=RefineConfig(points=points))
    torch.manual_seed(0)  # the refiner's initial weights
    model = PHiM(cfg)
    weights = {k: v for k, v in detector.state_dict().items() if not k.startswith("refiner.")}
    model.load_state_dict(weights, strict=False)
    with ProcessPoolExecutor(len(seeds), mp_context=multiprocessing.get_context("spawn")) as pool:
        data = Proposals.cat(list(pool.map(_stream_proposals, [(path, cfg.refine, s, scans) for s in seeds])))
    on_objects = int((data.iou >= MATCH_IOU).sum())
    click.echo(f"{len(data)} boxes from {len(seeds)} x {scans} scans, {on_objects} on objects")
    fit(model.refiner, data, epochs, lr)
    meta = read_checkpoint(path)["meta"] | {
        "refiner": {"detector": path.name, "seeds": list(seeds), "scans": scans, "epochs": epochs, "lr": lr}
    }
    save_checkpoint(out, model, meta)
    click.echo(f"model: {out}")


def _stream_proposals(job: tuple[Path, RefineConfig, int, int]) -> Proposals:
    """In a worker process of one thread: the detector's proposals on `scans` scans of sim stream `seed`."""
    import torch

    from lidar.sources import scan_source
    from model.checkpoint import load_checkpoint
    from model.train.refine import proposals

    path, cfg, seed, scans = job
    torch.set_num_threads(1)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    return proposals(load_checkpoint(path), cfg, scan_source("sim", seed, shuffle=False), scans)
