"""`GraphStreamingDetector`: the streaming API of `model.stream.StreamingDetector` over the fixed-shape step.

The host pads the batch to its buckets (`model.graph.buckets`), runs the step (compiled with torch.compile
where asked), copies one flat tensor back (candidates, stats, site counts), re-runs the step with larger
capacities if any sites did not fit, and runs NMS on the candidates. Stream states are fixed-shape tensors
on the device (`GraphStreamState`); input states are never modified, so a failed step changes nothing.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import torch
from torch import Tensor

from model.config import Engine, Precision
from model.detector import PHiM
from model.geometry.boxes import Detections
from model.graph.buckets import CapacityPlanner, batch_bucket, row_bucket
from model.graph.step import STATS, GraphStep
from model.layers.head import Candidates, select_detections
from model.layers.voxelize import PointsError
from model.precision import autocast
from model.stream import SectorResult, StreamingDetector, StreamState

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class GraphStreamState:
    """One stream's state in the graph step's fixed shapes (S = `sector_voxels`)."""

    conv: tuple[Tensor, ...]  # per PHiM block (di, d_conv - 1): the global Mamba's conv state
    ssm: tuple[Tensor, ...]  # per PHiM block (di, N)
    feats: Tensor  # (keep, S, C) backbone outputs of the last `keep` sectors, oldest first
    cols: Tensor  # (keep, S, 2) int64 polar column (r, theta) of each row
    valid: Tensor  # (keep, S) bool
    sectors_seen: int

    @property
    def buffered_sectors(self) -> int:
        return min(self.sectors_seen, self.valid.shape[0])


class GraphStreamingDetector:
    """`step(points, states)` as StreamingDetector's, on the fixed-shape step; `compile` runs it through
    torch.compile(fullgraph=True), one specialisation per (batch, capacity) bucket; the step runs in
    `precision` (`model.precision`)."""

    def __init__(
        self,
        model: PHiM,
        sector_voxels: int = 8192,
        compile: bool = False,
        precision: Precision = Precision.FP32,
    ):
        # folds the batchnorms, checks the precision; validation and initial states
        self.reference = StreamingDetector(model, precision=precision)
        self.precision = precision
        self.model = self.reference.model
        self.cfg = model.cfg
        self.step_module = GraphStep(self.model, sector_voxels)
        self.planner = CapacityPlanner(len(self.step_module.keys))
        self.engine = Engine.GRAPH if compile else Engine.FIXED
        self._blank: GraphStreamState | None = None  # a fresh state: pads a batch to its bucket
        if compile:
            cfg = torch._dynamo.config
            cfg.recompile_limit = max(cfg.recompile_limit, 64)  # one graph per bucket
            self._run = torch.compile(self.step_module, fullgraph=True, dynamic=False)
        else:
            self._run = self.step_module
        log.info("graph streaming detector: sector_voxels=%d compile=%s", sector_voxels, compile)

    @property
    def device(self) -> torch.device:
        return self.reference.device

    @property
    def sector_voxels(self) -> int:
        return self.step_module.sector_voxels

    def calibrate(self, sectors: list[Tensor]) -> None:
        """Learn the capacity ratios from sample sectors with the uncompiled step, so that a compiled
        detector compiles its serving buckets only."""
        run, self._run = self._run, self.step_module
        try:
            state = self.init_state()
            for s in sectors:
                _, (state,) = self.step([s], [state])
        finally:
            self._run = run

    def validate(self, points: Tensor) -> None:
        self.reference.validate(points)

    def init_state(self) -> GraphStreamState:
        d = self.model.backbone.cfg.d_model
        return from_stream_state(self.reference.init_state(), self.cfg.buffer_sectors, self.sector_voxels, d)

    def reset(self, state: GraphStreamState | None = None) -> GraphStreamState:
        return self.init_state()

    @torch.inference_mode()
    def step(
        self, points: list[Tensor], states: list[GraphStreamState]
    ) -> tuple[list[SectorResult], list[GraphStreamState]]:
        """One sector per stream: points[i] (N_i, C) float32 goes with states[i]."""
        if len(points) != len(states):
            raise ValueError(f"{len(points)} sectors but {len(states)} states")
        for p in points:
            self.validate(p)
        n, b = len(points), batch_bucket(len(points))
        if self._blank is None:
            self._blank = self.init_state()
        inputs = self.inputs(points, [*states, *[self._blank] * (b - n)])
        total = sum(int(p.shape[0]) for p in points)
        layout = self.step_module.host_layout(b)
        while True:
            cap = self.planner.capacity(max(int(p.shape[0]) for p in points), total)
            with autocast(self.precision, self.device):
                host, *new = self._run(*inputs, cap)
            cand, stats, counts = layout.split(host.cpu())  # the step's one device -> host copy
            if self.planner.fits(cap, counts[:-1].tolist(), total):
                break
            log.info("graph step: sites did not fit %s (counts %s); running it again", cap, counts.tolist())
        largest = int(counts[-1])
        if largest > self.sector_voxels:
            raise PointsError(
                f"points: a sector of {largest} voxels; the graph step buffers at most {self.sector_voxels} "
                "per sector (sector_voxels)"
            )
        return self._results(cand[:n], stats[:n], states), self._states(new, states)

    def inputs(self, points: list[Tensor], states: list[GraphStreamState]) -> list:
        """Pad the sectors to (B, Np, C) and stack the states."""
        width = max(int(p.shape[1]) for p in points)
        rows = row_bucket(max(int(p.shape[0]) for p in points))
        padded = torch.zeros(len(states), rows, width)  # (B, Np, C)
        for i, p in enumerate(points):
            padded[i, : p.shape[0], : p.shape[1]] = p
        counts = torch.tensor([int(p.shape[0]) for p in points] + [0] * (len(states) - len(points)))
        dev = self.device
        blocks = range(len(states[0].conv))
        return [
            padded.to(dev, non_blocking=True),
            counts.to(dev, non_blocking=True),
            [torch.stack([s.conv[k] for s in states]) for k in blocks],
            [torch.stack([s.ssm[k] for s in states]) for k in blocks],
            torch.stack([s.feats for s in states]),
            torch.stack([s.cols for s in states]),
            torch.stack([s.valid for s in states]),
        ]

    def _results(self, cand: Tensor, stats: Tensor, states: list[GraphStreamState]) -> list[SectorResult]:
        """cand (n, K, 10), stats (n, 3) on the host -> each stream's detections after NMS."""
        c = Candidates(cand[..., :7], cand[..., 7], cand[..., 8].long(), cand[..., 9] > 0)
        dets: list[Detections] = select_detections(c, self.cfg.head)
        kept, out_of_range = STATS.index("points_kept"), STATS.index("points_out_of_range")
        return [
            SectorResult(d, s.buffered_sectors + 1, int(st[kept]), int(st[out_of_range]))
            for d, s, st in zip(dets, states, stats, strict=True)
        ]

    def _states(self, new: list, states: list[GraphStreamState]) -> list[GraphStreamState]:
        conv, ssm, feats, cols, valid = new
        return [
            GraphStreamState(
                tuple(c[i] for c in conv),
                tuple(h[i] for h in ssm),
                feats[i],
                cols[i],
                valid[i],
                s.sectors_seen + 1,
            )
            for i, s in enumerate(states)
        ]


