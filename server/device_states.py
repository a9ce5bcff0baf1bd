"""The worker's side of stream states: a fixed-shape detector keeps every live stream's state in a device
slot (`model.graph.slots`); the stream table takes one for a new stream and gives it back when the stream
leaves. The eager detector keeps per-stream states: nothing to take or give back."""

from __future__ import annotations

from model.graph.buckets import BATCH_BUCKETS
from model.graph.engine import Detector, GraphStreamingDetector
from model.graph.slots import SlotState
from model.stream import StreamState

State = StreamState | SlotState | None  # None: fresh (the device loop makes the eager initial state)


class DetectorStates:
    """Bound to the detector once the device thread has loaded it (no stream starts before)."""

    def __init__(self, max_streams: int):
        self.max_streams = max_streams
        self.slots: GraphStreamingDetector | None = None  # the detector, when it keeps slots
        self.buckets: tuple[int, ...] | None = None  # its batch buckets (None: batches run unpadded)

    def bind(self, det: Detector) -> None:
        """ValueError if a fixed-shape detector has fewer slots than max_streams."""
        if not isinstance(det, GraphStreamingDetector):
            return
        if det.slots.count < self.max_streams:
            raise ValueError(
                f"max_streams: {self.max_streams}, but the detector has {det.slots.count} stream-state "
                "slots; expected at least max_streams (build it with slots=max_streams)"
            )
        self.slots, self.buckets = det, BATCH_BUCKETS

    def new_state(self) -> SlotState | None:
        """A new stream's state: a device slot (SlotsExhausted when none is free), or None (eager)."""
        return None if self.slots is None else self.slots.init_state()

    def drop_state(self, state: State) -> None:
        """A stream left the table: its device slot goes back."""
        if isinstance(state, SlotState):
            assert self.slots is not None
            self.slots.release(state)

    def prior(self, state: State, reset: bool) -> State:
        """The state a sector runs on (None: a fresh eager state). A reset in a device slot is a fresh state
        in the same slot: nothing is written before the step succeeds."""
        if isinstance(state, SlotState):
            assert self.slots is not None
            return self.slots.reset(state) if reset else state
        return None if reset else state
