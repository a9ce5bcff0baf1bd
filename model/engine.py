"""The engine interface: how the server (and any other caller) runs the model, whatever runs it.

Two engines implement `StreamEngine`: `model.stream.StreamingDetector` (eager: the model as written,
data-dependent shapes, the reference) and `model.graph.engine.GraphStreamingDetector` (graph: the
fixed-shape step over preallocated device-resident state slots, compiled with torch.compile). A caller
holds each stream's state as an opaque `EngineState`: `new_state` makes one (StatesExhausted where a
fixed-shape engine has no free slot), `step` runs a batch of sectors of different streams and returns
their outcomes and new states, `reset` gives a stream a fresh state (nothing written before a step
succeeds), `release` gives a state back when its stream leaves. `warm_up` prepares the engine before it
serves (each engine its own way), `describe` says what it is. `build_engine` builds the engine that
`EngineSettings` name, loading its weights.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

from torch import Tensor

from model.checkpoint import init_model, load_checkpoint, load_default_model
from model.config import EgoFootprint, Engine, PHiMConfig, Precision, get_config
from model.detector import PHiM
from model.device import pick_device
from model.engine_base import EngineInfo, SectorOutcome, SectorRejected, SectorResult, StatesExhausted
from model.graph.engine import DEFAULT_SLOTS, GraphStreamingDetector
from model.stream import StreamingDetector

__all__ = [
    "EngineInfo",
    "EngineSettings",
    "EngineState",
    "SectorOutcome",
    "SectorRejected",
    "SectorResult",
    "StatesExhausted",
    "StreamEngine",
    "build_engine",
    "engine_for",
]

log = logging.getLogger(__name__)


class EngineState(Protocol):
    """One stream's state, opaque to the caller (immutable: a step returns a new one)."""

    @property
    def buffered_sectors(self) -> int: ...


class StreamEngine(Protocol):
    """What every engine does (module docstring). `cfg` is the model's config."""

    cfg: PHiMConfig

    def new_state(self) -> EngineState:
        """A new stream's fresh state; StatesExhausted when a fixed-shape engine has no free slot."""
        ...

    def release(self, state: EngineState) -> None:
        """The stream left: its state goes back (nothing to do for the eager engine)."""
        ...

    def reset(self, state: EngineState) -> EngineState:
        """A fresh state for the stream (the same slot for a fixed-shape engine, nothing written)."""
        ...

    def validate(self, points: Tensor) -> None:
        """PointsError if a sector's (N, C) points can't be run."""
        ...

    def step(
        self, points: list[Tensor], states: Sequence[EngineState]
    ) -> tuple[list[SectorOutcome], list[EngineState]]:
        """One sector per stream, points[i] (N_i, C) float32 with states[i] -> per stream its outcome and new
        state (a SectorRejected stream keeps its state); a failed step changes no state."""
        ...

    def warm_up(self, sectors: int, max_batch: int = 1) -> float:
        """Before serving: `sectors` warm-up steps, batches planned up to `max_batch` streams (a fixed-shape
        engine derives its capacities and padding from a synthetic turn) -> the mean seconds of one step."""
        ...

    def describe(self) -> EngineInfo: ...


@dataclass(frozen=True)
class EngineSettings:
    """Which engine runs which weights, where and how."""

    checkpoint: Path | None = None  # None: `config` untrained, or the shipped default without a config
    config: str | None = None  # a named config: checked against the checkpoint's, or served untrained
    device: str = "auto"  # auto, cpu, cuda or cuda:N (model.device)
    engine: Engine = Engine.EAGER
    precision: Precision = Precision.FP32
    refiner: bool = True  # run the model's box refiner, where it has one
    # x_min, x_max, y_min, y_max (m) of the ego vehicle; (): none; None: the config's
    ego_footprint: tuple[float, ...] | None = None
    slots: int = DEFAULT_SLOTS  # graph: stream-state slots (a server's max_streams)
    sector_voxels: int = 0  # graph: voxel rows a stream buffers per sector (0: the config's)
    # graph: points every sector is planned for at least (0: the batch's largest; a warm-up derives it)
    sector_points: int = 0
    bev_crop: bool = True  # graph: the dense part on crops around each new sector after a stream's turn


def engine_for(model: PHiM, settings: EngineSettings = EngineSettings()) -> StreamEngine:
    """The engine `settings.engine` running `model` (weights, device, refiner and footprint as they are)."""
    s = settings
    if s.engine is Engine.EAGER:
        return StreamingDetector(model, precision=s.precision)
    return GraphStreamingDetector(
        model,
        s.sector_voxels,
        compile=True,
        slots=s.slots,
        precision=s.precision,
        sector_points=s.sector_points,
        bev_crop=s.bev_crop,
    )


def load_model(settings: EngineSettings) -> tuple[PHiM, str]:
    """The settings' model on its device (refiner and footprint applied) -> (model, where its weights come
    from)."""
    device = pick_device(settings.device)
    if settings.checkpoint is None:
        model, source = init_model(settings.config, device) if settings.config else load_default_model(device)
    else:
        expected = get_config(settings.config) if settings.config else None
        model = load_checkpoint(settings.checkpoint, expected, device)
        source = f"checkpoint {settings.checkpoint}"
    if not settings.refiner:
        model.drop_refiner()
    if settings.ego_footprint is not None:  # () is 'off'
        model.set_ego(EgoFootprint(*settings.ego_footprint) if settings.ego_footprint else None)
    return model, source


def build_engine(settings: EngineSettings) -> tuple[StreamEngine, str]:
    """The engine the settings name, its weights loaded -> (engine, where its weights come from)."""
    model, source = load_model(settings)
    engine = engine_for(model, settings)
    log.info(
        "model: config=%s device=%s engine=%s precision=%s scan=%s refiner=%s weights=%s",
        engine.cfg.name,
        model.device,
        settings.engine.value,
        settings.precision.value,
        engine.cfg.backbone.mamba.scan.value,
        "yes" if model.refiner is not None else "no",
        source,
    )
    return engine, source
