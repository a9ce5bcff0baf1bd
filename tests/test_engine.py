"""The engine interface (`model.engine`): both engines build from settings, describe themselves, make,
reset and give back stream states the same way, and drop the ego vehicle's points and boxes in the one frame
they share."""

from __future__ import annotations

import pytest
import torch

from lidar.synthetic import synthetic_turn
from model.checkpoint import DEFAULT_SOURCE
from model.config import Engine
from model.engine import EngineSettings, StatesExhausted, build_engine
from model.graph.buckets import BATCH_BUCKETS
from model.graph.engine import GraphStreamingDetector
from model.sectors import split_turn
from model.stream import StreamingDetector


def test_the_eager_engine_builds_from_settings_and_gives_every_stream_a_real_state() -> None:
    engine, source = build_engine(EngineSettings(device="cpu", ego_footprint=()))
    assert isinstance(engine, StreamingDetector) and source == DEFAULT_SOURCE and engine.cfg.ego is None
    info = engine.describe()
    assert (info.engine, info.device, info.refiner) == (Engine.EAGER, "cpu", engine.cfg.refine is not None)
    assert (info.state_slots, info.sector_voxels, info.batch_buckets) == (None, None, None)
    a, b = engine.new_state(), engine.new_state()
    assert a.buffered_sectors == b.buffered_sectors == 0  # a state, never None
    sectors = split_turn(torch.from_numpy(synthetic_turn(seed=2)), engine.cfg.sectors_per_turn)
    (r,), (stepped,) = engine.step([sectors[0]], [a])
    assert r.context_sectors == 1 and stepped.buffered_sectors == 1 and a.buffered_sectors == 0
    assert engine.reset(stepped).buffered_sectors == 0
    engine.release(stepped)  # nothing to give back


def test_the_graph_engine_builds_its_slots_from_settings_and_runs_out_of_them() -> None:
    settings = EngineSettings(device="cpu", engine=Engine.GRAPH, slots=2, sector_voxels=512)
    engine, _ = build_engine(settings)
    assert isinstance(engine, GraphStreamingDetector) and engine.compiled
    info = engine.describe()
    assert (info.engine, info.state_slots, info.sector_voxels) == (Engine.GRAPH, 2, 512)
    assert info.batch_buckets == BATCH_BUCKETS and info.slot_bytes and info.slot_memory_mb
    a, b = engine.new_state(), engine.new_state()
    with pytest.raises(StatesExhausted, match="all 2 stream-state slots are taken"):
        engine.new_state()
    assert engine.reset(a).slot == a.slot  # the same slot, nothing written
    engine.release(b)
    assert engine.new_state().slot == b.slot


@pytest.mark.parametrize("engine", [StreamingDetector, GraphStreamingDetector], ids=["eager", "fixed-shape"])
def test_both_engines_drop_the_ego_vehicles_points(engine: type[StreamingDetector]) -> None:
    """A synthetic turn with points put on the ego car streams as the turn without them, in either engine
    (the fixed-shape one op by op: the graph engine's plain twin)."""
    det, _ = build_engine(EngineSettings(device="cpu"))
    assert isinstance(det, StreamingDetector)
    run = engine(det.model)
    turn = torch.from_numpy(synthetic_turn(seed=1))
    car = torch.tensor([[0.5, -0.6, -1.0, 0.0], [1.5, 1.0, -0.7, 0.0], [-2.0, 0.3, -0.5, 0.0]]).repeat(20, 1)
    with_car = torch.cat([turn, car + 0.01 * torch.randn_like(car)])
    outs = []
    for pts in (turn, with_car):
        state = run.new_state()
        for sector in split_turn(pts, run.cfg.sectors_per_turn):
            (r,), (state,) = run.step([sector], [state])
        outs.append(r)
    torch.testing.assert_close(outs[0].detections.boxes, outs[1].detections.boxes)
    assert outs[0].points_kept == outs[1].points_kept


def test_a_compiled_graph_engine_may_compile_a_graph_per_bucket_in_the_thread_that_runs_it() -> None:
    """torch.compile's recompile limit (8) is per thread: the thread that meets a new bucket (a server's
    device thread, not the one that built the engine) must allow one graph per bucket (2 x 6 buckets > 8)."""
    import threading

    from model.graph.step import Capacity

    engine, _ = build_engine(EngineSettings(device="cpu", engine=Engine.GRAPH, slots=2))
    assert isinstance(engine, GraphStreamingDetector) and engine.compiled
    seen: list[int] = []

    def device_thread() -> None:
        seen.append(torch._dynamo.config.recompile_limit)
        engine._runner(1, Capacity(points=1, voxels=1, coarse=()))  # a new bucket
        seen.append(torch._dynamo.config.recompile_limit)

    thread = threading.Thread(target=device_thread)
    thread.start()
    thread.join()
    assert seen[0] == 8 and seen[1] >= 2 * len(BATCH_BUCKETS), seen


def test_a_warmed_up_graph_engine_derives_its_padding_and_capacities_from_the_calibration_turn() -> None:
    """No server setting for them: the points every sector pads to are the bucket of 1.5 x the warm-up turn's
    largest sector (four 32,000-point quarters: 49,152), more in proportion to a larger sector_voxels, unless
    the engine was given them; the capacities are twice the calibration's peaks."""
    eager, _ = build_engine(EngineSettings(device="cpu"))
    assert isinstance(eager, StreamingDetector)
    model = eager.model
    turn = split_turn(torch.from_numpy(synthetic_turn(seed=0)), model.cfg.sectors_per_turn)
    derived = GraphStreamingDetector(model, slots=2)
    assert derived.sector_points == 0  # until the warm-up: each batch's largest sector
    derived.warm_up(1)
    reference = GraphStreamingDetector(model, slots=1)
    reference.calibrate(turn)  # the measured peaks, no headroom
    assert derived.sector_points == 49_152 and derived.describe().sector_points == 49_152
    assert derived.planner.ratios == [2.0 * r for r in reference.planner.ratios]
    denser = GraphStreamingDetector(model, 2 * model.cfg.sector_voxels, slots=1)
    assert denser.planned_sector_points(turn) == 98_304
    given = GraphStreamingDetector(model, slots=2, sector_points=40_000)
    given.warm_up(1)
    assert given.sector_points == 40_000
