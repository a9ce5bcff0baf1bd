"""`phim eval` and `phim diagnose`."""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path
from typing import TYPE_CHECKING

import click

from contract import DEFAULT_MIN_SCORE
from lidar.selection import ClassMap, Split
from model.config import MambaHistory, Precision
from model.tools.options import (
    checkpoint_option,
    class_map_option,
    data_option,
    device_option,
    held_out_seed_option,
    precision_option,
    refiner_option,
)
from phim.options import json_option

if TYPE_CHECKING:
    from lidar.sources import FileSource, SimSource

NewFile = click.Path(dir_okay=False, path_type=Path)
Folder = click.Path(file_okay=False, path_type=Path)


def scans_option(default: int, what: str):
    return click.option(
        "--scans",
        type=click.IntRange(1),
        default=default,
        show_default=True,
        help=f"Scans to {what} (sim: how many; files: at most).",
    )


@click.command()
@checkpoint_option("default")
@data_option(Split.VAL)
@class_map_option
@scans_option(200, "evaluate")
@held_out_seed_option
@json_option
@click.option("--predictions", type=NewFile, help="Write the predictions to this file (native .npz).")
@click.option("--pictures", type=Folder, help="Write a BEV picture per scan into this folder.")
@click.option(
    "--min-score",
    type=click.FloatRange(0.0, 1.0),
    default=DEFAULT_MIN_SCORE,
    show_default=True,
    help="--pictures draw the boxes scored at least this, as a server at this min_score replies (the "
    "scores read every box).",
)
@click.option(
    "--score-curve",
    is_flag=True,
    help="Also precision, recall and F1 per class by score threshold (JSON: score_curve): where to cut the "
    "boxes a server returns (phim serve --min-score).",
)
@click.option(
    "--rescore",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    help="Score a predictions .npz (from --predictions) instead of running a model.",
)
@click.option(
    "--max-range",
    type=click.FloatRange(min=0.0, min_open=True),
    default=75.0,
    show_default=True,
    help="Score only boxes (predicted and labelled) centred within this many metres: every config the same.",
)
@click.option(
    "--turns",
    type=click.IntRange(1),
    default=1,
    show_default=True,
    help="Also stream each scan this many times as one stream and score every turn (the history policy).",
)
@click.option(
    "--history",
    type=click.Choice([h.value for h in MambaHistory]),
    help="Override the checkpoint's streaming-history policy (MambaHistory) for the streamed --turns.",
)
@device_option()
@precision_option
@refiner_option
def eval_cmd(
    checkpoint: str,
    data: str,
    class_map: ClassMap,
    scans: int,
    seed: int,
    as_json: bool,
    predictions: Path | None,
    pictures: Path | None,
    min_score: float,
    score_curve: bool,
    rescore: Path | None,
    max_range: float,
    turns: int,
    history: str | None,
    device: str,
    precision: Precision,
    refiner: bool,
) -> None:
    """Waymo-style AP/APH per class and level, per buffer fill (the full turn and each buffered count), the
    vehicle AP at IoU 0.5 too, and the vehicle check (recall of well-seen vehicles, false boxes per scan)."""
    from lidar.types import LabeledScan
    from model.checkpoint import resolve_checkpoint
    from model.device import pick_device
    from model.eval.metrics import count_ground_truths, format_table
    from model.eval.prediction_files import read_predictions_by_fill, write_predictions
    from model.eval.runner import ScanResult, run_eval, run_rescore, within_range
    from phim.progress import Progress

    source = _source(data, seed, class_map)
    count = min(scans, len(source))
    t0 = time.perf_counter()
    progress, evaluated = Progress("eval"), [0]
    progress(f"{count} scans of {data} to evaluate")

    def on_scan(scan: LabeledScan, r: ScanResult) -> None:
        evaluated[0] += 1
        progress.count("scans evaluated", evaluated[0], count)
        if pictures is not None:
            from model.eval.pictures import draw_result

            draw_result(pictures / f"{r.name}.png", scan, r, min_score)

    by_turn: dict = {}
    if rescore is not None:
        what = f"predictions {rescore}"
        results = run_rescore(read_predictions_by_fill(rescore), range(count), source, on_scan)
    else:
        model, ckpt_path = resolve_checkpoint(checkpoint, pick_device(device))
        if not refiner:  # the detector's own boxes (e.g. the default's, beside a fine-tuned detector's)
            model.drop_refiner()
        what = f"checkpoint {ckpt_path}{'' if refiner else ' (no refiner)'}, precision {precision.value}"
        results = run_eval(model, range(count), source, on_scan, precision)
        if history is not None:
            model.cfg = dataclasses.replace(model.cfg, history=MambaHistory(history))
        if turns > 1:
            from model.eval.turns import run_turns, score_turns

            streamed = run_turns(model, range(count), source, turns, precision)
            by_turn = score_turns([[within_range(r, max_range) for r in rs] for rs in streamed])
    if predictions is not None:
        write_predictions(predictions, results)
    results = [within_range(r, max_range) for r in results]
    metrics = _metrics(results, max_range, by_turn)
    if score_curve:
        from model.eval.score_curve import score_curve as curve_of

        metrics["score_curve"] = curve_of(results)
    if as_json:
        click.echo(json.dumps(metrics, indent=2))
        return
    click.echo(f"{what}, data {data}, {count} scans in {time.perf_counter() - t0:.1f} s")
    click.echo(format_table(metrics, count_ground_truths([r.truths[-1] for r in results])))
    _print_more(metrics)
    if score_curve:
        from model.eval.score_curve import format_curve

        click.echo(format_curve(metrics["score_curve"]))


