"""The box refiner (model/layers/refine.py): the points it reads, the residual it predicts, its training
(`phim train-refiner`), the shipped model's refiner in streaming and on simulated scans, and a server
with and without it (`--no-refiner`)."""

from __future__ import annotations

import dataclasses
import json
import math
import re
import subprocess
import sys
from pathlib import Path

import httpx
import numpy as np
import pytest
import torch
from conftest import REPO, kitti_scan
from server_helpers import assert_same_boxes, run_direct, sector_msg, serve
from test_streaming import assert_same_detections

from contract import DetectionsReply, decode_response, encode_sector
from lidar.sources import scan_source
from model.checkpoint import (
    init_weights,
    load_checkpoint,
    load_default_model,
    read_checkpoint,
    resolve_checkpoint,
)
from model.config import PHiMConfig, RefineConfig, tiny
from model.detector import PHiM
from model.eval.metrics import iou_matrix
from model.eval.runner import scan_sectors
from model.geometry.boxes import Detections
from model.geometry.nms import class_nms
from model.layers import refine as refine_module
from model.layers.head import decode
from model.layers.phim_block import StreamLayout
from model.layers.refine import (
    apply_output,
    apply_residual,
    box_points,
    box_points_reference,
    box_points_torch,
    grown_boxes,
    refine,
    refine_many,
    refine_streams,
    residual_target,
)
from model.sectors import split_turn
from model.stream import StreamingDetector
from model.train.refine import Proposals, fit, scan_proposals
from model.train.refine_cli import scan_runs

CFG = RefineConfig(points=16)


