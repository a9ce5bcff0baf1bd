"""Device-resident stream-state slots of the fixed-shape step.

`StateSlots` preallocates, on the model's device, every state tensor for `count` streams plus one blank row
(row `count`: the initial state, never written) that fresh streams and a batch's padding streams read. A
stream's state is a `SlotState` handle (its slot and how many sectors it has seen). The step gathers its
inputs with `index_select` over the batch's rows and writes the new rows back with `index_copy_` once the
whole step has succeeded.

A slot also holds the head's maps of its stream's last step (the step's dense part runs on a crop around a
new sector and keeps the rest: `model.graph.bev_crop`), and a handle the wedges of its last sectors.

A handle with `sectors_seen == 0` is a fresh state: the step reads the blank row for it, never its slot. So a
stream's slot is first written (and, on the CPU, its pages first touched) by the stream's first step, a reset
is a new handle on the same slot with nothing written, and a failed step after a reset leaves the slot as it
was. The free list is thread-safe: the server takes and returns slots from its transport threads.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from model.stream import StreamState


class SlotsExhausted(RuntimeError):
    """Every slot is taken."""


@dataclass(frozen=True)
class SlotState:
    """One stream's state: its slot in a `StateSlots` and the sectors it has seen (0: fresh)."""

    slot: int
    sectors_seen: int
    keep: int  # buffer sectors the slot holds
    generation: int  # of the slot when taken: a handle kept after its release is refused
    # the wedges (`model.graph.bev_crop`) of the last keep + 1 sectors its slot's steps ran, oldest first
    wedges: tuple[int, ...] = ()
    # the buffered sectors' raw points (N_i, 3), oldest first, for the box refiner (host memory, not a slot)
    points: tuple[Tensor, ...] = ()

    @property
    def buffered_sectors(self) -> int:
        return min(self.sectors_seen, self.keep)

    def fresh(self) -> SlotState:
        return SlotState(self.slot, 0, self.keep, self.generation)

    def stepped(self, wedge: int, points: tuple[Tensor, ...] = ()) -> SlotState:
        """This state after a step that ran a sector of `wedge`, buffering `points` for the refiner."""
        wedges = (*self.wedges, wedge)[-(self.keep + 1) :]
        return SlotState(self.slot, self.sectors_seen + 1, self.keep, self.generation, wedges, points)


@dataclass(frozen=True)
class GraphStreamState:
    """One stream's state as tensors in the step's fixed shapes (S = `sector_voxels`): what a slot holds."""

    conv: tuple[Tensor, ...]  # per PHiM block (di, d_conv - 1): the global Mamba's conv state
    ssm: tuple[Tensor, ...]  # per PHiM block (di, N)
    feats: Tensor  # (keep, S, C) backbone outputs of the last `keep` sectors, oldest first
    cols: Tensor  # (keep, S, 2) int64 polar column (r, theta) of each row
    valid: Tensor  # (keep, S) bool
    maps: Tensor  # (H, W, M) float32 the head's maps of the last step (zeros before one)
    sectors_seen: int

    @property
    def buffered_sectors(self) -> int:
        return min(self.sectors_seen, self.valid.shape[0])


@dataclass(frozen=True)
class StepStates:
    """The states of one step's B streams, stacked: the step's state inputs or outputs."""

    conv: list[Tensor]  # per block (B, di, d_conv - 1)
    ssm: list[Tensor]  # per block (B, di, N)
    feats: Tensor  # (B, keep, S, C)
    cols: Tensor  # (B, keep, S, 2) int64
    valid: Tensor  # (B, keep, S) bool
    maps: Tensor  # (B, H, W, M) float32

    def tensors(self) -> list[Tensor]:
        return [*self.conv, *self.ssm, self.feats, self.cols, self.valid, self.maps]


