"""`phim model info`, `phim bench model`, `engines`, `refiner` and `ops` as commands (their numbers are
benchmarks, not checked here)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from lidar.sources import scan_source
from lidar.synthetic import synthetic_turn
from model.checkpoint import resolve_checkpoint, save_checkpoint
from model.config import Engine, PHiMConfig, paper, tiny
from model.detector import PHiM
from model.graph.bev import dense_cell_table
from model.graph.bev_crop import crop_plan
from model.tools.op_count import count_ops
from phim.cli import main as app


def test_model_info_paper_is_within_ten_percent_of_the_papers_parameters(tmp_path: Path) -> None:
    g = np.random.default_rng(0)  # a small scan keeps the counted forwards quick; params do not depend on it
    r, a = g.uniform(3, 60, 4000), g.uniform(-np.pi, np.pi, 4000)
    scan = np.stack([r * np.cos(a), r * np.sin(a), g.uniform(-1.5, 2, 4000), g.uniform(0, 1, 4000)], 1)
    scan.astype(np.float32).tofile(tmp_path / "scan.bin")
    args = ["model", "info", "--config", "paper", "--points", str(tmp_path / "scan.bin"), "--json"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    info = json.loads(result.stdout)  # stderr: its progress lines
    assert isinstance(info["params"], int) and abs(info["params"] / 11.8e6 - 1) <= 0.10
    assert info["gflops"] > 0 and info["input_points"] == 4000


@pytest.mark.parametrize(("precision", "refiner"), [("fp32", "--refiner"), ("bf16", "--no-refiner")])
def test_bench_model_runs_the_shipped_weights(precision: str, refiner: str) -> None:
    args = ["bench", "model", "--config", "tiny", "--checkpoint", "default", "--turns", "1", "--json"]
    result = CliRunner().invoke(app, [*args, "--precision", precision, refiner])
    assert result.exit_code == 0, result.output
    bench = json.loads(result.output.strip().splitlines()[-1])
    assert bench["precision"] == precision and bench["refiner"] is (refiner == "--refiner")
    assert bench["device"] == "cpu" and bench["sectors_per_turn"] == 4 and bench["iterations"] == 4
    assert 0 < bench["p50_ms"] <= bench["p90_ms"] and bench["peak_mem_mb"] > 0


def test_bench_model_names_a_missing_checkpoint() -> None:
    result = CliRunner().invoke(app, ["bench", "model", "--checkpoint", "no/such.pt", "--turns", "1"])
    assert result.exit_code != 0
    assert "no/such.pt" in str(result.exception)


@pytest.mark.slow  # the graph engine compiles its buckets in the warm-up turns
def test_bench_engines_alternates_the_engines_and_divides_by_the_first() -> None:
    args = ["bench", "engines", "--config", "tiny", "--checkpoint", "default", "--engines", "eager,graph"]
    result = CliRunner().invoke(app, [*args, "--rounds", "3", "--scan", "chunked", "--no-refiner", "--json"])
    assert result.exit_code == 0, result.output
    bench = json.loads(result.output.strip().splitlines()[-1])
    assert bench["engines"] == ["eager", "graph"] and bench["rounds"] == 3 and bench["device"] == "cpu"
    assert bench["refiner"] is False
    assert bench["scan"] == "chunked"  # the eager engine's, as asked
    p50 = bench["p50_ms"]
    assert 0 < p50["graph"] <= bench["p90_ms"]["graph"] and 0 < p50["eager"] <= bench["p90_ms"]["eager"]
    assert bench["ratio_p50"] == {"eager": 1.0, "graph": pytest.approx(p50["graph"] / p50["eager"], abs=2e-3)}
    assert bench["round_ratios"]["eager"] == [1.0] * 3 and len(bench["round_ratios"]["graph"]) == 3
    assert all(r > 0 for r in bench["round_ratios"]["graph"])


@pytest.mark.parametrize("engines", ["graph", "eager,eager", "eager,jit"])
def test_bench_engines_names_a_bad_engine_list(engines: str) -> None:
    result = CliRunner().invoke(app, ["bench", "engines", "--engines", engines])
    assert result.exit_code == 2 and "--engines" in result.output and "two or more different" in result.output


@pytest.mark.parametrize("streams", [1, 3])
def test_bench_refiner_times_the_shipped_refiner_on_a_whole_turns_boxes(tmp_path: Path, streams: int) -> None:
    scan = scan_source("sim", 7, shuffle=False)(0).points  # a scan with boxes, samples or not
    scan.astype(np.float32).tofile(tmp_path / "scan.bin")
    args = ["bench", "refiner", "--points", str(tmp_path / "scan.bin"), "--repeats", "2", "--json"]
    result = CliRunner().invoke(app, [*args, "--streams", str(streams)])
    assert result.exit_code == 0, result.output
    bench = json.loads(result.output.strip().splitlines()[-1])
    assert bench["config"] == "tiny" and bench["repeats"] == 2 and bench["boxes"] > 0 and bench["points"] > 0
    assert bench["streams"] == streams and bench["points"] == len(scan)
    refine = resolve_checkpoint("default")[0].cfg.refine
    assert (bench["points_per_box"], bench["stages"]) == (refine.points, refine.stages)
    assert min(bench["lookup_p50_ms"], bench["pointnet_p50_ms"], bench["refine_p50_ms"]) > 0


def test_bench_refiner_names_a_checkpoint_without_one(tmp_path: Path) -> None:
    save_checkpoint(tmp_path / "plain.pt", PHiM(tiny()), {})
    result = CliRunner().invoke(app, ["bench", "refiner", "--checkpoint", str(tmp_path / "plain.pt")])
    assert result.exit_code == 2 and "--checkpoint" in result.output and "no box refiner" in result.output


def test_bench_ops_credits_every_op_to_a_model_function() -> None:
    args = ["bench", "ops", "--config", "tiny", "--checkpoint", "default", "--json"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    report = json.loads(result.output.strip().splitlines()[-1])
    rows = {r["where"]: r for r in report["rows"]}
    assert report["device"] == "cpu" and report["cuda_kernels"] is None
    assert sum(r["ops"] for r in rows.values()) == report["ops"] > report["ops_outside_scan"] > 0
    assert sum(r["host_syncs"] for r in rows.values()) == report["host_syncs"] > 0
    # the Mamba layers, the rule books (their `nonzero` waits for a GPU) and the scan (numba's) are all seen
    assert rows["model/layers/mamba.py: forward"]["ops"] > 0
    assert rows["model/geometry/rulebook.py: build_strided_rulebook"]["host_syncs"] > 0
    assert report["scan"] == "numba" and any(w.startswith("model/ops/scan_numba.py") for w in rows)


def test_the_graph_step_never_waits_for_the_device(tmp_path: Path) -> None:
    """`phim bench ops --engine graph`: no op between the inputs on the device and the host copy syncs."""
    points = tmp_path / "turn.bin"
    synthetic_turn(seed=0)[::8].astype(np.float32).tofile(points)  # thinned: a few CPU steps
    args = ["bench", "ops", "--config", "tiny", "--engine", "graph", "--points", str(points), "--json"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    report = json.loads(result.output.strip().splitlines()[-1])
    assert report["engine"] == "graph" and report["ops"] > 100
    assert report["host_syncs"] == 0, [r for r in report["rows"] if r["host_syncs"]]


def narrow_paper() -> PHiMConfig:
    """The paper config's layers, grids, crops and heading code, every layer 16 channels wide: the graph
    step runs the same ops as the paper config's on a fraction of the arithmetic."""
    p = paper()
    return dataclasses.replace(
        p,
        vfe=dataclasses.replace(p.vfe, hidden=(16,)),
        backbone=dataclasses.replace(p.backbone, d_model=16),
        bev=dataclasses.replace(p.bev, num_filters=(16, 16, 32), num_upsample_filters=(16, 16, 16)),
        head=dataclasses.replace(p.head, shared_channels=16, head_channels=16),
    )


def test_the_paper_configs_graph_step_never_waits_for_the_device() -> None:
    """The same count (`count_ops`, which `phim bench ops --config paper --engine graph` runs) for the paper
    config's layers: its step after a turn runs its dense part on crops of the map, as the paper's does."""
    cfg = narrow_paper()
    model = PHiM(cfg).eval()
    assert crop_plan(cfg, dense_cell_table(model.to_bev)) is not None  # the crops of the paper's map
    turn = torch.from_numpy(synthetic_turn(seed=0)[::8].astype(np.float32))  # (N, 4): as --points reads it
    report = count_ops(model, turn, Engine.GRAPH)
    assert report.engine == "graph" and report.config == "paper" and report.ops > 100
    assert report.host_syncs == 0, [r for r in report.rows if r.host_syncs]
