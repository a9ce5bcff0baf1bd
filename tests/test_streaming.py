"""The streaming contract: sector-by-sector with carried state == whole turn; streams never mix."""

from __future__ import annotations

import copy
import dataclasses

import pytest
import torch
from conftest import kitti_scan

from lidar.synthetic import synthetic_turn
from model.config import MambaHistory, PHiMConfig, RefineConfig, ScanImpl, tiny
from model.detector import PHiM
from model.ego import drop_ego_points
from model.fold_bn import fold_batchnorms
from model.geometry.boxes import Detections
from model.layers.mamba import Mamba
from model.layers.phim_block import StreamLayout
from model.layers.voxelize import PointsError
from model.sectors import split_turn
from model.stream import StreamingDetector


def make_model(cfg: PHiMConfig | None = None, refine: bool = False) -> PHiM:
    """Random weights (of `cfg`, default tiny; with a box refiner where `refine`), but with a heatmap that
    has clear peaks, so that only a few hundred boxes pass the score threshold and the pre/post-NMS top-k
    never cut between near-ties (float noise would pick there)."""
    cfg = cfg or tiny()
    cfg = dataclasses.replace(cfg, head=dataclasses.replace(cfg.head, score_threshold=0.45))
    torch.manual_seed(1)
    model = PHiM(cfg)
    if refine:  # the same detector as without it, whatever the refiner's size draws from the generator
        with torch.random.fork_rng():
            detector = model.state_dict()
            model = PHiM(dataclasses.replace(cfg, refine=RefineConfig()))
            model.load_state_dict(detector, strict=False)
    with torch.no_grad():
        model.head.heatmap[-1].weight.mul_(40.0)
    # Non-trivial BatchNorm statistics so eval mode is not an identity-like network.
    for m in model.modules():
        if isinstance(m, torch.nn.modules.batchnorm._BatchNorm):
            m.running_mean.uniform_(-0.1, 0.1)
            m.running_var.uniform_(0.5, 1.5)
    return model.eval()


def assert_same_detections(a: Detections, b: Detections, atol: float = 1e-4) -> None:
    assert len(a) == len(b), f"{len(a)} vs {len(b)} boxes"
    if len(a) == 0:
        return
    torch.testing.assert_close(a.scores.sort().values, b.scores.sort().values, atol=atol, rtol=0)
    d = torch.cdist(a.boxes[:, :3].double(), b.boxes[:, :3].double())  # (K, K)
    assert d.min(1).values.max() < atol * 10 and d.min(0).values.max() < atol * 10


def stream(det: StreamingDetector, sectors: list[torch.Tensor]):
    state = det.new_state()
    results = []
    for s in sectors:
        (r,), (state,) = det.step([s], [state])
        results.append(r)
    return results, state


@pytest.fixture(scope="module")
def model() -> PHiM:
    return make_model()


@pytest.fixture(scope="module")
def refined() -> PHiM:
    return make_model(refine=True)


@pytest.mark.parametrize("refine", [False, True])
def test_streaming_equals_whole_turn(model: PHiM, refined: PHiM, refine: bool):
    """With a box refiner too: the stream buffers its sectors' points, and the refiner reads them."""
    model = refined if refine else model
    sectors = split_turn(kitti_scan(0), model.cfg.sectors_per_turn)
    det = StreamingDetector(model)
    results, state = stream(det, sectors)
    with torch.inference_mode():
        whole, enc = model.forward_turn(sectors)
    # Global-Mamba outputs feed every sector's backbone output: the buffer holds sectors 1..3.
    for buffered, ref in zip(state.buffer, enc.sectors[1:], strict=True):
        torch.testing.assert_close(buffered.coords, ref.coords, rtol=0, atol=0)
        torch.testing.assert_close(buffered.features, ref.features, rtol=1e-4, atol=1e-5)
    for k, (s_state, ref) in enumerate(zip(state.mamba, enc.states, strict=True)):
        torch.testing.assert_close(s_state.ssm, ref.ssm, rtol=1e-4, atol=1e-5, msg=f"block {k} ssm state")
        torch.testing.assert_close(s_state.conv, ref.conv, rtol=1e-4, atol=1e-5, msg=f"block {k} conv state")
    assert len(whole[0]) > 0
    assert_same_detections(results[-1].detections, whole[0])
    assert [r.context_sectors for r in results] == [1, 2, 3, 4]
    if refine:  # the refiner ran: the boxes moved, and the stream holds its buffered sectors' points
        with torch.inference_mode():
            plain = model.detect([enc.sectors])[0]
        assert not torch.allclose(plain.boxes, whole[0].boxes)
        off_ego = drop_ego_points(sectors[1:], model.cfg.ego)  # the points the model reads
        assert [len(p) for p in state.points] == [len(s) for s in off_ego]


