"""`phim bench model`: per-sector latency of the streaming model with its buffer loaded; `phim bench engines`:
engines against each other in one process (this machine's speed drifts between processes by more than the
differences sought, so a ratio is measured in alternating turns of one run); `phim bench refiner`: the box
refiner's share of a step."""

from __future__ import annotations

import resource
import statistics
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass

import torch
from torch import Tensor

from model.config import Engine, Precision
from model.detector import PHiM
from model.engine import EngineSettings, SectorRejected, StreamEngine, engine_for
from model.graph.engine import GraphStreamingDetector
from model.layers.phim_block import StreamLayout
from model.layers.refine import box_points_many, grown_boxes, refine_many, refiner_forward
from model.ops.scan import resolve_scan
from model.precision import autocast
from model.sectors import split_turn


@dataclass(frozen=True)
class ModelBench:
    config: str
    device: str
    engine: str  # model.config.Engine
    precision: str  # model.config.Precision
    scan: str  # the selective-scan implementation that ran (model/ops/scan.py)
    refiner: bool  # the box refiner ran after each step
    threads: int
    batch: int  # streams per forward
    sector_points: int  # graph: the points every sector was padded to (0: its own bucket)
    bev_crop: bool  # graph: the dense part on crops after a stream's first turn
    sectors_per_turn: int
    points_per_sector: list[int]
    iterations: int  # timed steps
    p50_ms: float
    p90_ms: float
    mean_ms: float
    per_sector_p50_ms: list[float]
    peak_mem_mb: float  # CUDA: max allocated during the timed steps; CPU: peak process RSS
    full_turn_peak_mem_mb: float | None  # CUDA only: one whole-turn pass, batch 1

    def to_dict(self) -> dict:
        return asdict(self)


Progress = Callable[[str], None]  # says what a benchmark is doing (the CLI prints it on stderr)


def _silent(what: str) -> None:
    """No progress reports."""


def _turn_stage(t: int, warmup: int, timed: int) -> str:
    """What turn `t` (0-based, warm-up first) of a benchmark is."""
    if t < warmup:
        return f"warm-up turn {t + 1} of {warmup} (a graph engine compiles here)"
    return f"timed turn {t - warmup + 1} of {timed}"


def _device_name(dev: torch.device) -> str:
    return str(dev) if dev.type == "cpu" else torch.cuda.get_device_name(dev)


def _sync(dev: torch.device) -> None:
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


def _full_turn_peak(model: PHiM, sectors: list[Tensor], precision: Precision) -> float | None:
    dev = model.device
    if dev.type != "cuda":
        return None
    torch.cuda.reset_peak_memory_stats(dev)
    with torch.inference_mode(), autocast(precision, dev):
        model.forward_turn([s.to(dev) for s in sectors])
    _sync(dev)
    return torch.cuda.max_memory_allocated(dev) / 2**20


class _Streams:
    """`batch` streams of one detector, each stepped through the same sectors (a graph detector first learns
    its capacities from them)."""

    def __init__(self, det: StreamEngine, sectors: list[Tensor], batch: int = 1):
        if isinstance(det, GraphStreamingDetector):
            det.calibrate(sectors)
        self.det, self.sectors, self.batch = det, sectors, batch
        self.states = [det.new_state() for _ in range(batch)]

    def turn(self) -> list[float]:
        """Step every sector once; the ms of each step."""
        dev, out = self.det.device, []
        for sector in self.sectors:
            _sync(dev)
            t0 = time.perf_counter()
            results, self.states = self.det.step([sector] * self.batch, self.states)
            _sync(dev)
            rejected = [r for r in results if isinstance(r, SectorRejected)]
            if rejected:  # a step that skipped a stream's sector would be timed as if it had run
                raise ValueError(rejected[0].message)
            out.append((time.perf_counter() - t0) * 1e3)
        return out