def _source(data: str, seed: int, class_map: ClassMap) -> SimSource | FileSource:
    """The evaluated scans: custom:DIR's val split (ImageSets/val.txt when present) with its class map, every
    file checked now (a bad one: a usage error naming it, before any model runs)."""
    from lidar.custom import check_custom_files
    from lidar.sources import FileSource, scan_source

    try:
        source = scan_source(data, seed, shuffle=False, split=Split.VAL, classes=class_map)
        if isinstance(source, FileSource) and source.paths[0].suffix == ".npy":
            check_custom_files(list(source.paths), class_map, points=True)
    except ValueError as e:
        raise click.BadParameter(str(e), param_hint="--data / --class-map") from None
    return source


def _metrics(results: list, max_range: float, by_turn: dict) -> dict:
    """Scored results (within range) -> `phim eval --json`'s object."""
    from model.eval.runner import score, vehicle_ap
    from model.eval.vehicle_check import vehicle_check

    metrics = score(results)
    by_iou = {"0.7": metrics["LEVEL_1"]["VEHICLE"]["AP"], "0.5": vehicle_ap(results, 0.5)}
    metrics |= {"max_range": max_range, "vehicle_ap_by_iou": by_iou, "vehicle_check": vehicle_check(results)}
    if by_turn:
        metrics["by_turn"] = by_turn
    return metrics


def _print_more(metrics: dict) -> None:
    """The lines after the AP/APH table: vehicle AP by IoU, the vehicle check, turns, buffer fill."""
    from model.eval.vehicle_check import format_check

    ap = metrics["vehicle_ap_by_iou"]
    click.echo(f"LEVEL_1 VEHICLE AP at 3D IoU 0.7: {ap['0.7']:.4f}, at 0.5: {ap['0.5']:.4f}")
    click.echo(format_check(metrics["vehicle_check"]))
    for t, m in metrics.get("by_turn", {}).items():
        level = m["LEVEL_1"]
        click.echo(
            f"turn {t} of one stream: LEVEL_1 VEHICLE AP {level['VEHICLE']['AP']:.4f}, "
            f"mean AP / APH {level['mean']['AP']:.4f} / {level['mean']['APH']:.4f}"
        )
    click.echo(
        "LEVEL_1 mean AP / APH by buffered sectors: on the sectors seen | on the whole turn (Figure 8)"
    )
    for b, m in metrics["by_buffered_sectors"].items():
        seen, scene = m["LEVEL_1"]["mean"], metrics["by_buffered_sectors_global"][b]["LEVEL_1"]["mean"]
        click.echo(
            f"buffered {b}: {seen['AP']:.3f} / {seen['APH']:.3f} | {scene['AP']:.3f} / {scene['APH']:.3f}"
        )


