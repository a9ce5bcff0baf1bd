"""The fixed-shape step (model/graph) against its reference twin, the eager StreamingDetector: the same
detections, states and buffers, alone and batched in any order, at any capacity bucket, over three turns."""

from __future__ import annotations

import copy
import dataclasses

import pytest
import torch
from conftest import kitti_scan
from test_streaming import assert_same_detections, make_model

from lidar.synthetic import synthetic_turn
from model.config import MambaHistory, PHiMConfig, paper, tiny
from model.detector import PHiM
from model.graph.buckets import CapacityPlanner, row_bucket
from model.graph.engine import GraphStreamingDetector, GraphStreamState, SlotState
from model.sectors import split_turn
from model.stream import StreamingDetector, StreamState


@pytest.fixture(scope="module")
def model() -> PHiM:
    return make_model()


def assert_same_state(g: GraphStreamState, e: StreamState, atol: float = 1e-4) -> None:
    """The graph state holds the eager one: Mamba states, and each buffered sector's rows in its slot."""
    for k, m in enumerate(e.mamba):
        torch.testing.assert_close(g.conv[k], m.conv[0], rtol=atol, atol=atol, msg=f"block {k} conv")
        torch.testing.assert_close(g.ssm[k], m.ssm[0], rtol=atol, atol=atol, msg=f"block {k} ssm")
    keep = g.valid.shape[0]
    assert g.sectors_seen == e.sectors_seen
    for slot, sector in zip(range(keep - len(e.buffer), keep), e.buffer, strict=True):
        n = sector.num_voxels
        assert int(g.valid[slot].sum()) == n and bool(g.valid[slot, :n].all())
        torch.testing.assert_close(g.cols[slot, :n], sector.coords[:, :2], rtol=0, atol=0)
        torch.testing.assert_close(g.feats[slot, :n], sector.features, rtol=atol, atol=atol)
    assert not bool(g.valid[: keep - len(e.buffer)].any())


def synthetic_sectors(model: PHiM, seed: int, every: int = 3) -> list[torch.Tensor]:
    """A synthetic turn (128,000 points) in the model's sectors, every `every`-th point: the steps are faster,
    and the two engines agree on any sector (every 3rd keeps boxes: every 2nd or 4th keeps only even beams,
    where the test model finds none)."""
    return split_turn(torch.from_numpy(synthetic_turn(seed=seed))[::every], model.cfg.sectors_per_turn)


def run_both(
    graph: GraphStreamingDetector,
    eager: StreamingDetector,
    batches: list[list[torch.Tensor]],
    atol: float = 1e-4,
):
    """Step both detectors through `batches` (one sector per stream each); compare every step to `atol`."""
    n = len(batches[0])
    g_states, e_states = [graph.new_state() for _ in range(n)], [eager.new_state() for _ in range(n)]
    boxes = 0
    for sectors in batches:
        g_res, g_states = graph.step(sectors, g_states)
        e_res, e_states = eager.step(sectors, e_states)
        for g, e, gs, es in zip(g_res, e_res, g_states, e_states, strict=True):
            assert_same_detections(g.detections, e.detections.to(torch.device("cpu")), atol)
            assert (g.context_sectors, g.points_kept, g.points_out_of_range) == (
                e.context_sectors,
                e.points_kept,
                e.points_out_of_range,
            )
            assert isinstance(gs, SlotState)
            assert_same_state(graph.read_state(gs), es, atol)
            boxes += len(g.detections)
    assert boxes > 0  # the comparison saw boxes


@pytest.mark.samples
@pytest.mark.parametrize("history", list(MambaHistory))
def test_equals_eager_over_three_turns(model: PHiM, history: MambaHistory):
    """Across turn boundaries too: both reset the global Mamba there (TURN) or both carry it (STREAM)."""
    model = copy.copy(model)
    model.cfg = dataclasses.replace(model.cfg, history=history)
    sectors = split_turn(kitti_scan(0), model.cfg.sectors_per_turn)
    graph, eager = GraphStreamingDetector(model), StreamingDetector(model)
    run_both(graph, eager, [[s] for s in sectors * 3])


@pytest.mark.samples
def test_with_a_box_refiner_equals_eager_alone_and_batched():
    """The refiner runs after the step in both engines on the points each stream buffers."""
    model = make_model(refine=True)
    sectors = [split_turn(kitti_scan(0)[::2], model.cfg.sectors_per_turn), synthetic_sectors(model, seed=3)]
    graph, eager = GraphStreamingDetector(model), StreamingDetector(model)
    run_both(graph, eager, [[s[k % 4] for s in sectors] for k in range(6)])  # thinned turns: faster