def random_scene(seed: int, n: int = 5000, b: int = 40) -> tuple[torch.Tensor, torch.Tensor]:
    """Points (n, 4) clustered around b boxes (some far from every point, some with more than P points)."""
    g = torch.Generator().manual_seed(seed)
    centres = (torch.rand(b, 3, generator=g) - 0.5) * torch.tensor([80.0, 80.0, 2.0])
    dims = torch.rand(b, 3, generator=g) * torch.tensor([5.0, 2.0, 1.5]) + 0.3
    yaw = (torch.rand(b, 1, generator=g) - 0.5) * 4 * math.pi
    boxes = torch.cat((centres, dims, yaw), 1)
    near = centres[torch.randint(0, b // 2, (n,), generator=g), :] + torch.randn(n, 3, generator=g) * 2.0
    points = torch.cat((near, torch.rand(n, 1, generator=g)), 1)
    return points, boxes


@pytest.mark.parametrize(("seed", "n"), [(0, 5000), (1, 5000), (2, 5000), (3, 60_000)])
@pytest.mark.parametrize("lookup", [box_points, box_points_torch])
def test_the_grid_index_reads_the_points_every_point_against_every_box_reads(lookup, seed: int, n: int):
    """The numba kernel (`box_points` on the CPU) and the tensor ops (on CUDA) against the plain twin; the
    large scene has boxes of hundreds of points (the kernel's radix sort, several passes)."""
    points, boxes = random_scene(seed, n)
    labels = torch.arange(boxes.shape[0]) % 3
    boxes = grown_boxes(boxes, labels, CFG)
    local, counts = lookup(points, boxes, CFG.points)
    ref_local, ref_counts = box_points_reference(points, boxes, CFG.points)
    assert torch.equal(counts, ref_counts)
    torch.testing.assert_close(local, ref_local, rtol=0, atol=1e-5)
    assert int((counts == 0).sum()) > 0 and int((counts > CFG.points).sum()) > 0  # both cases were seen
    assert n < 10_000 or int(counts.max()) > 500
    assert bool((local[counts == 0] == 0).all())
    assert bool((local.abs() <= boxes[:, None, 3:6] / 2 + 1e-5).all())  # in the box, in its frame


@pytest.mark.parametrize("lookup", [box_points, box_points_torch])
def test_no_boxes_or_no_points(lookup):
    points, boxes = random_scene(0)
    for p, b in ((points, boxes[:0]), (points[:0], boxes)):
        local, counts = lookup(p, b, CFG.points)
        assert local.shape == (b.shape[0], CFG.points, 3) and counts.shape == (b.shape[0],)
        assert int(counts.sum()) == 0


# Issue 51's killer sector, kernel level, in a child process (a crash fails the test instead of killing
# pytest): a lone cluster of 300 points and one more far away on x (or y), a finite float32 whose 1 m cell
# index overflowed int64: the compiled bounds check was folded away and the kernel wrote outside its
# buffers. Each case is named on stdout before it runs; its counts from each lookup follow as JSON.
_FAR_POINT = """
import json, sys
import numpy as np, torch
from model.config import RefineConfig
from model.layers.refine import box_points, box_points_reference, box_points_torch
torch.set_num_threads(1)
g = np.random.default_rng(0)
cluster = np.stack([g.uniform(20, 40, 300), g.uniform(-10, -2, 300), g.uniform(-1.5, 1, 300)], 1)
two = torch.tensor([[30.0, -6, 0, 5, 3, 2, 0.3], [25.0, -3, -0.5, 1.8, 1.8, 2.2, -1.0]])  # grown
cfg = RefineConfig(points=16)
for far in (-1e30, 1e30, 1e19, -1e19, -3.4e38, 3.4028235e38):
    for axis in (0, 1):
        for boxes in (two[:1], two):
            print("case", far, axis, len(boxes), flush=True)
            point = [30.0, -5.0, 0.0]
            point[axis] = far
            points = torch.from_numpy(np.concatenate([cluster, [point]]).astype(np.float32))
            out = {}
            for name, lookup in (("kernel", box_points), ("torch", box_points_torch)):
                for _ in range(20):  # the corruption did not always crash the first call
                    local, counts = lookup(points, boxes, cfg.points)
                out[name] = (counts.tolist(), local.tolist())
            local, counts = box_points_reference(points, boxes, cfg.points)
            out["plain"] = (counts.tolist(), local.tolist())
            print(json.dumps(out), flush=True)
"""


def test_a_point_whose_cell_index_overflows_int64_is_looked_up_without_a_crash():
    """The kernel (and its tensor twin) bucket a point by its cell only after checking it against the grid's
    bounds as a float: the far point is in no box, the cluster's points are read as the plain twin reads
    them."""
    run = subprocess.run(
        [sys.executable, "-c", _FAR_POINT], cwd=REPO, capture_output=True, text=True, timeout=600
    )
    lines = run.stdout.splitlines()
    assert run.returncode == 0, f"exit code {run.returncode} in {lines[-1:]}: {run.stderr[-2000:]}"
    results = [json.loads(line) for line in lines if not line.startswith("case")]
    assert len(results) == 24
    for got in results:
        counts, local = got["plain"]
        assert got["kernel"][0] == got["torch"][0] == counts and min(counts) > 0, got  # cluster points read
        for name in ("kernel", "torch"):
            np.testing.assert_allclose(got[name][1], local, rtol=0, atol=1e-5)


def test_the_residual_target_turns_a_box_into_its_truth():
    _, boxes = random_scene(3)
    g = torch.Generator().manual_seed(4)
    truth = boxes + torch.randn(boxes.shape, generator=g) * torch.tensor([0.5, 0.5, 0.2, 0.3, 0.2, 0.1, 0.4])
    truth[:, 3:6] = truth[:, 3:6].abs() + 0.1
    got = apply_residual(boxes, residual_target(boxes, truth))
    torch.testing.assert_close(got[:, :6], truth[:, :6], atol=1e-4, rtol=1e-4)
    dyaw = torch.remainder(got[:, 6] - truth[:, 6] + math.pi / 2, math.pi) - math.pi / 2  # on the axis
    assert float(dyaw.abs().max()) < 1e-4


def test_the_refiner_learns_from_the_points_which_boxes_point_the_wrong_way():
    """`RefineConfig.flip`: boxes whose points lie in their front half point the wrong way (their true box
    is turned by pi); `fit` teaches the flip logit that, and `apply_output` turns those boxes."""
    g = torch.Generator().manual_seed(5)
    n, p = 512, 16
    boxes = torch.cat(
        (torch.randn(n, 3, generator=g) * 10, torch.full((n, 3), 2.0), torch.rand(n, 1, generator=g) * 6), 1
    )
    backwards = torch.rand(n, generator=g) < 0.5
    local = torch.rand(n, p, 3, generator=g) - 0.5
    local[:, :, 0] = torch.where(backwards[:, None], local[:, :, 0].abs(), -local[:, :, 0].abs())
    truth = boxes.clone()
    truth[:, 6] += backwards.float() * math.pi
    data = Proposals(
        local,
        torch.full((n,), p),
        boxes,
        torch.full((n,), 0.5),
        torch.zeros(n, dtype=torch.long),
        truth,
        torch.ones(n),
    )
    cfg = RefineConfig(points=p, flip=True)
    torch.manual_seed(0)
    refiner = PHiM(dataclasses.replace(tiny(), refine=cfg)).refiner
    fit(refiner, data, epochs=60, lr=5e-3, batch=128)
    with torch.no_grad():
        out = refiner(data.local, data.counts, data.boxes, data.scores, data.labels)  # (n, 9)
    turned = apply_output(boxes, out, cfg)
    assert float(((out[:, 8] > 0) == backwards).float().mean()) > 0.95
    ahead = torch.cos(turned[:, 6] - truth[:, 6]) > 0  # the refined box points the true box's way
    assert float(ahead.float().mean()) > 0.95


def test_a_refiner_saved_before_context_flip_and_stages_loads_as_it_was_trained():
    d = dataclasses.replace(tiny(), refine=RefineConfig()).to_dict()
    del d["refine"]["context"], d["refine"]["flip"], d["refine"]["stages"]
    cfg = PHiMConfig.from_dict(d).refine
    assert cfg is not None and not cfg.context and not cfg.flip and cfg.stages == 1
    refiner = PHiM(dataclasses.replace(tiny(), refine=cfg)).refiner
    assert refiner.out[-1].out_features == 8 and not hasattr(refiner, "context_point")
    assert refiner.chain() == [refiner]


def test_each_class_reads_the_points_around_its_boxes_grown_by_its_own_margin():
    """`RefineConfig.grow` per class: a pedestrian (label 1) reads 0.2 m around itself, a vehicle 0.5 m; a
    checkpoint saved when one margin held for every class loads with it for each."""
    boxes = torch.tensor([[10.0, 0, 0, 4, 2, 1.5, 0.3], [5.0, 5, 0, 0.8, 0.7, 1.7, 1.0]])
    grown = grown_boxes(boxes, torch.tensor([0, 1]), RefineConfig())
    assert torch.equal(grown[:, [0, 1, 2, 6]], boxes[:, [0, 1, 2, 6]])
    torch.testing.assert_close(grown[:, 3:6], torch.tensor([[5.0, 3, 2], [1.2, 1.1, 2.2]]))
    # a pedestrian's neighbour 0.85 m away: inside a vehicle's margin, outside a pedestrian's
    neighbour = torch.tensor([[5.0 + 0.85 * math.cos(1.0), 5 + 0.85 * math.sin(1.0), 0]])
    for label, seen in ((1, 0), (0, 1)):
        ped = grown_boxes(boxes[1:], torch.tensor([label]), RefineConfig())
        assert int(box_points(neighbour, ped, 8)[1][0]) == seen
    d = dataclasses.replace(tiny(), refine=RefineConfig()).to_dict()
    d["refine"]["grow"] = [1.0, 1.0, 0.5]
    assert PHiMConfig.from_dict(d).refine.grow == ((1.0, 1.0, 0.5),) * 3
    with pytest.raises(ValueError, match="one value per class"):
        dataclasses.replace(tiny(), refine=RefineConfig(grow=((1.0, 1.0, 0.5),)))


def test_a_refiner_saved_before_every_cell_reads_the_local_maxima_and_the_lists_need_one_per_class():
    d = dataclasses.replace(tiny(), refine=RefineConfig()).to_dict()
    del d["refine"]["every_cell"], d["refine"]["nms_iou"]
    cfg = PHiMConfig.from_dict(d)
    assert cfg.every_cell == (False,) * 3 and cfg.refine.nms_iou == RefineConfig.nms_iou
    assert tiny().every_cell == () and any(dataclasses.replace(tiny(), refine=RefineConfig()).every_cell)
    for bad in ({"every_cell": (True,)}, {"nms_iou": (0.5, 0.5)}):
        with pytest.raises(ValueError, match="one value per class"):
            dataclasses.replace(tiny(), refine=RefineConfig(**bad))


def test_nms_runs_over_the_last_stages_boxes_only(shipped):
    """Two boxes on one pedestrian (every cell of a person is a candidate: `every_cell`) refine to one
    place; NMS with `nms_iou` after the last stage keeps one of them, sorted by score as before; after an
    earlier stage (fitting the next) both stay."""
    ped = torch.tensor([[10.0, 3.0, -0.9, 0.7, 0.6, 1.7, 0.4]])
    g = torch.Generator().manual_seed(0)
    points = ped[0, :3] + (torch.rand(200, 3, generator=g) - 0.5) * torch.tensor([0.5, 0.4, 1.6])
    det = Detections(ped.repeat(2, 1), torch.tensor([0.6, 0.5]), torch.tensor([1, 1]))
    last = refine_many(shipped.refiner, [det], [points])[0]
    first = refine_many(shipped.refiner, [det], [points], stages=1)[0]
    assert len(first) == 2 and bool(first.scores[0] > first.scores[1])  # the box scored higher stays so
    unsorted = refine_many(shipped.refiner, [Detections(det.boxes, det.scores.flip(0), det.labels)], [points])
    assert len(last) == 1 and len(unsorted[0]) == 1  # the same box kept (to float rounding: rows reordered)
    torch.testing.assert_close(last.boxes, unsorted[0].boxes, rtol=1e-5, atol=1e-5)


def test_a_cascade_chains_its_stages_and_the_first_is_drawn_as_a_single_stage():
    """`RefineConfig.stages`: the stages in turn; stage 1's initial weights are those of a one-stage
    refiner (a later stage draws after it)."""
    torch.manual_seed(0)
    one = PHiM(dataclasses.replace(tiny(), refine=RefineConfig(stages=1))).refiner
    torch.manual_seed(0)
    three = PHiM(dataclasses.replace(tiny(), refine=RefineConfig(stages=3))).refiner
    chain = three.chain()
    assert len(chain) == 3 and chain[-1].next_stage is None and one.next_stage is None
    own = {k: v for k, v in three.state_dict().items() if not k.startswith("next_stage.")}
    assert own.keys() == one.state_dict().keys() and all(
        torch.equal(own[k], v) for k, v in one.state_dict().items()
    )
    assert not torch.equal(chain[1].out[-1].weight, chain[0].out[-1].weight)
    with pytest.raises(ValueError, match="stages: 0"):
        RefineConfig(stages=0)


def test_a_later_stage_learns_from_the_boxes_the_stages_before_it_refined(shipped):
    """`scan_proposals(refined=k)`: the detector's boxes (its heatmaps' local maxima, and every cell of the
    classes its `every_cell` argument names, whatever the model's config says) as the first k stages return
    them reading each box once (re-sorted by their refined score, no NMS), with those boxes' points; k = 0:
    the detector's own."""
    scan = scan_source("sim", 5, shuffle=False)(0)
    sectors = scan_sectors(scan, shipped.cfg.vfe.point_features, shipped.cfg.sectors_per_turn)
    assert any(shipped.cfg.every_cell)
    with torch.inference_mode():
        _, enc = shipped.forward_turn(sectors)
        det = decode(shipped.predict([enc.sectors]), shipped.cfg.head, shipped.cfg.bev)[0]
        once = refine_many(shipped.refiner, [det], [torch.cat(sectors)], stages=1, mirror=False)[0]
        cells = decode(shipped.predict([enc.sectors]), shipped.cfg.head, shipped.cfg.bev, (False, True, True))
    raw = scan_proposals(shipped, shipped.refiner.cfg, scan)
    later = scan_proposals(shipped, shipped.refiner.cfg, scan, refined=1)
    assert len(det) >= 10 and torch.equal(raw.boxes, det.boxes) and torch.equal(later.boxes, once.boxes)
    assert torch.equal(later.scores, once.scores) and not torch.equal(later.local, raw.local)
    every = scan_proposals(shipped, shipped.refiner.cfg, scan, every_cell=(False, True, True))
    assert len(every) > len(raw) and torch.equal(every.boxes, cells[0].boxes)
    assert int((every.labels == 1).sum()) > int((raw.labels == 1).sum())  # a pedestrian's cells, not its peak


def test_the_stream_buffers_its_last_sectors_points_and_a_model_without_refiner_none():
    refiner = PHiM(dataclasses.replace(tiny(), refine=RefineConfig())).refiner
    sectors = [torch.randn(n, 4) for n in (10, 20, 30, 40, 50)]
    det = Detections.empty()
    buffered: tuple[torch.Tensor, ...] = ()
    for s in sectors:
        out, (buffered,) = refine_streams(refiner, [det], [buffered], [s], keep=3)
        assert len(out) == 1 and len(out[0]) == 0
    assert [len(p) for p in buffered] == [30, 40, 50] and buffered[0].shape[1] == 3
    for p, s in zip(buffered, sectors[2:], strict=True):  # x, y, z of their own, not views of the caller's
        assert p.is_contiguous() and p.untyped_storage().data_ptr() != s.untyped_storage().data_ptr()
        assert torch.equal(p, s[:, :3])
    assert refine_streams(None, [det], [buffered], [sectors[0]], keep=3) == ([det], [()])


def _refine_plain(refiner, det: Detections, points: torch.Tensor) -> Detections:
    """The refiner's stages in turn on one prediction, its boxes looked up every point against every box,
    each box of a class `mirror` names read mirrored too, then the class NMS: the twin of `refine_many`'s
    per-stream lookups and batched forward per stage."""
    boxes, scores, a = det.boxes, det.scores, refiner.cfg.iou_weight
    for stage in refiner.chain():
        grown = grown_boxes(boxes, det.labels, stage.cfg)
        local, counts = box_points_reference(points, grown, stage.cfg.points)
        out = stage(local, counts, boxes, scores, det.labels)
        if any(stage.cfg.mirror):  # every box read mirrored too, the classes `mirror` names averaged with it
            seen = stage(local * torch.tensor([1.0, -1.0, 1.0]), counts, boxes, scores, det.labels)
            seen[:, [1, 6]] *= -1
            out = torch.where(torch.tensor(stage.cfg.mirror)[det.labels][:, None], (out + seen) / 2, out)
        scores = det.scores.pow(1 - a) * torch.sigmoid(out[:, 7]).pow(a)  # the detector's and this IoU
        boxes = apply_residual(boxes, out)
        if stage.cfg.flip:
            boxes[:, 6] = torch.where(out[:, 8] > 0, boxes[:, 6] + math.pi, boxes[:, 6])
    keep = class_nms(boxes, scores, det.labels, refiner.cfg.nms_iou, len(boxes), len(boxes))  # by score
    return Detections(boxes[keep], scores[keep], det.labels[keep])


@pytest.fixture(params=[1, 2])
def torch_threads(request):
    before = torch.get_num_threads()
    torch.set_num_threads(request.param)
    yield request.param
    torch.set_num_threads(before)


@torch.no_grad()
@pytest.mark.parametrize(
    "cfg",
    [
        RefineConfig(points=16, context=False, flip=False, stages=1),
        RefineConfig(points=16, context=True, flip=True, stages=2),
    ],
)
def test_a_batchs_streams_refined_in_one_forward_equal_each_refined_alone(torch_threads: int, cfg):
    """`refine_many` (the engines' path: lookups per stream, on torch's threads at once where it has
    several, one forward over the batch's boxes, in chunks on the CPU; per stage of a cascade) against the
    plain twin per stream; streams of 40, 0 and 300 boxes (two chunks), a few of which the last NMS drops."""
    torch.manual_seed(0)
    refiner = PHiM(dataclasses.replace(tiny(), refine=cfg)).refiner.eval()
    g = torch.Generator().manual_seed(9)
    dets, points = [], []
    for seed, b in ((4, 40), (5, 0), (6, 300)):
        p, boxes = random_scene(seed, b=max(b, 2))
        boxes = boxes[:b]
        scores, labels = torch.rand(b, generator=g), torch.randint(0, 3, (b,), generator=g)
        dets.append(Detections(boxes, scores, labels))
        points.append(p)
    got = refine_many(refiner, dets, points)
    wants = [_refine_plain(refiner, d, p) for d, p in zip(dets, points, strict=True)]
    assert [len(d) for d in got] == [len(d) for d in wants] and 320 < sum(map(len, got)) < 340
    for out, want in zip(got, wants, strict=True):
        torch.testing.assert_close(out.boxes, want.boxes, rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(out.scores, want.scores, rtol=1e-5, atol=1e-6)
        assert torch.equal(out.labels, want.labels)
    assert float((got[2].boxes.sum(0) - dets[2].boxes.sum(0)).abs().max()) > 1e-2  # the boxes did move
    assert torch_threads == 1 or refine_module._pool.cache_info().currsize > 0  # the lookups ran at once


def test_train_refiner_writes_the_frozen_detector_with_a_refiner_and_train_starts_without_it(tmp_path: Path):
    """A one-stage refiner, then (--keep) a second stage fitted on its boxes, the first kept as it was; the
    second fitted on every cell of pedestrians and cyclists (more boxes than the first's local maxima)."""
    one, out = tmp_path / "one.pt", tmp_path / "refined.pt"
    cmd = [sys.executable, "-m", "phim", "train-refiner", "--seed", "5", "--points", "8", "--scans", "2"]
    cmd += ["--epochs", "1", "--threads", "1"]
    first_run = [*cmd, "--out", str(one), "--stages", "1"]
    run = subprocess.run(first_run, check=True, capture_output=True, text=True)
    cells = ["--fit-every-cell", "pedestrian", "--fit-every-cell", "CYCLIST"]
    args = ["--checkpoint", str(one), "--keep", "--out", str(out), *cells]
    kept_run = subprocess.run([*cmd, *args], check=True, capture_output=True, text=True)
    peaks = int(re.search(r"stage 1: (\d+) boxes", run.stdout).group(1))
    every = int(re.search(r"stage 2: (\d+) boxes", kept_run.stdout).group(1))
    assert 10 < peaks < every, (peaks, every)  # a stage's boxes are the detector's: as many, without cells
    meta = read_checkpoint(out)["meta"]["refiner"]
    assert meta["fit_every_cell"] == ["PEDESTRIAN", "CYCLIST"] and meta["stages_kept"] == 1
    first = load_checkpoint(one, expected=tiny())  # `tiny` with a refiner is still `tiny`
    refined = load_checkpoint(out, expected=tiny())
    assert first.cfg.refine == RefineConfig(points=8, stages=1) and len(first.refiner.chain()) == 1
    assert refined.cfg.refine == RefineConfig(points=8) and refined.cfg.refine.flip
    assert len(refined.refiner.chain()) == 2
    kept = {k: v for k, v in refined.refiner.state_dict().items() if not k.startswith("next_stage.")}
    assert all(torch.equal(kept[k], v) for k, v in first.refiner.state_dict().items())
    torch.manual_seed(0)  # as the command draws the refiner's initial weights
    fresh = PHiM(refined.cfg).refiner
    for stage, drawn in zip(refined.refiner.chain(), fresh.chain(), strict=True):  # each stage was fitted
        assert not torch.equal(stage.out[-1].weight, drawn.out[-1].weight)
    again = subprocess.run(
        [*cmd, "--checkpoint", str(out), "--keep", "--out", str(tmp_path / "x.pt")],
        capture_output=True,
        text=True,
    )
    assert again.returncode == 2 and "--stages 2 adds none" in again.stderr, again.stderr
    default, _ = resolve_checkpoint("default")
    plain = {k: v for k, v in refined.state_dict().items() if not k.startswith("refiner.")}
    base = {k: v for k, v in default.state_dict().items() if not k.startswith("refiner.")}
    assert plain.keys() == base.keys() and all(torch.equal(plain[k], base[k]) for k in plain)  # frozen
    state = init_weights(out, dataclasses.replace(refined.cfg, refine=None))
    assert not any(k.startswith("refiner.") for k in state)


def test_more_workers_split_each_streams_scans_into_runs_and_fit_the_same_refiner(tmp_path: Path):
    """--workers 2 on one stream reads its scans in two runs: the same boxes in the same order, so the
    same refiner, bit for bit."""
    assert scan_runs(5, 2) == [(0, 2), (2, 3)] and scan_runs(2, 4) == [(0, 1), (1, 1)]
    assert scan_runs(3, 0) == [(0, 3)]  # 0 workers: one run a stream
    cmd = [sys.executable, "-m", "phim", "train-refiner", "--seed", "5", "--points", "8", "--scans", "3"]
    cmd += ["--epochs", "1", "--threads", "1", "--stages", "1"]
    runs = {
        w: subprocess.run(
            [*cmd, "--workers", w, "--out", str(tmp_path / f"{w}.pt")],
            check=True,
            capture_output=True,
            text=True,
        )
        for w in ("1", "2")
    }
    boxes = {w: re.search(r"stage 1: (\d+) boxes", r.stdout).group(1) for w, r in runs.items()}
    assert boxes["1"] == boxes["2"] and int(boxes["1"]) > 10, boxes
    one, two = (read_checkpoint(tmp_path / f"{w}.pt")["state_dict"] for w in ("1", "2"))
    assert any(k.startswith("refiner.") for k in one)
    assert one.keys() == two.keys() and all(torch.equal(one[k], two[k]) for k in one)


@pytest.fixture(scope="module")
def shipped():
    model, _ = resolve_checkpoint("default")
    if model.refiner is None:
        pytest.fail("the shipped default has no box refiner")
    return model.eval()


@pytest.mark.samples
def test_the_shipped_refiner_streams_as_the_whole_turn_and_reads_the_buffered_points(shipped):
    sectors = split_turn(kitti_scan(0), shipped.cfg.sectors_per_turn)
    det = StreamingDetector(shipped)
    state = det.new_state()
    for s in sectors:
        (result,), (state,) = det.step([s], [state])
    with torch.inference_mode():
        whole, enc = shipped.forward_turn(sectors)
        plain = shipped.detect([enc.sectors])[0]
        grown = grown_boxes(plain.boxes, plain.labels, shipped.refiner.cfg)
        _, counts = box_points(torch.cat(sectors), grown, shipped.refiner.cfg.points)
        alone = refine(shipped.refiner, plain, sectors[-1])  # without the buffered sectors' points
    assert int((counts > 0).sum()) >= 20  # boxes with points: the refiner's input matters
    assert_same_detections(result.detections, whole[0])
    same_count = len(alone) == len(whole[0])  # the last NMS may keep another number of boxes
    assert not same_count or not torch.allclose(
        alone.boxes.sort(0).values, whole[0].boxes.sort(0).values, atol=1e-3
    )


def test_the_shipped_refiner_brings_the_boxes_closer_to_the_truth(shipped):
    """On held-out simulated scans (stream 7): the refined boxes overlap their true boxes more."""
    source = scan_source("sim", 7, shuffle=False)
    before, after = [], []
    for i in range(3):
        scan = source(i)
        n = shipped.cfg.sectors_per_turn
        sectors = scan_sectors(scan, shipped.cfg.vfe.point_features, n)
        with torch.inference_mode():
            layout = StreamLayout.single_stream(n, shipped.device)
            enc = shipped.encode(sectors, layout, shipped.init_states(1))
            plain = shipped.detect([enc.sectors])[0]
            refined = refine(shipped.refiner, plain, torch.cat(sectors))
        for det, into in ((plain, before), (refined, after)):
            keep = det.scores.numpy() >= 0.3
            iou = iou_matrix(det.boxes.numpy()[keep], scan.gt.boxes)
            into.extend(iou.max(1)[iou.max(1) >= 0.3])
    b, a = np.median(before), np.median(after)
    assert a > b + 0.05, (b, a)


def test_a_server_refines_unless_told_not_to():
    """`phim serve` runs the default model's refiner; `--no-refiner` serves the detector's boxes alone. Each
    server's replies equal its model's own streaming steps, and the two differ."""
    sectors = [s.numpy() for s in scan_sectors(scan_source("sim", 7, shuffle=False)(0), 4, 4)]
    replies: dict[bool, list[DetectionsReply]] = {}
    for refiner in (True, False):
        model = load_default_model("cpu")[0]
        if not refiner:
            model.drop_refiner()
        ref = run_direct(StreamingDetector(model), sectors)
        assert len(ref[-1]) > 0
        with serve(None, refiner=refiner) as server:
            assert httpx.get(f"{server.url}/v1/model").json()["refiner"] is refiner
            url, headers = f"{server.url}/v1/streams/car/sectors", {"Content-Type": "application/msgpack"}
            bodies = [encode_sector(sector_msg("car", i, s)) for i, s in enumerate(sectors)]
            posted = [httpx.post(url, content=b, headers=headers, timeout=60) for b in bodies]
            replies[refiner] = [decode_response(r.content) for r in posted]
        for r, d in zip(replies[refiner], ref, strict=True):
            assert isinstance(r, DetectionsReply), r
            assert_same_boxes(r.boxes, r.scores, r.labels, d)
    assert not np.array_equal(replies[True][-1].scores, replies[False][-1].scores)
