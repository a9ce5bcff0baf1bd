"""Device-resident stream-state slots (model/graph/slots.py) of the fixed-shape detector: taken and given
back, refused when stale or doubled in a batch, never changed by a failed step, filled from an eager state,
allocated lazily, and a sector too big for its slot failing alone."""

from __future__ import annotations

import pytest
import torch
from conftest import rss_bytes
from test_graph_step import assert_same_state
from test_streaming import assert_same_detections, make_model

from lidar.synthetic import synthetic_turn
from model.detector import PHiM
from model.engine import SectorRejected, SectorResult, StatesExhausted
from model.graph.engine import GraphStreamingDetector
from model.sectors import split_turn
from model.stream import StreamingDetector


@pytest.fixture(scope="module")
def model() -> PHiM:
    return make_model()


@pytest.fixture(scope="module")
def sectors(model: PHiM) -> list[torch.Tensor]:
    return split_turn(torch.from_numpy(synthetic_turn(seed=2)), model.cfg.sectors_per_turn)


def test_slots_are_taken_given_back_and_stale_handles_refused(model: PHiM, sectors):
    det = GraphStreamingDetector(model, slots=3)
    a, b, c = (det.new_state() for _ in range(3))
    assert sorted(s.slot for s in (a, b, c)) == [0, 1, 2] and det.slots.free == 0
    with pytest.raises(StatesExhausted, match="all 3 stream-state slots are taken"):
        det.new_state()
    det.release(b)
    assert det.slots.free == 1
    with pytest.raises(ValueError, match="slot 1 was released since this state was made"):
        det.release(b)
    d = det.new_state()
    assert d.slot == b.slot
    with pytest.raises(ValueError, match="stale"):
        det.step([sectors[0]], [b])
    assert det.reset(d).slot == d.slot and det.slots.free == 0  # a reset keeps the slot


def test_two_states_of_one_slot_in_one_batch_are_refused(model: PHiM, sectors):
    det = GraphStreamingDetector(model, slots=2)
    a = det.new_state()
    with pytest.raises(ValueError, match=r"states: slots \[0\] appear twice in one batch"):
        det.step(sectors[:2], [a, det.reset(a)])


def test_a_failed_step_changes_no_slot(model: PHiM, sectors, monkeypatch: pytest.MonkeyPatch):
    det, eager = GraphStreamingDetector(model, slots=2), StreamingDetector(model)
    _, states = det.step(sectors[:2], [det.new_state(), det.new_state()])
    _, e_states = eager.step(sectors[:2], [eager.new_state(), eager.new_state()])
    before = [t.clone() for t in det.slots.rows.tensors()]  # every row written: both slots and the blank
    real = det._run

    def run_then_fail(*args):
        real(*args)
        raise RuntimeError("injected: the step ran, then failed")

    monkeypatch.setattr(det, "_run", run_then_fail)
    with pytest.raises(RuntimeError, match="injected"):
        det.step(sectors[2:], states)
    for was, now in zip(before, det.slots.rows.tensors(), strict=True):
        assert torch.equal(was, now)
    monkeypatch.undo()
    for s, e in zip(states, e_states, strict=True):
        assert_same_state(det.read_state(s), e)  # the handles still read the states before the failure


def test_an_eager_state_written_into_a_slot_goes_on(model: PHiM, sectors):
    det, eager = GraphStreamingDetector(model, slots=2), StreamingDetector(model)
    e_state = eager.new_state()
    for s in sectors[:2]:
        _, (e_state,) = eager.step([s], [e_state])
    state = det.from_stream_state(e_state)
    assert_same_state(det.read_state(state), e_state)
    (g,), (state,) = det.step([sectors[2]], [state])
    (e,), (e_state,) = eager.step([sectors[2]], [e_state])
    assert isinstance(g, SectorResult) and g.context_sectors == e.context_sectors == 3
    assert_same_detections(g.detections, e.detections)
    assert_same_state(det.read_state(state), e_state)
    small = GraphStreamingDetector(model, sector_voxels=256, slots=1)
    with pytest.raises(ValueError, match="a buffered sector of"):
        small.from_stream_state(e_state)
    assert small.slots.free == 1  # no slot taken


def test_an_oversized_sector_fails_alone_and_its_state_stays(model: PHiM, sectors):
    det, eager = GraphStreamingDetector(model, sector_voxels=256, slots=2), StreamingDetector(model)
    light = [s[:120] for s in sectors]  # at most 120 voxels each
    _, (a, b) = det.step(light[:2], [det.new_state(), det.new_state()])
    _, (ea, eb) = eager.step(light[:2], [eager.new_state(), eager.new_state()])
    kept = _tensors(det, a)
    (big, ok), (a2, b2) = det.step([sectors[2], light[2]], [a, b])
    assert isinstance(big, SectorRejected) and big.field == "points" and big.voxels > 256
    assert big.message == (
        f"points: a sector of {big.voxels} voxels; the graph engine buffers at most 256 voxels per sector "
        "(sector_voxels): raise it (phim serve --sector-voxels, PHIM_SECTOR_VOXELS) or send fewer points"
    )
    assert a2 == a
    for was, now in zip(kept, _tensors(det, a2), strict=True):
        assert torch.equal(was, now)
    (e,), (eb,) = eager.step([light[2]], [eb])
    assert isinstance(ok, SectorResult)
    assert_same_detections(ok.detections, e.detections)
    assert_same_state(det.read_state(b2), eb)
    (g,), (a3,) = det.step([light[2]], [a2])  # the rejected stream's next sector runs on its old state
    (e,), (ea,) = eager.step([light[2]], [ea])
    assert isinstance(g, SectorResult) and g.context_sectors == 2
    assert_same_state(det.read_state(a3), ea)


def _tensors(det: GraphStreamingDetector, state) -> tuple[torch.Tensor, ...]:
    s = det.read_state(state)
    return (*s.conv, *s.ssm, s.feats, s.cols, s.valid, s.maps)


def test_slot_memory_is_counted_and_only_used_slots_are_touched(model: PHiM):
    cfg = model.cfg.backbone
    di, blocks = cfg.mamba.expand * cfg.d_model, len(cfg.down_strides)
    keep = model.cfg.buffer_sectors
    mamba = blocks * di * (cfg.mamba.d_conv - 1 + cfg.mamba.d_state) * 4  # float32 conv and ssm states
    buffer = keep * 4096 * (cfg.d_model * 4 + 2 * 8 + 1)  # feats float32, cols int64 (r, theta), valid
    maps = model.cfg.bev.ny * model.cfg.bev.nx * (3 + 7 + 3) * 4  # the head's maps, float32
    rss = rss_bytes()
    det = GraphStreamingDetector(model, sector_voxels=4096, slots=300)
    assert det.slots.slot_bytes == mamba + buffer + maps
    assert det.slots.total_bytes == 301 * (mamba + buffer + maps)
    assert det.slots.total_bytes > 400 * 2**20
    assert rss_bytes() - rss < 100 * 2**20  # torch.empty: pages of unused slots are never touched