class StateSlots:
    """`count` streams' states and one blank row on `blank`'s device, allocated with torch.empty."""

    def __init__(self, blank: GraphStreamState, count: int):
        if count < 1:
            raise ValueError(f"slots: {count}; expected at least 1 stream-state slot")
        self.count = count
        self.keep = int(blank.valid.shape[0])
        self.blank_row = count

        def alloc(t: Tensor) -> Tensor:  # (count + 1, *t.shape); only the blank row written here
            rows = torch.empty(count + 1, *t.shape, dtype=t.dtype, device=t.device)
            rows[count] = t
            return rows

        self.rows = StepStates(
            [alloc(c) for c in blank.conv],
            [alloc(h) for h in blank.ssm],
            alloc(blank.feats),
            alloc(blank.cols),
            alloc(blank.valid),
            alloc(blank.maps),
        )
        self._free = list(range(count - 1, -1, -1))  # pop() takes the lowest slot
        self._generation = [0] * count
        self._lock = threading.Lock()

    @property
    def device(self) -> torch.device:
        return self.rows.feats.device

    @property
    def slot_bytes(self) -> int:
        """Bytes of one slot (every state tensor of one stream)."""
        return sum(t[0].numel() * t.element_size() for t in self.rows.tensors())

    @property
    def total_bytes(self) -> int:
        """Bytes of every slot and the blank row."""
        return (self.count + 1) * self.slot_bytes

    @property
    def free(self) -> int:
        with self._lock:
            return len(self._free)

    def acquire(self) -> SlotState:
        """A fresh state in a free slot; SlotsExhausted when all `count` are taken."""
        with self._lock:
            if not self._free:
                raise SlotsExhausted(
                    f"slots: all {self.count} stream-state slots are taken; release a stream's state first "
                    "(a server sizes them by max_streams)"
                )
            slot = self._free.pop()
            return SlotState(slot, 0, self.keep, self._generation[slot])

    def release(self, state: SlotState) -> None:
        """Give the state's slot back (its rows are left as they are; the next taker starts fresh)."""
        with self._lock:
            self._check(state)
            self._generation[state.slot] += 1
            self._free.append(state.slot)

    def check(self, states: Sequence[SlotState]) -> None:
        """ValueError for a released handle or two handles of one slot in one batch."""
        with self._lock:
            for s in states:
                self._check(s)
        slots = [s.slot for s in states]
        if len(set(slots)) != len(slots):
            dup = sorted({s for s in slots if slots.count(s) > 1})
            raise ValueError(f"states: slots {dup} appear twice in one batch; expected one state per stream")

    def _check(self, s: SlotState) -> None:
        if not isinstance(s, SlotState) or not 0 <= s.slot < self.count:
            raise ValueError(f"state: {s!r}; expected a SlotState of these {self.count} slots")
        if s.generation != self._generation[s.slot]:
            raise ValueError(f"state: slot {s.slot} was released since this state was made; it is stale")

    def read_rows(self, states: Sequence[SlotState], batch: int) -> Tensor:
        """(batch,) int64 on the device: each state's slot, the blank row for fresh states and padding."""
        rows = [s.slot if s.sectors_seen > 0 else self.blank_row for s in states]
        return torch.tensor(rows + [self.blank_row] * (batch - len(rows))).to(self.device, non_blocking=True)

    def gather(self, rows: Tensor) -> StepStates:
        """rows (B,) int64 -> the B streams' states, stacked (copies: the step never sees the slots)."""
        r = self.rows
        return StepStates(
            [c.index_select(0, rows) for c in r.conv],
            [h.index_select(0, rows) for h in r.ssm],
            r.feats.index_select(0, rows),
            r.cols.index_select(0, rows),
            r.valid.index_select(0, rows),
            r.maps.index_select(0, rows),
        )

    def scatter(self, slots: list[int], new: StepStates, picks: list[int]) -> None:
        """Write new's rows picks[k] into slot slots[k]."""
        dev = self.device
        dst_rows = torch.tensor(slots).to(dev, non_blocking=True)
        first = picks == list(range(len(picks)))  # the usual case: no copy of new's rows before the write
        src_rows = None if first else torch.tensor(picks).to(dev, non_blocking=True)
        for dst, src in zip(self.rows.tensors(), new.tensors(), strict=True):
            rows = src[: len(picks)] if src_rows is None else src.index_select(0, src_rows)
            dst.index_copy_(0, dst_rows, rows)

    def read(self, state: SlotState) -> GraphStreamState:
        """A copy of the state's tensors (the blank row's for a fresh state)."""
        self.check([state])
        row = state.slot if state.sectors_seen > 0 else self.blank_row
        r = self.rows
        return GraphStreamState(
            tuple(c[row].clone() for c in r.conv),
            tuple(h[row].clone() for h in r.ssm),
            r.feats[row].clone(),
            r.cols[row].clone(),
            r.valid[row].clone(),
            r.maps[row].clone(),
            state.sectors_seen,
        )

    def write(self, state: SlotState, tensors: GraphStreamState) -> SlotState:
        """Store `tensors` in the state's slot -> the handle that reads them."""
        self.check([state])
        r, row = self.rows, state.slot
        src = [*tensors.conv, *tensors.ssm, tensors.feats, tensors.cols, tensors.valid, tensors.maps]
        for dst, t in zip(r.tensors(), src, strict=True):
            dst[row] = t
        return SlotState(row, tensors.sectors_seen, self.keep, state.generation)


def from_stream_state(
    state: StreamState, keep: int, sector_voxels: int, channels: int, map_shape: tuple[int, int, int]
) -> GraphStreamState:
    """An eager stream state in the graph step's shapes: `keep` buffer slots of `sector_voxels` rows, the
    latest sector last, zero maps (H, W, M) (its next step runs the whole map); ValueError if a buffered
    sector has more rows."""
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
        maps=torch.zeros(map_shape, device=dev),
        sectors_seen=state.sectors_seen,
    )