def bench_model(
    model: PHiM,
    turn: Tensor,
    batch: int = 1,
    turns: int = 10,
    warmup_turns: int = 2,
    engine: Engine = Engine.EAGER,
    precision: Precision = Precision.FP32,
    sector_points: int = 0,
    bev_crop: bool = True,
    progress: Progress = _silent,
) -> ModelBench:
    """Stream `turn` (N, C) split into sectors, `batch` streams at once, in `precision`; time every step
    after warm-up (a graph engine first learns its capacities from the turn, and compiles during the
    warm-up; every sector padded to `sector_points` shares one bucket; `bev_crop`: its dense part on crops
    after a stream's first turn)."""
    settings = EngineSettings(
        engine=engine, precision=precision, sector_points=sector_points, bev_crop=bev_crop
    )
    det = engine_for(model, settings)
    dev = det.device
    cfg = model.cfg
    sectors = [s.to(dev) for s in split_turn(turn, cfg.sectors_per_turn)]
    run = _Streams(det, sectors, batch)
    times: dict[int, list[float]] = {k: [] for k in range(len(sectors))}
    if dev.type == "cuda":
        torch.cuda.reset_peak_memory_stats(dev)
    for t in range(warmup_turns + turns):
        progress(_turn_stage(t, warmup_turns, turns))
        for k, ms in enumerate(run.turn()):
            if t >= warmup_turns:
                times[k].append(ms)
    if dev.type == "cuda":
        peak = torch.cuda.max_memory_allocated(dev) / 2**20
    else:
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    all_ms = sorted(x for v in times.values() for x in v)
    return ModelBench(
        config=cfg.name,
        device=_device_name(dev),
        engine=engine.value,
        precision=precision.value,
        scan=resolve_scan(cfg.backbone.mamba.scan, dev).value,
        refiner=model.refiner is not None,
        threads=torch.get_num_threads(),
        batch=batch,
        sector_points=sector_points,
        bev_crop=bool(det.describe().bev_crop),
        sectors_per_turn=len(sectors),
        points_per_sector=[int(s.shape[0]) for s in sectors],
        iterations=len(all_ms),
        p50_ms=round(statistics.median(all_ms), 2),
        p90_ms=round(all_ms[int(0.9 * (len(all_ms) - 1))], 2),
        mean_ms=round(statistics.fmean(all_ms), 2),
        per_sector_p50_ms=[round(statistics.median(v), 2) for v in times.values()],
        peak_mem_mb=round(peak, 1),
        full_turn_peak_mem_mb=_full_turn_peak(model, sectors, precision),
    )


@dataclass(frozen=True)
class EngineComparison:
    config: str
    device: str
    precision: str
    scan: str  # the eager engine's selective scan (the graph engine has its own)
    refiner: bool  # the box refiner ran after each step
    threads: int
    engines: list[str]  # the first is the one the others are divided by
    points_per_sector: list[int]
    rounds: int  # timed turns of each engine, alternating (the order reversed every other round)
    p50_ms: dict[str, float]
    p90_ms: dict[str, float]
    ratio_p50: dict[str, float]  # each engine's p50 / the first's
    round_ratios: dict[str, list[float]]  # per round: its turn's p50 / the first engine's turn's p50

    def to_dict(self) -> dict:
        return asdict(self)


def compare_engines(
    model: PHiM,
    turn: Tensor,
    engines: list[Engine],
    rounds: int = 10,
    warmup_turns: int = 2,
    precision: Precision = Precision.FP32,
    progress: Progress = _silent,
) -> EngineComparison:
    """Stream `turn` through a detector of each engine (one stream each, same weights) in alternating turns,
    after `warmup_turns` of each (compiles there); the ratios of their p50s, overall and per round."""
    if len(engines) < 2 or len(set(engines)) != len(engines):
        raise ValueError(f"engines: {[e.value for e in engines]}; expected two or more different engines")
    sectors = [s.to(model.device) for s in split_turn(turn, model.cfg.sectors_per_turn)]
    runs = {
        e: _Streams(engine_for(model, EngineSettings(engine=e, precision=precision)), sectors)
        for e in engines
    }
    for t in range(warmup_turns):
        progress(_turn_stage(t, warmup_turns, rounds) + " of each engine")
        for run in runs.values():
            run.turn()
    times: dict[Engine, list[list[float]]] = {e: [] for e in engines}
    for r in range(rounds):
        progress(_turn_stage(warmup_turns + r, warmup_turns, rounds) + " of each engine")
        for e in engines if r % 2 == 0 else engines[::-1]:
            times[e].append(runs[e].turn())
    flat = {e: sorted(x for t in ts for x in t) for e, ts in times.items()}
    p50 = {e: statistics.median(v) for e, v in flat.items()}
    base = engines[0]
    per_round = {
        e: [statistics.median(a) / statistics.median(b) for a, b in zip(ts, times[base], strict=True)]
        for e, ts in times.items()
    }
    return EngineComparison(
        config=model.cfg.name,
        device=_device_name(model.device),
        precision=precision.value,
        scan=resolve_scan(model.cfg.backbone.mamba.scan, model.device).value,
        refiner=model.refiner is not None,
        threads=torch.get_num_threads(),
        engines=[e.value for e in engines],
        points_per_sector=[int(s.shape[0]) for s in sectors],
        rounds=rounds,
        p50_ms={e.value: round(v, 2) for e, v in p50.items()},
        p90_ms={e.value: round(v[int(0.9 * (len(v) - 1))], 2) for e, v in flat.items()},
        ratio_p50={e.value: round(p50[e] / p50[base], 3) for e in engines},
        round_ratios={e.value: [round(x, 3) for x in v] for e, v in per_round.items()},
    )


