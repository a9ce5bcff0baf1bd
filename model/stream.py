"""The eager engine: the model run as it is written, with data-dependent shapes (the reference).

A stream (one vehicle's LiDAR) has an explicit, immutable `StreamState`. `StreamingDetector.step`
(`model.engine_base.EngineBase`) runs one forward over a batch of sectors from different streams, each with
its own state, and returns each sector's detections plus each stream's new state. Input states are never
modified, so a failed batch leaves every stream exactly as it was, and one fresh state serves every new
stream.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import torch
from torch import Tensor

from model.config import Engine, Precision
from model.detector import PHiM, SectorFeatures
from model.engine_base import EngineBase, EngineInfo, SectorResult
from model.fold_bn import fold_batchnorms
from model.layers.head import decode
from model.layers.mamba import MambaState
from model.layers.phim_block import StreamLayout
from model.layers.refine import refine_streams
from model.precision import autocast, check_precision

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class StreamState:
    mamba: tuple[MambaState, ...]  # per PHiM block: the global Mamba's (conv, ssm) state of this stream
    buffer: tuple[SectorFeatures, ...]  # backbone outputs of the last sectors, oldest first
    sectors_seen: int
    # the buffered sectors' raw points (N_i, 3) x, y, z, oldest first, which the box refiner reads (none
    # without a refiner)
    points: tuple[Tensor, ...] = ()

    @property
    def buffered_sectors(self) -> int:
        return len(self.buffer)


class StreamingDetector(EngineBase):
    def __init__(self, model: PHiM, fold_bn: bool = True, precision: Precision = Precision.FP32):
        """Runs `model` in eval mode; with `fold_bn` an inference copy of it with every BatchNorm folded into
        the conv before it (`model.fold_bn`: the same outputs up to float rounding, a little faster). The
        forward runs in `precision` (`model.precision`; ValueError where the device cannot)."""
        check_precision(precision, model.device)
        self.model = fold_batchnorms(model) if fold_bn else model.eval()
        self.cfg = model.cfg
        self.engine = Engine.EAGER
        self.precision = precision
        # every new stream's state: immutable, and a step never writes its input states
        self._fresh = StreamState(mamba=tuple(self.model.init_states(1)), buffer=(), sectors_seen=0)
        log.info(
            "streaming detector: config=%s device=%s scan=%s batchnorms folded=%s precision=%s",
            self.cfg.name,
            model.device,
            self.cfg.backbone.mamba.scan.value,
            fold_bn,
            precision.value,
        )

    @property
    def device(self) -> torch.device:
        return self.model.device

    def new_state(self) -> StreamState:
        """A new stream's initial state (no tensor is made: the fresh state is shared)."""
        return self._fresh

    def release(self, state: StreamState) -> None:
        """Nothing to give back: a state is dropped with its stream."""

    def reset(self, state: StreamState) -> StreamState:
        """A fresh state; the old one is simply dropped."""
        return self._fresh

    def describe(self) -> EngineInfo:
        return self._info()  # no fixed shapes, no slots: batches run unpadded

    def warm_up(self, sectors: int, max_batch: int = 1) -> float:
        """Before a server is ready: the CPU NMS kernels compiled, then `sectors` single-stream steps of a
        synthetic turn (filling the sector buffer) and one batch of two streams (`max_batch`: nothing to plan
        here). The mean seconds of one step (0.1 if none ran)."""
        turn = self._warm_up_turn(sectors)
        if turn is None:
            return 0.1
        return self._timed_steps(turn, sectors, self.new_state(), self.new_state() if sectors >= 2 else None)

    def _step(
        self, points: list[Tensor], states: list[StreamState]
    ) -> tuple[list[SectorResult], list[StreamState]]:
        """The batch checked, the ego vehicle's points dropped (`EngineBase.step`)."""
        dev = self.device
        host, points = points, [p.to(dev, non_blocking=True) for p in points]
        layout = StreamLayout.one_per_item(len(points), dev)
        reset = [self.cfg.resets_history(s.sectors_seen) for s in states]
        zero = self.model.init_states(1) if any(reset) else []  # a turn boundary: the global Mamba restarts
        mamba = [zero if r else s.mamba for s, r in zip(states, reset, strict=True)]
        per_block = [MambaState.cat([m[k] for m in mamba]) for k in range(len(self.model.backbone.blocks))]
        with autocast(self.precision, dev):
            enc = self.model.encode(points, layout, per_block)
            scenes = [[*s.buffer, new] for s, new in zip(states, enc.sectors, strict=True)]
            maps = self.model.predict(scenes)  # float32 maps
        keep = self.cfg.buffer_sectors
        detections = decode(maps, self.cfg.head, self.cfg.bev, self.cfg.every_cell)
        buffered = [s.points for s in states]  # the refiner reads the points where the caller holds them
        detections, kept = refine_streams(self.model.refiner, detections, buffered, host, keep)
        results, new_states = [], []
        for i, (s, scene, det) in enumerate(zip(states, scenes, detections, strict=True)):
            idx = torch.tensor([i], device=dev)
            mamba = tuple(b.index(idx) for b in enc.states)
            buffer = tuple(scene[-keep:]) if keep else ()
            new_states.append(StreamState(mamba, buffer, s.sectors_seen + 1, kept[i]))
            results.append(
                SectorResult(
                    detections=det,
                    context_sectors=len(scene),
                    points_kept=enc.stats.points_kept[i],
                    points_out_of_range=enc.stats.points_out_of_range[i],
                )
            )
        return results, new_states
