"""What every engine shares (`model.engine` is the interface the server sees; this module is beneath both
engines): the outcome types, the one error for running out of stream states, the engine's description, and
`EngineBase`, the frame around each engine's own step and warm-up.

`EngineBase.step` checks the batch, drops the ego vehicle's points (`cfg.ego`, model.ego) before the
engine's own `_step` and the boxes centred on it after: the one place either engine applies the footprint.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from lidar.synthetic import synthetic_turn
from model.config import Engine, PHiMConfig, Precision, ScanImpl
from model.ego import drop_ego_boxes, drop_ego_points
from model.geometry.boxes import Detections
from model.layers.voxelize import PointsError, validate_points
from model.ops.nms_numba import compile_kernels as compile_nms_kernels
from model.ops.scan import resolve_scan
from model.sectors import split_turn

log = logging.getLogger(__name__)


class StatesExhausted(RuntimeError):
    """A fixed-shape engine has no free stream-state slot for a new stream."""


@dataclass(frozen=True)
class SectorResult:
    detections: Detections  # boxes over everything the buffer covers (up to 360 degrees)
    context_sectors: int  # sectors the prediction saw: the new one plus the buffered ones
    points_kept: int
    points_out_of_range: int


@dataclass(frozen=True)
class SectorRejected:
    """A sector its stream could not run (the batch's other streams ran); the stream's state is unchanged."""

    field: str  # the sector message's field at fault
    message: str  # what was wrong and what is expected
    voxels: int  # the sector's voxels


SectorOutcome = SectorResult | SectorRejected


@dataclass(frozen=True)
class EngineInfo:
    """What an engine is (GET /v1/model reports it); None where a field does not apply to the engine."""

    engine: Engine
    device: str
    precision: Precision
    scan: ScanImpl  # as configured (auto: the best available)
    scan_impl: ScanImpl  # what runs on this device
    refiner: bool  # the box refiner runs after each step
    # a fixed-shape engine's (None for an engine without fixed shapes)
    sector_voxels: int | None = None  # voxel rows a stream buffers per sector
    sector_points: int | None = None  # points every sector is planned for at least
    bev_crop: bool | None = None  # the dense part on crops around each new sector
    state_slots: int | None = None  # device-resident stream states (None: one state per stream)
    slot_bytes: int | None = None  # one slot's bytes
    slot_memory_mb: float | None = None  # every slot and the blank row, MiB
    batch_buckets: tuple[int, ...] | None = None  # the batch sizes a step pads to (None: unpadded)


class EngineBase:
    """The frame both engines share. A subclass sets `cfg`, `engine` and `precision`, defines `_step` (the
    batch already checked, without the ego vehicle's points) and `device`."""

    cfg: PHiMConfig
    engine: Engine
    precision: Precision

    @property
    def device(self) -> torch.device:
        raise NotImplementedError

    def validate(self, points: Tensor) -> None:
        """Raise PointsError if a sector's points can't be run."""
        validate_points(points)
        if points.dtype != torch.float32:
            raise PointsError(f"points: dtype {points.dtype}; expected float32")

    @torch.inference_mode()
    def step(self, points: list[Tensor], states: Sequence[Any]) -> tuple[list[SectorOutcome], list[Any]]:
        """One sector per stream: points[i] (N_i, C) float32 goes with states[i]. Per stream its outcome and
        new state (in order); a rejected sector's stream keeps its state. Input states are never modified."""
        if len(points) != len(states):
            raise ValueError(f"{len(points)} sectors but {len(states)} states")
        return self._without_ego(points, lambda kept: self._step(kept, list(states)))

    def _step(self, points: list[Tensor], states: list[Any]) -> tuple[list[SectorOutcome], list[Any]]:
        raise NotImplementedError

    def _without_ego(
        self, points: list[Tensor], run: Callable[[list[Tensor]], tuple[list[SectorOutcome], list[Any]]]
    ) -> tuple[list[SectorOutcome], list[Any]]:
        """Validate the sectors, run `run` on them without the ego vehicle's points (the box refiner reads
        what is left), and drop the boxes centred on it from its results."""
        for p in points:
            self.validate(p)
        ego = self.cfg.ego
        outcomes, new_states = run(drop_ego_points(points, ego))
        outcomes = [
            dataclasses.replace(o, detections=drop_ego_boxes(o.detections, ego))
            if isinstance(o, SectorResult)
            else o
            for o in outcomes
        ]
        return outcomes, new_states

    def _info(self, **fixed_shape: Any) -> EngineInfo:
        """The description: what every engine has, and `fixed_shape` (EngineInfo's fields of a fixed-shape
        engine)."""
        scan = self.cfg.backbone.mamba.scan
        return EngineInfo(
            engine=self.engine,
            device=str(self.device),
            precision=self.precision,
            scan=scan,
            scan_impl=resolve_scan(scan, self.device),
            refiner=self.cfg.refine is not None,
            **fixed_shape,
        )

    def _warm_up_turn(self, sectors: int) -> list[Tensor] | None:
        """Compile the CPU NMS kernels (or load them from numba's cache: whether a forward reaches NMS depends
        on the weights and the turn); then, if a warm-up of `sectors` steps runs any, the synthetic turn's
        sectors, (N_k, 4) each."""
        compile_nms_kernels()
        if sectors <= 0:
            return None
        return split_turn(torch.from_numpy(synthetic_turn(seed=0)), self.cfg.sectors_per_turn)

    def _timed_steps(self, turn: list[Tensor], sectors: int, first: Any, pair: Any | None) -> float:
        """`sectors` single-stream steps from state `first` through the turn, then (with `pair`, a fresh
        state) one batch of two streams; the mean seconds of one step."""
        state = first
        t0 = time.monotonic()
        for i in range(sectors):
            _, (state,) = self.step([turn[i % len(turn)]], [state])
        if pair is not None:
            self.step(turn[:2], [pair, state])
        forwards = sectors + int(pair is not None)
        mean_s = (time.monotonic() - t0) / forwards
        log.info("warm-up: %d forwards, %.1f ms each on average", forwards, mean_s * 1e3)
        return mean_s
