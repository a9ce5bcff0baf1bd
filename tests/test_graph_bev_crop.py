"""The dense part on crops (model/graph/bev_crop.py) against the whole map: the halo is the receptive field,
a crop merged into the last maps equals the whole map's maps, and the engine's crops (predicted wedges,
verified, the whole map on a miss) give the eager detector's detections and states."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch
from test_graph_step import narrow_paper, run_both
from test_streaming import make_model

from lidar.synthetic import synthetic_turn
from model.config import PHiMConfig, tiny
from model.detector import PHiM
from model.fold_bn import fold_batchnorms
from model.graph.bev_crop import bev_halo, crop_cells, merge_crop, wedge_bins
from model.graph.engine import GraphStreamingDetector
from model.graph.step import GraphStep
from model.sectors import split_turn
from model.stream import StreamingDetector


def _maps(step: GraphStep, bev: torch.Tensor) -> torch.Tensor:
    return step._head_maps(bev).permute(0, 2, 3, 1)  # (B, H, W, M)


@pytest.mark.parametrize("cfg", [tiny(), narrow_paper()], ids=["tiny", "paper"])
def test_halo_is_the_receptive_radius(cfg: PHiMConfig):
    """With positive weights and inputs no ReLU cuts a path, so the gradient of one output cell's maps (no
    rounding against the outputs' values) is nonzero exactly on its receptive field: the farthest input
    cell, over the four alignments to the backbone's strides, is `bev_halo` cells away (no more, no less)."""
    model = fold_batchnorms(PHiM(cfg).eval())
    with torch.no_grad():
        for p in [*model.bev_backbone.parameters(), *model.head.parameters()]:
            p.abs_()
    model.double()
    # the dense part is convolutions: a map far wider than twice the reach (paper's 468 cells less 256: 212,
    # its centre 128 cells from the whole map's, the same alignment to every stride) shows the same field
    h = cfg.bev.ny if cfg.bev.ny <= 256 else cfg.bev.ny - 256
    bev = torch.rand(1, model.bev_backbone.stages[0][0].conv1.in_channels, h, h, dtype=torch.float64)
    reach = 0
    bev.requires_grad_(True)
    for k in range(4):
        c = h // 2 + k
        out = model.head.forward_per_branch(model.bev_backbone(bev))  # the head's twin: autograd-safe
        cell = sum(getattr(out, f.name)[0, :, c, c].sum() for f in dataclasses.fields(out))
        (grad,) = torch.autograd.grad(cell, bev)
        ys, xs = torch.nonzero(grad.abs().amax(1)[0] > 0, as_tuple=True)
        reach = max(reach, int((ys - c).abs().max()), int((xs - c).abs().max()))
    assert reach == bev_halo(cfg)


@pytest.mark.parametrize("cfg", [tiny(), narrow_paper()], ids=["tiny", "paper"])
def test_a_crop_merged_into_the_last_maps_equals_the_whole_map(cfg: PHiMConfig):
    """Change the BEV input in one wedge's cells: the crop's maps merged into the maps before the change
    equal the whole map's after it, for every wedge, two streams at once (one wedge each)."""
    model = fold_batchnorms(make_model(cfg).eval())
    step = GraphStep(model, cfg.sector_voxels)
    plan = step.crop
    assert plan is not None
    n_wedges, per = cfg.sectors_per_turn, wedge_bins(cfg)
    table = step.cell_table.view(cfg.grid.r_bins, cfg.grid.theta_bins, -1)
    torch.manual_seed(0)
    bev = torch.rand(2, model.bev_backbone.stages[0][0].conv1.in_channels, cfg.bev.ny, cfg.bev.nx)
    with torch.no_grad():
        before = _maps(step, bev)
        for w in range(n_wedges):
            pair = [w, (w + 1) % n_wedges]
            after = bev.clone()
            for b, wedge in enumerate(pair):
                cells = table[:, wedge * per : (wedge + 1) * per].reshape(-1)
                cells = cells[cells >= 0]
                after[b].view(after.shape[1], -1)[:, cells] += torch.rand(after.shape[1], cells.numel())
            bounds = plan.bounds[pair]
            part = step._head_maps(crop_cells(after, bounds[:, :2], plan.size))
            merged = merge_crop(before, part, bounds)
            whole = _maps(step, after)
            assert not torch.equal(whole, before)
            torch.testing.assert_close(merged, whole, rtol=1e-5, atol=1e-5)


def test_crop_sizes():
    """tiny: 108 x 108 of 128 x 128 cells; paper: 320 x 320 of 468 x 468 (47 % of the map)."""
    for cfg, size in ((tiny(), (108, 108)), (narrow_paper(), (320, 320))):
        step = GraphStep(fold_batchnorms(PHiM(cfg).eval()), cfg.sector_voxels)
        assert step.crop is not None and step.crop.size == size


def _crops(graph: GraphStreamingDetector) -> list[bool]:
    """Whether each run of the step ran crops (wraps the step module)."""
    runs: list[bool] = []
    module = graph.step_module
    forward = module.forward

    def spy(*args):
        runs.append(args[-1].bev_crop)
        return forward(*args)

    graph._run = spy
    return runs


def test_a_sector_outside_its_predicted_wedge_runs_the_whole_map():
    """A stream that skips a sector: its next one is not where predicted; the engine sees the step's
    wedge, runs the whole map, and the results stay the eager detector's."""
    model = make_model()
    sectors = split_turn(torch.from_numpy(synthetic_turn(seed=3)), model.cfg.sectors_per_turn)
    graph = GraphStreamingDetector(model)
    runs = _crops(graph)
    order = [0, 1, 2, 3, 0, 2, 3, 0, 1, 2, 3, 0]  # wedge 1 skipped at the sixth step
    run_both(graph, StreamingDetector(model), [[sectors[k]] for k in order])
    assert graph.crop_misses == 1
    assert runs.count(True) >= 5  # the steps after the first keep + 1 sectors, but the miss and its wake


def test_sectors_across_wedges_run_the_whole_map():
    """A turn split at 45 degrees: every sector spans two wedges, so no step runs crops."""
    model = make_model()
    turn = torch.from_numpy(synthetic_turn(seed=3))
    c, s = math.cos(math.pi / 4), math.sin(math.pi / 4)
    rotated = turn.clone()
    rotated[:, 0], rotated[:, 1] = c * turn[:, 0] - s * turn[:, 1], s * turn[:, 0] + c * turn[:, 1]
    sectors = split_turn(rotated, model.cfg.sectors_per_turn)
    rotated_back = [x.clone() for x in sectors]
    for x in rotated_back:
        x[:, 0], x[:, 1] = c * x[:, 0] + s * x[:, 1], -s * x[:, 0] + c * x[:, 1]
    graph = GraphStreamingDetector(model)
    runs = _crops(graph)
    run_both(graph, StreamingDetector(model), [[x] for x in rotated_back * 2])
    assert not any(runs) and graph.crop_misses == 0


@pytest.mark.slow
def test_paper_crops_equal_eager():
    """`paper`'s geometry (halo 43, crops 320 x 320) over five sectors: the fifth runs crops."""
    model = make_model(narrow_paper())
    turn = torch.from_numpy(synthetic_turn(seed=1))[::8]
    turn = torch.cat([turn, turn.new_zeros(turn.shape[0], 1)], 1)
    sectors = split_turn(turn, model.cfg.sectors_per_turn)
    graph = GraphStreamingDetector(model)
    runs = _crops(graph)
    run_both(graph, StreamingDetector(model), [[s] for s in [*sectors, sectors[0]]])
    assert runs[-1] and graph.crop_misses == 0