@pytest.mark.samples
@pytest.mark.parametrize("order", [[0, 1, 2], [2, 0, 1]])
def test_batched_equals_eager_in_any_order(model: PHiM, order: list[int]):
    turns = [kitti_scan(0), kitti_scan(1), torch.from_numpy(synthetic_turn(seed=3))]
    sectors = [split_turn(turns[i][::2], model.cfg.sectors_per_turn) for i in order]  # every 2nd point
    graph, eager = GraphStreamingDetector(model), StreamingDetector(model)
    run_both(graph, eager, [[s[k] for s in sectors] for k in range(model.cfg.sectors_per_turn)])


@pytest.mark.samples
def test_padding_to_a_larger_bucket_changes_nothing(model: PHiM):
    sectors = split_turn(kitti_scan(0)[::2], model.cfg.sectors_per_turn)
    graph, eager = GraphStreamingDetector(model), StreamingDetector(model)
    run_both(graph, eager, [[s] for s in sectors])  # learns the ratios
    tight = graph.planner.capacity(40_000, 1)
    graph.planner.ratios = [r * 2.5 for r in graph.planner.ratios]
    assert graph.planner.capacity(40_000, 1).voxels > tight.voxels
    run_both(graph, eager, [[s] for s in sectors])


def test_sectors_up_to_sector_points_share_one_bucket_and_padding_changes_nothing(model: PHiM):
    sectors = split_turn(torch.from_numpy(synthetic_turn(seed=3)), model.cfg.sectors_per_turn)
    small = [s[: 3000 * (k + 1)] for k, s in enumerate(sectors)]  # 3,000 to 12,000 points
    graph, eager = GraphStreamingDetector(model, sector_points=12_000), StreamingDetector(model)
    fresh = graph.new_state()
    padded = {graph.inputs([s], [fresh])[0].shape[1] for s in small}
    graph.release(fresh)
    assert padded == {row_bucket(12_000)}
    run_both(graph, eager, [[s] for s in small])


def test_sites_that_do_not_fit_run_again_never_truncated(model: PHiM):
    sectors = synthetic_sectors(model, seed=3)
    graph, eager = GraphStreamingDetector(model), StreamingDetector(model)
    graph.planner = CapacityPlanner(graph.planner.num_keys, [0.001] * (1 + 2 * graph.planner.num_keys))
    run_both(graph, eager, [[s] for s in sectors])
    assert all(r > 0.01 for r in graph.planner.ratios)  # learned from the counts the steps reported


def test_frozen_capacities_run_op_by_op_when_sites_do_not_fit(model: PHiM):
    """A compiled detector's capacities are frozen after calibration (no new graph while serving): a step
    that does not fit them runs op by op at capacities that hold it, equal to eager, and learns nothing."""
    sectors = synthetic_sectors(model, seed=3)
    graph, eager = GraphStreamingDetector(model, compile=True), StreamingDetector(model)
    graph.calibrate(sectors[:1], headroom=1.5)
    assert graph.planner.frozen
    graph.planner.ratios = [0.001] * len(graph.planner.ratios)  # far too small for any sector
    calls: list[str] = []
    graph._run = lambda *a: calls.append("compiled") or graph.step_module(*a)  # stands in for the graph
    run_both(graph, eager, [[s] for s in sectors])
    assert graph.planner.ratios == [0.001] * len(graph.planner.ratios)
    assert calls == ["compiled"] * len(sectors)  # each step tried its bucket once, then ran op by op


def test_a_sealed_detector_runs_buckets_it_did_not_compile_op_by_op(model: PHiM):
    """After `seal` (a server's warm-up) a bucket the compiled step has not run goes op by op: nothing
    compiles on the request path. Results stay equal to eager either way."""
    sectors = synthetic_sectors(model, seed=3)
    graph, eager = GraphStreamingDetector(model, compile=True), StreamingDetector(model)
    graph.calibrate(sectors)
    calls: list[int] = []
    graph._run = lambda *a: calls.append(a[0].shape[0]) or graph.step_module(*a)  # stands in for the graph
    graph.run_fresh(sectors[:1])  # compiles (batch 1, its capacities)
    graph.seal()
    run_both(graph, eager, [[s, sectors[-1 - k]] for k, s in enumerate(sectors)])  # batch 2: op by op
    assert calls == [1]
    run_both(graph, eager, [[s] for s in sectors])  # batch 1: compiled
    assert calls == [1] * (1 + len(sectors))


def test_calibration_headroom_scales_the_ratios(model: PHiM):
    sectors = synthetic_sectors(model, seed=3)
    a, b = GraphStreamingDetector(model), GraphStreamingDetector(model)
    a.calibrate(sectors[:2])
    b.calibrate(sectors[:2], headroom=2.0)
    assert b.planner.ratios == [2.0 * r for r in a.planner.ratios]
    assert not a.planner.frozen  # the op-by-op engine keeps learning: it compiles nothing
    assert b.planner.capacity(30_000, 1).voxels > a.planner.capacity(30_000, 1).voxels


