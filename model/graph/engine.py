"""`GraphStreamingDetector`: the graph engine (`model.engine`'s interface) over the fixed-shape step.

Stream states live on the device in preallocated slots (`model.graph.slots.StateSlots`); a state is a small
handle (`SlotState`). The host picks the batch's buckets (`model.graph.buckets`), pads the batch on the
device (only the sectors' own rows are copied there), gathers the batch's state rows, runs the step
(compiled with torch.compile where asked), copies one flat tensor back (candidates, stats, site counts),
re-runs the step with larger capacities if any sites did not fit, runs NMS on the candidates and, only
then, writes the new state rows back: a failed step changes no slot. A compiled detector, once sealed after
its warm-up, runs op by op whatever bucket it did not compile; built with `compile=False` it always runs op
by op (the compiled step's plain twin, for tests and tools). Once a batch's streams have each run a turn,
the step's dense part runs on crops around their new sectors (`model.graph.bev_crop`; checked by the wedge
the step reports, else the batch runs again on the whole map). A sector with more voxels than
`sector_voxels` fails alone (`SectorRejected`): the batch's other streams get their results and new
states, its stream keeps its state.
"""

from __future__ import annotations

import logging
from dataclasses import replace

import torch
from torch import Tensor

from model.config import Engine, Precision
from model.detector import PHiM
from model.engine_base import (
    EngineBase,
    EngineInfo,
    SectorOutcome,
    SectorRejected,
    SectorResult,
    StatesExhausted,
)
from model.geometry.boxes import Detections
from model.graph.bev_crop import EMPTY, crop_wedges
from model.graph.buckets import BATCH_BUCKETS, CapacityPlanner, batch_bucket, row_bucket
from model.graph.compile import allow_bucket_graphs, compile_step
from model.graph.slots import (
    GraphStreamState,
    SlotsExhausted,
    SlotState,
    StateSlots,
    StepStates,
    from_stream_state,
)
from model.graph.step import STATS, Capacity, GraphStep
from model.layers.head import Candidates, select_detections
from model.layers.refine import refine_streams
from model.precision import autocast
from model.stream import StreamingDetector, StreamState

log = logging.getLogger(__name__)

__all__ = ["GraphStreamState", "GraphStreamingDetector", "SlotState", "from_stream_state"]
DEFAULT_SLOTS = 32  # stream-state slots of a detector built without a count (the largest batch bucket)
# The warm-up calibrates on a synthetic 64-beam turn (`lidar.synthetic`: four 32,000-point quarters); real
# scans have up to twice its sites per point, so a warmed-up engine plans its capacities for twice the
# peaks it measured there.
CALIBRATION_HEADROOM = 2.0
# Real sectors vary around the calibration turn's size (KITTI quarters 26-33k points): a warmed-up engine
# pads every sector to the bucket of 1.5 x the turn's largest (49,152 points: a Waymo top-LiDAR quarter turn
# fits), so that all of them share the one capacity bucket per batch size that the warm-up compiles.
SECTOR_POINTS_OVER_TURN = 1.5