def from_stream_state(state: StreamState, keep: int, sector_voxels: int, channels: int) -> GraphStreamState:
    """An eager stream state in the graph step's shapes: `keep` buffer slots of `sector_voxels` rows, the
    latest sector last; ValueError if a buffered sector has more rows."""
    dev = state.mamba[0].conv.device
    feats = torch.zeros(keep, sector_voxels, channels, device=dev)
    cols = torch.zeros(keep, sector_voxels, 2, dtype=torch.int64, device=dev)
    valid = torch.zeros(keep, sector_voxels, dtype=torch.bool, device=dev)
    for slot, sector in zip(range(keep - len(state.buffer), keep), state.buffer, strict=True):
        n = sector.num_voxels
        if n > sector_voxels:
            raise ValueError(f"a buffered sector of {n} voxels; the graph state holds {sector_voxels}")
        feats[slot, :n] = sector.features
        cols[slot, :n] = sector.coords[:, :2]  # (r, theta)
        valid[slot, :n] = True
    return GraphStreamState(
        conv=tuple(m.conv[0] for m in state.mamba),
        ssm=tuple(m.ssm[0] for m in state.mamba),
        feats=feats,
        cols=cols,
        valid=valid,
        sectors_seen=state.sectors_seen,
    )


def streaming_detector(
    model: PHiM, engine: Engine, sector_voxels: int = 8192, precision: Precision = Precision.FP32
) -> Detector:
    """The detector that runs `model` with `engine` in `precision`."""
    if engine is Engine.EAGER:
        return StreamingDetector(model, precision=precision)
    return GraphStreamingDetector(model, sector_voxels, compile=engine is Engine.GRAPH, precision=precision)


Detector = StreamingDetector | GraphStreamingDetector  # what the server runs
