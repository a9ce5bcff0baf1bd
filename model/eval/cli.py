"""`phim eval` and `phim diagnose`."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Annotated

import typer

DataOpt = Annotated[str, typer.Option("--data", help="sim, kitti:DIR, nuscenes:DIR or native:DIR")]
DeviceOpt = Annotated[str, typer.Option("--device", help="auto (cuda if present), cpu, cuda, cuda:1")]
CheckpointOpt = Annotated[str, typer.Option("--checkpoint", help="a checkpoint file, or 'default'")]
HeldOutSeedOpt = Annotated[int, typer.Option(help="sim stream of the held-out scans")]


def eval_cmd(
    checkpoint: CheckpointOpt = "default",
    data: DataOpt = "sim",
    scans: Annotated[int, typer.Option(help="scans to evaluate (sim: how many; files: at most)")] = 200,
    seed: HeldOutSeedOpt = 7,
    as_json: Annotated[bool, typer.Option("--json", help="print the metrics as JSON only")] = False,
    predictions: Annotated[Path | None, typer.Option(help="write predictions (native .npz) here")] = None,
    pictures: Annotated[
        Path | None, typer.Option(help="write a BEV picture per scan into this folder")
    ] = None,
    rescore: Annotated[
        Path | None, typer.Option(help="score a predictions .npz (from --predictions) instead of a model")
    ] = None,
    device: DeviceOpt = "auto",
) -> None:
    """Waymo-style AP/APH per class and level, full turn and per buffered sectors."""
    from model.checkpoint import resolve_checkpoint
    from model.data.sources import scan_source
    from model.data.types import LabeledScan
    from model.device import pick_device
    from model.eval.metrics import count_ground_truths, format_table
    from model.eval.prediction_files import read_predictions_by_fill, write_predictions
    from model.eval.runner import ScanResult, run_eval, run_rescore, score
    from phim.process import tune_malloc

    tune_malloc()
    source = scan_source(data, seed, shuffle=False)
    count = min(scans, len(source))
    t0 = time.perf_counter()

    def on_scan(scan: LabeledScan, r: ScanResult) -> None:
        if pictures is not None:
            from model.eval.pictures import draw_result

            draw_result(pictures / f"{r.name}.png", scan, r)

    if rescore is not None:
        what = f"predictions {rescore}"
        results = run_rescore(read_predictions_by_fill(rescore), range(count), source, on_scan)
    else:
        model, ckpt_path = resolve_checkpoint(checkpoint, pick_device(device))
        what = f"checkpoint {ckpt_path}"
        results = run_eval(model, range(count), source, on_scan)
    metrics = score(results)
    if predictions is not None:
        write_predictions(predictions, results)
    if as_json:
        typer.echo(json.dumps(metrics, indent=2))
        return
    typer.echo(f"{what}, data {data}, {count} scans in {time.perf_counter() - t0:.1f} s")
    typer.echo(format_table(metrics, count_ground_truths([r.truths[-1] for r in results])))
    typer.echo(
        "LEVEL_1 mean AP / APH by buffered sectors: on the sectors seen | on the whole turn (Figure 8)"
    )
    for b, m in metrics["by_buffered_sectors"].items():
        seen, scene = m["LEVEL_1"]["mean"], metrics["by_buffered_sectors_global"][b]["LEVEL_1"]["mean"]
        typer.echo(
            f"buffered {b}: {seen['AP']:.3f} / {seen['APH']:.3f} | {scene['AP']:.3f} / {scene['APH']:.3f}"
        )


def diagnose_cmd(
    checkpoint: CheckpointOpt = "default",
    data: DataOpt = "sim",
    scans: Annotated[int, typer.Option(help="scans to look at (sim: how many; files: at most)")] = 50,
    seed: HeldOutSeedOpt = 7,
    as_json: Annotated[bool, typer.Option("--json", help="print JSON only")] = False,
    device: DeviceOpt = "auto",
    by: Annotated[str, typer.Option(help="group by: class, points (inside the box) or range")] = "class",
) -> None:
    """Each part of the predicted boxes against the truth, read at the true centre cells, per class."""
    from model.checkpoint import resolve_checkpoint
    from model.data.sources import scan_source
    from model.device import pick_device
    from model.eval.diagnose import Breakdown, diagnose, format_diagnosis
    from phim.process import tune_malloc

    if by not in {b.value for b in Breakdown}:
        raise typer.BadParameter(f"{by!r}; expected one of {[b.value for b in Breakdown]}", param_hint="--by")

    tune_malloc()
    source = scan_source(data, seed, shuffle=False)
    count = min(scans, len(source))
    model, ckpt_path = resolve_checkpoint(checkpoint, pick_device(device))
    result = diagnose(model, range(count), source, by=Breakdown(by))
    if as_json:
        typer.echo(json.dumps(result, indent=2))
        return
    typer.echo(f"checkpoint {ckpt_path}, data {data}, {count} scans")
    typer.echo(format_diagnosis(result))