def test_partial_turn_differs_from_full(model: PHiM):
    """Sanity for the test above: predictions with fewer buffered sectors are not the full-turn ones."""
    sectors = split_turn(kitti_scan(0), model.cfg.sectors_per_turn)
    results, _ = stream(StreamingDetector(model), sectors)
    assert len(results[0].detections) != len(results[-1].detections) or not torch.allclose(
        results[0].detections.scores, results[-1].detections.scores
    )


def test_batched_equals_alone_in_any_order(model: PHiM):
    det = StreamingDetector(model)
    turns = [kitti_scan(0), kitti_scan(1), torch.from_numpy(synthetic_turn(seed=3))]
    sectors = [split_turn(t, model.cfg.sectors_per_turn) for t in turns]
    alone = [stream(det, s)[0] for s in sectors]
    for order in ([0, 1, 2], [2, 0, 1]):
        states = [det.new_state() for _ in order]
        for k in range(model.cfg.sectors_per_turn):
            results, states = det.step([sectors[i][k] for i in order], states)
            for r, i in zip(results, order, strict=True):
                assert_same_detections(r.detections, alone[i][k].detections)
                assert r.context_sectors == alone[i][k].context_sectors


def test_empty_sector_and_buffer_limit(model: PHiM):
    det = StreamingDetector(model)
    sectors = split_turn(kitti_scan(0), 4)
    empty = torch.zeros(0, 4)
    results, state = stream(det, [empty, *sectors, empty])
    assert results[0].points_kept == 0
    assert [r.context_sectors for r in results] == [1, 2, 3, 4, 4, 4]
    assert len(state.buffer) == model.cfg.buffer_sectors
    assert state.sectors_seen == 6


def test_bad_points_raise_and_leave_states_alone(model: PHiM):
    det = StreamingDetector(model)
    sectors = split_turn(kitti_scan(0), 4)
    _, state = stream(det, sectors[:2])
    bad = sectors[2].clone()
    bad[5, 0] = float("nan")
    with pytest.raises(PointsError, match="points"):
        det.step([sectors[2], bad], [state, det.new_state()])
    with pytest.raises(PointsError, match="float32"):
        det.step([sectors[2].double()], [state])
    # The state object is immutable and still valid: continuing gives the uninterrupted result.
    (r,), _ = det.step([sectors[2]], [state])
    ref, _ = stream(det, sectors[:3])
    assert_same_detections(r.detections, ref[-1].detections)


def test_reset_starts_fresh(model: PHiM):
    det = StreamingDetector(model)
    sectors = split_turn(kitti_scan(1), 4)
    _, state = stream(det, sectors)
    (after_reset,), _ = det.step([sectors[0]], [det.reset(state)])
    (fresh,), _ = det.step([sectors[0]], [det.new_state()])
    assert after_reset.context_sectors == 1
    assert_same_detections(after_reset.detections, fresh.detections)


def test_set_scan_changes_how_not_what(model: PHiM):
    sectors = split_turn(torch.from_numpy(synthetic_turn(seed=8)[::4]), model.cfg.sectors_per_turn)[:2]
    chunked, _ = stream(StreamingDetector(model), sectors)
    ref_model = copy.deepcopy(model)
    ref_model.set_scan(ScanImpl.REFERENCE)
    layers = [m for m in ref_model.modules() if isinstance(m, Mamba)]
    assert layers and all(m.cfg.scan is ScanImpl.REFERENCE for m in layers)
    assert (
        ref_model.cfg.backbone.mamba.scan is ScanImpl.REFERENCE
        and model.cfg.backbone.mamba.scan is ScanImpl.AUTO
    )
    reference, _ = stream(StreamingDetector(ref_model), sectors)
    assert len(chunked[-1].detections) > 0
    for a, b in zip(chunked, reference, strict=True):
        assert_same_detections(a.detections, b.detections)