@dataclass(frozen=True)
class RefinerBench:
    config: str
    device: str
    threads: int
    streams: int  # a batch of this many streams, each with the same turn
    points: int  # the turn's points, which every step's refiner searches (each stream's, on the host)
    boxes: int  # the detector's boxes on the whole turn, which it refines (each stream's)
    points_per_box: int  # RefineConfig.points
    stages: int  # RefineConfig.stages: refine_many runs a lookup and a PointNet per stage
    repeats: int
    lookup_p50_ms: float  # box_points_many: the batch's lookups (one stage's)
    pointnet_p50_ms: float  # the first stage's forward over the batch's boxes (one stage's)
    refine_p50_ms: float  # refine_many(): every stage's lookups and PointNet, the residuals and the re-sort

    def to_dict(self) -> dict:
        return asdict(self)


def bench_refiner(
    model: PHiM, turn: Tensor, repeats: int = 30, streams: int = 1, progress: Progress = _silent
) -> RefinerBench:
    """The box refiner on the detector's boxes for the whole `turn` (what it does after every step with its
    buffer loaded) for a batch of `streams` streams with that turn, as a server holds them (the points on
    the host), `repeats` times each: one stage's point lookups and PointNet, and all of `refine_many`."""
    if model.refiner is None:
        raise ValueError(f"the model ({model.cfg.name}) has no box refiner")
    dev, cfg = model.device, model.refiner.cfg
    sectors = split_turn(turn, model.cfg.sectors_per_turn)
    points = [torch.cat(sectors)[:, :3].contiguous()] * streams  # (N, 3) each, on the host
    with torch.inference_mode():
        progress("detecting the turn's boxes (the refiner's input)")
        on_dev = [s.to(dev) for s in sectors]
        enc = model.encode(on_dev, StreamLayout.single_stream(len(sectors), dev), model.init_states(1))
        dets = [model.detect([enc.sectors])[0].to("cpu")] * streams
        boxes = [grown_boxes(d.boxes, d.labels, cfg) for d in dets]  # the first stage's outlines
        looked = box_points_many(points, boxes, cfg.points)
        local, counts = (torch.cat([lc[i] for lc in looked]).to(dev) for i in (0, 1))
        inputs = [torch.cat([getattr(d, f) for d in dets]).to(dev) for f in ("boxes", "scores", "labels")]
        runs = {
            "lookup": lambda: box_points_many(points, boxes, cfg.points),
            "pointnet": lambda: refiner_forward(model.refiner, local, counts, *inputs),
            "refine": lambda: refine_many(model.refiner, dets, points),
        }
        progress(f"timing lookup, PointNet and refine on {len(dets[0])} boxes, {repeats} + 2 runs of each")
        p50 = _interleaved(runs, repeats, dev)
    return RefinerBench(
        config=model.cfg.name,
        device=_device_name(dev),
        threads=torch.get_num_threads(),
        streams=streams,
        points=int(points[0].shape[0]),
        boxes=len(dets[0]),
        points_per_box=cfg.points,
        stages=cfg.stages,
        repeats=repeats,
        lookup_p50_ms=p50["lookup"],
        pointnet_p50_ms=p50["pointnet"],
        refine_p50_ms=p50["refine"],
    )


def _interleaved(runs: dict, repeats: int, dev: torch.device) -> dict[str, float]:
    """Each run `repeats` times, in turns (the first two rounds warm-up) -> p50 ms by name."""
    times: dict[str, list[float]] = {k: [] for k in runs}
    for i in range(repeats + 2):
        for k, run in runs.items():
            _sync(dev)
            t0 = time.perf_counter()
            run()
            _sync(dev)
            if i >= 2:
                times[k].append((time.perf_counter() - t0) * 1e3)
    return {k: round(statistics.median(v), 2) for k, v in times.items()}