@click.command()
@checkpoint_option("default")
@data_option(Split.VAL)
@class_map_option
@scans_option(50, "look at")
@held_out_seed_option
@json_option
@device_option()
@click.option(
    "--by",
    type=click.Choice(["class", "points", "range", "group"]),
    default="class",
    show_default=True,
    help="Group by class, or by class and the points inside the box, or by class and range; --matched: by "
    "class, or (group) by class and samples subfolder.",
)
@click.option(
    "--matched",
    is_flag=True,
    help="Instead: the boxes a user gets (refiner included) matched to labels at BEV IoU 0.5, score >= 0.5: "
    "size bias (predicted - labelled) and heading flips, seen side-on and end-on.",
)
@click.option(
    "--rescore",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    help="--matched: read the boxes from a predictions .npz (phim eval --predictions) instead of a model.",
)
@refiner_option
def diagnose_cmd(
    checkpoint: str,
    data: str,
    class_map: ClassMap,
    scans: int,
    seed: int,
    as_json: bool,
    device: str,
    by: str,
    matched: bool,
    rescore: Path | None,
    refiner: bool,
) -> None:
    """Each part of the predicted boxes against the truth, read at the true centre cells, per class; with
    --matched, the size bias and heading flips of the returned boxes that match a label."""
    from model.checkpoint import resolve_checkpoint
    from model.device import pick_device
    from model.eval.diagnose import Breakdown, diagnose, format_diagnosis

    if (by == "group") != (matched and by != "class") or (rescore is not None and not matched):
        raise click.UsageError("--by group and --rescore go with --matched; --by points / range without it")
    source = _source(data, seed, class_map)
    count = min(scans, len(source))
    if matched:
        _diagnose_matched(checkpoint, data, source, count, as_json, device, by == "group", rescore, refiner)
        return
    model, ckpt_path = resolve_checkpoint(checkpoint, pick_device(device))
    result = diagnose(model, range(count), source, by=Breakdown(by))
    if as_json:
        click.echo(json.dumps(result, indent=2))
        return
    click.echo(f"checkpoint {ckpt_path}, data {data}, {count} scans")
    click.echo(format_diagnosis(result))


def _diagnose_matched(
    checkpoint: str,
    data: str,
    source: SimSource | FileSource,
    count: int,
    as_json: bool,
    device: str,
    by_group: bool,
    rescore: Path | None,
    refiner: bool,
) -> None:
    """`phim diagnose --matched`: the full-turn boxes as `phim eval` scores them, matched to the labels."""
    from model.checkpoint import resolve_checkpoint
    from model.device import pick_device
    from model.eval.box_bias import box_bias, format_box_bias
    from model.eval.prediction_files import read_predictions_by_fill
    from model.eval.runner import run_eval, run_rescore, within_range

    if rescore is not None:
        what = f"predictions {rescore}"
        results = run_rescore(read_predictions_by_fill(rescore), range(count), source)
    else:
        model, ckpt_path = resolve_checkpoint(checkpoint, pick_device(device))
        if not refiner:
            model.drop_refiner()
        what = f"checkpoint {ckpt_path}{'' if refiner else ' (no refiner)'}"
        results = run_eval(model, range(count), source)
    result = box_bias([within_range(r, 75.0) for r in results], by_group=by_group)
    if as_json:
        click.echo(json.dumps(result, indent=2))
        return
    click.echo(f"{what}, data {data}, {count} scans")
    click.echo(format_box_bias(result))