class GraphStreamingDetector(EngineBase):
    """`step(points, states)` as StreamingDetector's, on the fixed-shape step, for at most `slots` streams
    at once, each buffering `sector_voxels` voxel rows per sector (0: the config's); `compile` runs it
    through torch.compile(fullgraph=True), one specialisation per (batch, capacity) bucket; the step runs
    in `precision` (`model.precision`)."""

    def __init__(
        self,
        model: PHiM,
        sector_voxels: int = 0,
        compile: bool = False,
        slots: int = DEFAULT_SLOTS,
        precision: Precision = Precision.FP32,
        sector_points: int = 0,
        bev_crop: bool = True,
    ):
        # folds the batchnorms, checks the precision; the initial state
        self.reference = StreamingDetector(model, precision=precision)
        self.precision = precision
        self.model = self.reference.model
        self.cfg = model.cfg
        sector_voxels = sector_voxels or model.cfg.sector_voxels  # 0: the config's
        self.step_module = GraphStep(self.model, sector_voxels)
        self.planner = CapacityPlanner(len(self.step_module.keys))
        self.engine = Engine.GRAPH
        self.compiled = compile  # False: the step runs op by op (the compiled step's plain twin)
        # every sector pads to at least this many points' bucket, so that sectors of any size up to it share
        # one capacity bucket per batch bucket (the one a server compiles at warm-up); 0: the bucket of the
        # batch's largest sector, until a warm-up derives it (`planned_sector_points`)
        self.sector_points = sector_points
        # the dense part on crops around each new sector (`model.graph.bev_crop`), if asked and the config
        # has crops; crop_misses: steps that ran crops for a sector outside its predicted wedge, then the
        # whole map
        self.bev_crop = bev_crop and self.step_module.crop is not None
        self.crop_misses = 0
        self.map_shape = (self.cfg.bev.ny, self.cfg.bev.nx, self.step_module.map_channels)
        blank = self._graph_state(self.reference.new_state(), sector_voxels)
        self.slots = StateSlots(blank, slots)
        self._sealed = False  # see seal()
        self._compiled: set[tuple[int, Capacity]] = set()  # buckets the compiled step has run
        self._uncompiled: set[tuple[int, Capacity]] = set()  # buckets run op by op after seal()
        self._run = compile_step(self.step_module, self.device) if compile else self.step_module
        log.info(
            "graph streaming detector: sector_voxels=%d compile=%s state slots: %d x %.2f MiB = %.1f MiB "
            "on %s",
            sector_voxels,
            compile,
            slots,
            self.slots.slot_bytes / 2**20,
            self.slots.total_bytes / 2**20,
            self.slots.device,
        )

    @property
    def device(self) -> torch.device:
        return self.reference.device

    @property
    def sector_voxels(self) -> int:
        return self.step_module.sector_voxels

    def calibrate(self, sectors: list[Tensor], headroom: float = 1.0) -> None:
        """Learn the capacity ratios from sample sectors with the uncompiled step (one slot, given back),
        times `headroom` (for data denser in sites than the samples). A compiled detector's ratios are then
        frozen: it compiles its serving buckets at warm-up and never while it serves; a step that does not
        fit them runs op by op at capacities that hold it (logged). Ratios learned before are forgotten."""
        self.planner = CapacityPlanner(len(self.step_module.keys))
        run, self._run = self._run, self.step_module
        state = taken = self.new_state()
        try:
            for s in sectors:
                _, (state,) = self.step([s], [state])
        finally:
            self._run = run
            self.release(taken)
        self.planner.ratios = [r * headroom for r in self.planner.ratios]
        self.planner.frozen = self.compiled

    def new_state(self) -> SlotState:
        """A fresh state in a free slot (StatesExhausted when none is free); `release` gives it back."""
        try:
            return self.slots.acquire()
        except SlotsExhausted as e:
            raise StatesExhausted(str(e)) from None

    def reset(self, state: SlotState) -> SlotState:
        """A fresh state in `state`'s slot: nothing is written before a step succeeds."""
        self.slots.check([state])
        return state.fresh()

    def release(self, state: SlotState) -> None:
        self.slots.release(state)

    def read_state(self, state: SlotState) -> GraphStreamState:
        """A copy of the state's tensors (tests compare them with the eager detector's)."""
        return self.slots.read(state)

    def from_stream_state(self, state: StreamState) -> SlotState:
        """An eager state, written into a free slot; ValueError (and no slot taken) if a buffered sector has
        more than `sector_voxels` voxels."""
        tensors = self._graph_state(state, self.sector_voxels)  # first: a ValueError takes no slot
        return replace(self.slots.write(self.new_state(), tensors), points=state.points)

    def _graph_state(self, state: StreamState, sector_voxels: int) -> GraphStreamState:
        d = self.model.backbone.cfg.d_model
        return from_stream_state(state, self.cfg.buffer_sectors, sector_voxels, d, self.map_shape)

    def describe(self) -> EngineInfo:
        return self._info(
            sector_voxels=self.sector_voxels,
            sector_points=self.sector_points,
            bev_crop=self.bev_crop,
            state_slots=self.slots.count,
            slot_bytes=self.slots.slot_bytes,
            slot_memory_mb=round(self.slots.total_bytes / 2**20, 1),
            batch_buckets=BATCH_BUCKETS,
        )

    def warm_up(self, sectors: int, max_batch: int = 1) -> float:
        """Before a server is ready: the CPU NMS kernels compiled; then, if `sectors` > 0, the capacities
        learned from a synthetic turn (times CALIBRATION_HEADROOM), the points every sector pads to derived
        from it where not set (`planned_sector_points`), a batch of fresh streams run for every bucket up to
        `max_batch`, on the whole map and on crops (a compiled engine compiles them here), `sectors`
        single-stream steps on one slot (given back), and the engine sealed: no compiling after the warm-up.
        The mean seconds of one step (0.1 if none ran)."""
        turn = self._warm_up_turn(sectors)
        if turn is None:
            return 0.1
        self.calibrate(turn, CALIBRATION_HEADROOM)
        self.sector_points = self.sector_points or self.planned_sector_points(turn)
        crops = [False, True] if self.bev_crop else [False]
        for b in (b for b in BATCH_BUCKETS if b <= batch_bucket(max_batch)):
            for crop in crops:  # the whole map (a stream's first turn), and crops (every sector after it)
                self.run_fresh([turn[i % len(turn)] for i in range(b)], crop)
        taken = self.new_state()
        try:
            return self._timed_steps(turn, sectors, taken, None)
        finally:
            self.release(taken)
            self.seal()  # a bucket not compiled by now runs op by op: no compile while serving

    def planned_sector_points(self, turn: list[Tensor]) -> int:
        """The points every sector pads to, derived from the calibration turn's sectors: the bucket of
        SECTOR_POINTS_OVER_TURN x its largest, scaled up with `sector_voxels` over the config's (an engine
        told to buffer denser sectors than the config's sensor gives pads them in proportion)."""
        denser = max(1.0, self.sector_voxels / self.cfg.sector_voxels)
        return row_bucket(round(max(int(s.shape[0]) for s in turn) * SECTOR_POINTS_OVER_TURN * denser))

    def _step(
        self, points: list[Tensor], states: list[SlotState]
    ) -> tuple[list[SectorOutcome], list[SlotState]]:
        """Per stream: its result and new state, or SectorRejected and its state as it was (the batch
        checked, the ego vehicle's points dropped: `EngineBase.step`)."""
        self.slots.check(states)
        n = len(points)
        wedges = self._crop_wedges(states)
        inputs = self.inputs(points, states, batch_bucket(n), wedges)
        cand, stats, new = self._forward(points, inputs, wedges is not None)
        voxels = [int(v) for v in stats[:n, STATS.index("voxels")]]
        ok = [i for i, v in enumerate(voxels) if v <= self.sector_voxels]
        ran_wedges = [int(w) for w in stats[:n, STATS.index("wedge")]]
        if wedges is not None and any(ran_wedges[i] not in (wedges[i], EMPTY) for i in ok):
            self.crop_misses += 1  # a sector left its predicted wedge: the whole map, from the same inputs
            cand, stats, new = self._forward(points, inputs, False)
        results, kept = self._results(cand[:n], stats[:n], states, points)
        self._write_back(new, [states[i].slot for i in ok], ok)  # last: a failure before it changes nothing
        ran = set(ok)
        outcomes = [r if i in ran else self._rejected(voxels[i]) for i, r in enumerate(results)]
        new_states = [s.stepped(ran_wedges[i], kept[i]) if i in ran else s for i, s in enumerate(states)]
        return outcomes, new_states

    def _crop_wedges(self, states: list[SlotState]) -> list[int] | None:
        """Each stream's wedge if the batch can run its dense part on crops (`bev_crop.crop_wedges`), else
        None. The step reports the true wedge; the engine runs the whole map when one differs
        (`crop_misses`)."""
        if not self.bev_crop:
            return None
        return crop_wedges([s.wedges for s in states], self.cfg.buffer_sectors, self.cfg.sectors_per_turn)

    @property
    def compiled_buckets(self) -> frozenset[tuple[int, Capacity]]:
        """The (batch, capacity) buckets the compiled step has run (empty for an uncompiled detector)."""
        return frozenset(self._compiled)

    @property
    def uncompiled_buckets(self) -> frozenset[tuple[int, Capacity]]:
        """The buckets a sealed compiled detector ran op by op because they were not compiled at warm-up."""
        return frozenset(self._uncompiled)

    @property
    def sealed(self) -> bool:
        return self._sealed

    def seal(self) -> None:
        """No compiling from now on (a server after its warm-up): a step whose (batch, capacity) bucket was
        not compiled yet runs op by op (`fixed`), never stalling the device loop for a compile."""
        self._sealed = True

    def _runner(self, batch: int, cap: Capacity):
        """The compiled step for a bucket compiled before `seal`, or any bucket before it; else op by op."""
        if self._run is self.step_module:
            return self._run
        if (batch, cap) in self._compiled:
            return self._run
        if self._sealed:
            if (batch, cap) not in self._uncompiled:
                self._uncompiled.add((batch, cap))
                log.warning(
                    "graph step: bucket (batch %d, %s) was not compiled at warm-up: op by op", batch, cap
                )
            return self.step_module
        self._compiled.add((batch, cap))
        allow_bucket_graphs()  # a new bucket compiles here, in the calling thread
        return self._run

    @torch.inference_mode()
    def run_fresh(self, points: list[Tensor], crop: bool = False) -> list[SectorOutcome]:
        """The step for len(points) fresh streams padded to their bucket, on the whole map or (`crop`, where
        the detector runs crops) on crops, writing no slot (warm-up compiles a bucket with it)."""
        return self._without_ego(points, lambda kept: (self._run_fresh(kept, crop), []))[0]

    def _run_fresh(self, points: list[Tensor], crop: bool) -> list[SectorOutcome]:
        fresh = [SlotState(self.slots.blank_row, 0, self.slots.keep, 0)] * len(points)  # reads the blank row
        wedges = [0] * len(points) if crop and self.bev_crop else None
        inputs = self.inputs(points, fresh, batch_bucket(len(points)), wedges)
        cand, stats, _ = self._forward(points, inputs, wedges is not None)
        return list(self._results(cand, stats[: len(points)], fresh, points)[0])

    def inputs(
        self,
        points: list[Tensor],
        states: list[SlotState],
        batch: int | None = None,
        wedges: list[int] | None = None,
    ) -> list:
        """The step's inputs: the sectors padded to (B, Np, C), the B streams' state rows (B = `batch`, or
        len(states); the padding streams read the blank row) and the crops of `wedges` (or of wedge 0)."""
        b = len(states) if batch is None else batch
        width = max(int(p.shape[1]) for p in points)
        rows = row_bucket(self._points(points))
        dev = self.device
        # padded on the device: only the sectors' own rows cross from the host (or none, if already there)
        padded = torch.zeros(b, rows, width, device=dev)  # (B, Np, C)
        for i, p in enumerate(points):
            padded[i, : p.shape[0], : p.shape[1]] = p.to(dev, non_blocking=True)
        counts = torch.tensor([int(p.shape[0]) for p in points] + [0] * (b - len(points)))  # (B,)
        st = self.slots.gather(self.slots.read_rows(states, b))
        turn = [i for i, s in enumerate(states) if self.cfg.resets_history(s.sectors_seen)]
        if turn:  # a turn boundary: these streams' global Mamba starts from zero (the buffer stays)
            rows = torch.tensor(turn).to(self.device, non_blocking=True)
            for t in (*st.conv, *st.ssm):
                t.index_fill_(0, rows, 0.0)
        return [
            padded,
            counts.to(dev, non_blocking=True),
            st.conv,
            st.ssm,
            st.feats,
            st.cols,
            st.valid,
            st.maps,
            self._crop_bounds(wedges or [], b),
        ]

    def _crop_bounds(self, wedges: list[int], batch: int) -> Tensor:
        """(batch, 6) int64 on the device: each stream's crop bounds (wedge 0's for padding streams)."""
        plan = self.step_module.crop
        if plan is None:
            return torch.zeros(batch, 6, dtype=torch.int64, device=self.device)
        rows = plan.bounds[torch.tensor(wedges + [0] * (batch - len(wedges)), dtype=torch.int64)]
        return rows.to(self.device, non_blocking=True)

    def _forward(self, points: list[Tensor], inputs: list, crop: bool) -> tuple[Tensor, Tensor, StepStates]:
        """Run the step (the dense part on crops, or the whole map) until its sites fit -> candidates
        (B, K, 10), stats (B, len(STATS)) on the host, new states."""
        total = sum(int(p.shape[0]) for p in points)
        batch = int(inputs[0].shape[0])  # the batch bucket
        layout = self.step_module.host_layout(batch)
        cap = replace(self.planner.capacity(self._points(points), batch), bev_crop=crop)
        run = self._runner(batch, cap)
        while True:
            with autocast(self.precision, self.device):
                host, *new = run(*inputs, cap)
            cand, stats, counts = layout.split(host.cpu())  # the step's one device -> host copy
            if self.planner.fits(cap, counts.tolist(), total):
                return cand, stats, StepStates(*new)
            if self.planner.frozen:  # no new compiled bucket while serving: this step runs op by op
                cap, run = self.planner.holding(cap, counts.tolist()), self.step_module
                log.warning(
                    "graph step: sites did not fit (counts %s); running it op by op with %s",
                    counts.tolist(),
                    cap,
                )
            else:
                cap = replace(self.planner.capacity(self._points(points), batch), bev_crop=crop)
                run = self._runner(batch, cap)
                log.info(
                    "graph step: sites did not fit (counts %s); running it again with %s",
                    counts.tolist(),
                    cap,
                )

    def _points(self, points: list[Tensor]) -> int:
        """The points per stream a batch is planned for: its largest sector's, at least `sector_points`."""
        return max(self.sector_points, *(int(p.shape[0]) for p in points))

    def _write_back(self, new: StepStates, slots: list[int], picks: list[int]) -> None:
        """Stream picks[k]'s new rows into slot slots[k]."""
        if picks:
            self.slots.scatter(slots, new, picks)

    def _rejected(self, voxels: int) -> SectorRejected:
        return SectorRejected(
            "points",
            f"points: a sector of {voxels} voxels; the {self.engine.value} engine buffers at most "
            f"{self.sector_voxels} voxels per sector (sector_voxels): raise it (phim serve --sector-voxels, "
            "PHIM_SECTOR_VOXELS) or send fewer points",
            voxels,
        )

    def _results(
        self, cand: Tensor, stats: Tensor, states: list[SlotState], points: list[Tensor]
    ) -> tuple[list[SectorResult], list[tuple[Tensor, ...]]]:
        """cand (n, K, 10), stats (n, 3) on the host, the sectors' points -> each stream's detections after
        NMS (and the box refiner; `EngineBase` drops the ego vehicle's boxes), and the points each stream
        buffers for the refiner."""
        c = Candidates(cand[..., :7], cand[..., 7], cand[..., 8].long(), cand[..., 9])
        dets: list[Detections] = select_detections(c, self.cfg.head)
        dets, buffers = refine_streams(
            self.model.refiner, dets, [s.points for s in states], points, self.cfg.buffer_sectors
        )
        kept, out_of_range = STATS.index("points_kept"), STATS.index("points_out_of_range")
        results = [
            SectorResult(d, s.buffered_sectors + 1, int(st[kept]), int(st[out_of_range]))
            for d, s, st in zip(dets, states, stats, strict=True)
        ]
        return results, buffers