def test_blocks_with_the_same_kernel_and_stride_share_their_rule_books():
    """The backbone builds the frustum packings once and the rule books once per (kernel, stride); a block
    handed another block's geometry computes exactly what it computes with its own."""
    cfg = tiny()
    backbone = dataclasses.replace(cfg.backbone, down_strides=(1, 2, 1, 2), down_kernels=(3, 3, 3, 3))
    cfg = dataclasses.replace(cfg, backbone=backbone)
    torch.manual_seed(2)
    model = PHiM(cfg).eval()
    sectors = split_turn(kitti_scan(0), cfg.sectors_per_turn)[:2]
    layout = StreamLayout.one_per_item(2, model.device)
    with torch.inference_mode():
        x, _ = model.voxelizer(sectors)
        states = model.init_states(2)
        blocks = model.backbone.blocks
        local = blocks[0].local_packings(x)
        h0, _, c0 = blocks[0](x, layout, states[0], local)
        h1, _, c1 = blocks[1](h0, layout, states[1], local)
        h2, s2, c2 = blocks[2](h1, layout, states[2], local, c0)  # stride 1 again: block 0's geometry
        own, s_own, c_own = blocks[2](h1, layout, states[2])  # builds its own
        h3, _, c3 = blocks[3](h2, layout, states[3], local, c1)
        whole, _ = model.backbone(x, layout, states)
    assert c2 is c0 and c3 is c1 and c_own is not c0
    assert torch.equal(h2.features, own.features) and torch.equal(s2.ssm, s_own.ssm)
    assert torch.equal(c_own.down.theta_z.in_idx, c0.down.theta_z.in_idx)
    assert torch.equal(c_own.global_seqs.older, c0.global_seqs.older)
    assert not torch.equal(c1.down.rz.out_coords, c0.down.rz.out_coords)  # stride 2: other sites
    assert torch.equal(whole.features, h3.features)


def count_batchnorms(model: torch.nn.Module) -> int:
    return sum(isinstance(m, torch.nn.modules.batchnorm._BatchNorm) for m in model.modules())


def test_folded_batchnorms_give_the_unfolded_detections(model: PHiM):
    """StreamingDetector runs a copy with every BatchNorm folded into its conv; the model as it is is the
    twin."""
    folded = fold_batchnorms(model)
    vfe_norms = len(model.voxelizer.layers)  # the VFE folds its BatchNorm itself, in eval mode
    assert count_batchnorms(folded) == vfe_norms < count_batchnorms(model)
    assert all(not m.training for m in folded.modules())
    sectors = split_turn(kitti_scan(1), model.cfg.sectors_per_turn)
    plain, plain_state = stream(StreamingDetector(model, fold_bn=False), sectors)
    fast, fast_state = stream(StreamingDetector(model), sectors)
    assert len(plain[-1].detections) > 0
    for a, b in zip(plain, fast, strict=True):
        assert_same_detections(a.detections, b.detections)
    for a, b in zip(plain_state.buffer, fast_state.buffer, strict=True):
        torch.testing.assert_close(a.features, b.features, rtol=1e-4, atol=1e-5)
    assert count_batchnorms(model) > vfe_norms  # the model handed in is left as it was


@pytest.mark.parametrize("history", list(MambaHistory))
def test_turn_five_repeats_turn_one_only_when_the_history_resets_at_each_turn(history: MambaHistory):
    """A standing vehicle sends the same turn five times. Under MambaHistory.TURN (the default: training
    encodes each scan from a zero state) turn five is encoded as turn one, to the last feature; carried over
    the stream (STREAM) its features drift (so the test would see a missing reset)."""
    model = make_model()
    model.cfg = dataclasses.replace(model.cfg, history=history)
    det = StreamingDetector(model, fold_bn=False)
    n = model.cfg.sectors_per_turn
    turn = split_turn(torch.from_numpy(synthetic_turn(seed=0)), n)
    (*_, first), one = stream(det, turn)
    (*_, fifth), five = stream(det, turn * 5)
    assert len(first.detections) > 0 and five.sectors_seen == 5 * n
    pairs = zip(one.buffer, five.buffer, strict=True)
    drift = max(float((a.features - b.features).abs().max()) for a, b in pairs)
    if history is MambaHistory.TURN:
        assert drift == 0.0
        assert_same_detections(first.detections, fifth.detections, atol=1e-6)
    else:  # the trained tiny forgets within a sector too: its turn-five scores move by ~4e-4 (docs/model.md)
        assert drift > 0.0