def test_buckets():
    sizes = [row_bucket(n) for n in (1, 256, 257, 289, 480, 511, 513, 1000, 4283, 30_000)]
    assert sizes == [256, 256, 288, 320, 480, 512, 576, 1024, 4608, 30_720]


def test_empty_sectors_and_a_stream_without_points(model: PHiM):
    sectors = split_turn(torch.from_numpy(synthetic_turn(seed=2)), model.cfg.sectors_per_turn)
    empty = torch.zeros(0, 4)
    graph, eager = GraphStreamingDetector(model), StreamingDetector(model)
    run_both(graph, eager, [[empty, sectors[0]], [sectors[1], empty], [sectors[2], sectors[3]]])


def test_a_model_reading_intensity_equals_eager():
    """`tiny` reading intensity (`vfe.point_features` 4; `tiny` reads x, y, z) through the CPU kernels."""
    model = make_model(tiny().reading(4))
    sectors = synthetic_sectors(model, seed=3)
    run_both(GraphStreamingDetector(model), StreamingDetector(model), [[s] for s in sectors])


def narrow_paper() -> PHiMConfig:
    """`paper`'s grid, BEV map and layer structure (every block kind, so its halo and crops) with few
    channels and `tiny`'s VFE: fast."""
    cfg = paper()
    bev = dataclasses.replace(cfg.bev, num_filters=(8, 8, 8), num_upsample_filters=(8, 8, 8))
    head = dataclasses.replace(cfg.head, shared_channels=8, head_channels=8)
    backbone = dataclasses.replace(cfg.backbone, d_model=16)
    return dataclasses.replace(cfg, bev=bev, head=head, backbone=backbone, vfe=tiny().vfe)


def paper_model() -> PHiM:
    """The paper config's structure (`narrow_paper`, reading paper's five point columns) with random weights
    whose heatmap has clear peaks (score threshold 0.3). Both engines run the same code at any channel
    width: paper's widths only make the comparison slower."""
    cfg = dataclasses.replace(narrow_paper(), vfe=dataclasses.replace(tiny().vfe, point_features=5))
    cfg = dataclasses.replace(cfg, head=dataclasses.replace(cfg.head, score_threshold=0.3))
    torch.manual_seed(2)
    model = PHiM(cfg).eval()
    with torch.no_grad():
        model.head.heatmap[-1].weight.mul_(40.0)
    return model


def test_paper_config_equals_eager():
    """The paper config's structure (every block kind: strides 1, 2, 4, kernels 3 and 5; its grid and BEV map;
    five point columns) on a thinned synthetic turn."""
    model = paper_model()
    cfg = model.cfg
    turn = torch.from_numpy(synthetic_turn(seed=1))[::8]
    turn = torch.cat([turn, turn.new_zeros(turn.shape[0], 1)], 1)  # elongation column
    sectors = split_turn(turn, cfg.sectors_per_turn)
    run_both(GraphStreamingDetector(model), StreamingDetector(model), [[s] for s in sectors[:2]])


def test_compiled_step_equals_eager_with_no_graph_break(model: PHiM):
    """torch.compile(fullgraph=True) of the whole step (padded inputs -> candidates) on the CPU: a graph
    break raises. Two streams, five sectors each (the fifth runs the dense part on crops), a thinned turn
    (the graph's size does not depend on it)."""
    sectors = split_turn(torch.from_numpy(synthetic_turn(seed=4))[::4], model.cfg.sectors_per_turn)
    graph, eager = GraphStreamingDetector(model, compile=True), StreamingDetector(model)
    graph.calibrate(sectors)
    run_both(graph, eager, [[sectors[k % 4], sectors[(k + 2) % 4]] for k in range(5)])
    assert {cap.bev_crop for _, cap in graph.compiled_buckets} == {False, True}


def test_compiled_detectors_of_configs_differing_in_a_constant_run_their_own_graphs(model: PHiM):
    """The compiled step skips guards on its module tree (its weights are read live), not on the constants
    it was traced with: a second detector whose config differs only in one (the candidates per step)
    compiles its own graph and equals its eager twin (reusing the first's graph, it failed on the shapes)."""
    head = model.cfg.head
    doubled = dataclasses.replace(head, pre_nms_top_k=2 * head.pre_nms_top_k)
    more = dataclasses.replace(model.cfg, head=doubled)
    other = PHiM(more).eval()
    other.load_state_dict(model.state_dict())
    sectors = split_turn(torch.from_numpy(synthetic_turn(seed=4))[::4], model.cfg.sectors_per_turn)
    most = max(len(s) for s in sectors)  # one bucket: one graph per detector
    for m in (model, other):
        graph = GraphStreamingDetector(m, compile=True, bev_crop=False, sector_points=most)
        graph.calibrate(sectors)
        run_both(graph, StreamingDetector(m), [[s] for s in sectors])
        assert len(graph.compiled_buckets) == 1
