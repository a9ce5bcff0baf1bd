"""Numeric extremes on the serving path (issue 51). One sector with a point at x = -1e30 (a finite float32)
killed a worker: its int64 cell index overflowed in the box refiner's lookup, which wrote outside its
buffers. Here every numba kernel a sector reaches (the refiner's lookup, NMS, the voxelizer, the graph
engine's sort, search, BEV scatter, sparse conv and scans) and its twin meet +-1e19..3.4e38 in any
coordinate, subnormals, all points identical, all at the origin, boxes of extreme centre, size or yaw, NaN
and inf, empty inputs. Each group of cases runs in a child process (the cases of a group one after another,
each named on stdout before it runs), so a crash fails the test naming its case instead of killing pytest.
Where the inputs are finite, the lookup and NMS must also give their plain twins' results. The contract's
range in front of them, and the issue's inputs sent to a real worker: tests/test_extremes_serve.py."""

from __future__ import annotations

import math
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
import torch

TESTS = Path(__file__).resolve().parent
REPO = TESTS.parent
F32_MAX = float(np.finfo(np.float32).max)
EXTREMES = (0.0, -0.0, 1e-45, -1e-45, 1e-40, 1.1754944e-38, 1e19, -1e19, 9.2233715e18, 1.8446744e19)
EXTREMES += (1e30, -1e30, F32_MAX, -F32_MAX)
NON_FINITE = (math.nan, math.inf, -math.inf)
FIELDS = ("x", "y", "z", "intensity")


def cluster(rng: np.random.Generator, n: int = 300) -> np.ndarray:
    """The issue's lone cluster: (n, 4) float32, x 20..40 m, y -10..-2 m, z -1.5..1 m, intensity 0..1."""
    lo, hi = (20.0, -10.0, -1.5, 0.0), (40.0, -2.0, 1.0, 1.0)
    return rng.uniform(lo, hi, (n, 4)).astype(np.float32)


def killer_sector() -> np.ndarray:
    """The issue's sector: the cluster and one more point at x = -1e30."""
    return np.concatenate([cluster(np.random.default_rng(0)), [[-1e30, -5.0, 0.0, 0.5]]]).astype(np.float32)


def extreme_values(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n,) float32: the listed extremes and log-uniform magnitudes 1e19..3.4e38 of either sign."""
    listed = rng.choice(np.array(EXTREMES, np.float32), n)
    drawn = np.clip(10.0 ** rng.uniform(19, 38.6, n) * rng.choice([-1, 1], n), -F32_MAX, F32_MAX)
    return np.where(rng.random(n) < 0.5, listed, drawn.astype(np.float32))


def spoil(rng: np.random.Generator, a: np.ndarray, columns: int, fraction: float) -> np.ndarray:
    """A copy of a (N, C) with `fraction` of its first `columns` columns' values replaced by extremes."""
    out = a.copy()
    hit = rng.random((a.shape[0], columns)) < fraction
    out[:, :columns][hit] = extreme_values(rng, int(hit.sum()))
    return out


def case(name: str) -> None:
    print(f"case {name}", flush=True)


# ------------------------------------------------------------------------------------ the kernel groups


def _lookup_cases(rng: np.random.Generator) -> Iterator[tuple[str, np.ndarray, np.ndarray]]:
    """(name, points (N, 3), boxes (B, 7)) for the refiner's lookup."""
    pts = cluster(rng)[:, :3]
    boxes = np.array(
        [[30, -6, 0, 4, 2, 1.5, 0.3], [25, -3, -0.5, 0.8, 0.8, 1.7, -1.0], [35, -8, 0, 4.5, 1.9, 1.6, 2.0]],
        np.float32,
    )
    for v in EXTREMES + NON_FINITE:
        for c in range(7):
            if c < 3:
                p = pts.copy()
                p[-1, c] = v
                yield f"point[{c}]={v}", p, boxes
            b = boxes.copy()
            b[0, c] = v
            yield f"box[{c}]={v}", pts, b
    for at in ((0, 0, 0), (30, -6, 0), (1e30, 1e30, 1e30), (1e-45, -1e-45, 0)):
        yield (
            f"all points at {at}",
            np.tile(np.float32(at), (200, 1)),
            np.concatenate([boxes, [[*at, 1, 1, 1, 0]]]).astype(np.float32),
        )
    yield "no points", pts[:0], boxes
    yield "no boxes", pts, boxes[:0]
    yield "one point", pts[:1], boxes
    for i in range(40):
        n, b = int(rng.choice([1, 2, 50, 400])), int(rng.choice([1, 3, 12]))
        jitter = boxes[rng.integers(0, 3, b)] + rng.normal(0, 1, (b, 7)).astype(np.float32)
        yield f"random {i}", spoil(rng, cluster(rng, n)[:, :3], 3, 0.2), spoil(rng, jitter, 7, 0.15)


def refine_group() -> int:
    from model.layers.refine import box_points, box_points_reference, box_points_torch

    picked, done = 8, 0
    for name, pts, boxes in _lookup_cases(np.random.default_rng(51)):
        case(name)
        p, b = torch.from_numpy(pts), torch.from_numpy(boxes)
        want_local, want = box_points_reference(p, b, picked)
        comparable = (
            np.isfinite(pts).all() and np.isfinite(boxes).all() and bool((abs(boxes[:, 6]) < 1e3).all())
        )
        for lookup in (box_points, box_points_torch):
            local, counts = lookup(p, b, picked)
            assert local.shape == (len(boxes), 8, 3) and counts.shape == (len(boxes),), name
            assert bool(((counts >= 0) & (counts <= len(pts))).all()), (name, counts)
            if comparable:
                assert torch.equal(counts, want), (name, lookup.__name__, counts, want)
                np.testing.assert_allclose(local, want_local, rtol=1e-6, atol=1e-5, err_msg=name)
        done += 1
    return done


def nms_group() -> int:
    from model.geometry.nms import _grouped_nms_torch
    from model.ops.nms_numba import class_nms_batch_cpu, grouped_nms_cpu

    rng, done = np.random.default_rng(52), 0
    base = np.concatenate([rng.uniform(-20, 20, (40, 2)), rng.uniform(-1, 1, (40, 1))], 1)
    base = np.concatenate([base, rng.uniform(0.5, 4, (40, 3)), rng.uniform(-3, 3, (40, 1))], 1).astype(
        np.float32
    )
    cases: list[tuple[str, np.ndarray]] = []
    for v in EXTREMES + NON_FINITE:
        for c in range(7):
            b = base.copy()
            b[::4, c] = v
            cases.append((f"box[{c}]={v}", b))
    cases += [("identical", np.tile(base[:1], (40, 1))), ("at the origin", np.zeros((40, 7), np.float32))]
    cases += [("empty", base[:0])] + [(f"random {i}", spoil(rng, base, 7, 0.2)) for i in range(30)]
    for name, boxes in cases:
        case(name)
        n = len(boxes)
        scores = rng.random(n).astype(np.float32)
        if name.startswith("random") and n:
            scores[rng.random(n) < 0.1] = np.nan
        b, s = torch.from_numpy(boxes), torch.from_numpy(scores)
        groups, thresholds = torch.from_numpy(rng.integers(0, 3, n)), torch.full((n,), 0.3)
        kept = grouped_nms_cpu(b, s, thresholds, groups, 25)
        assert len(kept) <= 25 and len(set(kept.tolist())) == len(kept), name
        assert bool(((kept >= 0) & (kept < max(n, 1))).all()), name
        if np.isfinite(boxes).all() and np.isfinite(scores).all() and bool((abs(boxes) <= 1e4).all()):
            assert torch.equal(kept, _grouped_nms_torch(b, s, thresholds, groups, 25)), name
        valid = torch.from_numpy(rng.random((2, n)) < 0.8)
        flat, counts = class_nms_batch_cpu(
            b.expand(2, n, 7), s.expand(2, n), groups.expand(2, n), valid, (0.7, 0.5, 0.5), 30, 20
        )
        assert int(counts.sum()) == len(flat) and bool((counts <= 20).all()), name
        assert bool(valid.reshape(-1)[flat].all()), name  # only valid candidates kept
        done += 1
    return done


def voxelize_group() -> int:
    from test_voxelize import make_voxelizer

    from model.config import tiny
    from model.geometry.sparse_tensor import SENTINEL
    from model.graph.voxelize import group_torch, point_keys_torch
    from model.ops.voxelize_numba import grid_args, group_sorted, point_keys

    vox, rng, done = make_voxelizer(tiny().grid), np.random.default_rng(53), 0
    cells = 2 * math.prod(vox.spatial_shape)
    cases: list[tuple[str, np.ndarray]] = []
    for v in EXTREMES + NON_FINITE:
        for c in range(4):
            pts = np.concatenate([cluster(rng, 64), cluster(rng, 64) * [-1, 1, 1, 1]]).astype(np.float32)
            pts[::3, c] = v
            cases.append((f"point[{c}]={v}", pts))
    cases += [
        ("identical", np.tile(cluster(rng, 1), (128, 1))),
        ("at the origin", np.zeros((128, 4), np.float32)),
    ]
    cases += [(f"random {i}", spoil(rng, cluster(rng, 128), 4, 0.3)) for i in range(20)]
    for name, pts in cases:
        case(name)
        points = torch.from_numpy(pts).reshape(2, 64, 4)
        for counts in (torch.tensor([64, 50]), torch.tensor([0, 0])):  # the rest is padding, extremes too
            key, base, kept, out = point_keys(points, counts, vox.point_features, *grid_args(vox.grid))
            assert bool(((key == SENTINEL) | ((key >= 0) & (key < cells))).all()), name
            assert torch.equal(kept + out, counts), name
            if np.isfinite(pts).all():
                want = point_keys_torch(vox, points, counts)
                assert torch.equal(key, want[0]) and torch.equal(kept, want[2]), name
            sorted_key, order = torch.sort(key, stable=True)
            keys, vid, count, _ = group_sorted(sorted_key, order, base, 32)
            assert bool(((vid >= 0) & (vid <= 32)).all()) and int(count) <= int(kept.sum()), name
            twin = group_torch(vox, sorted_key, order, base, 32)
            assert torch.equal(keys, twin[0]) and torch.equal(vid, twin[1]), name
        done += 1
    return done


def graph_ops_group() -> int:
    from model.graph.segments import stream_segments
    from model.ops.bev_mean_numba import bev_mean_numba
    from model.ops.scan_numba import selective_scan_numba
    from model.ops.search_numba import search_numba
    from model.ops.sort_numba import sort_keys_numba
    from model.ops.table_conv_numba import table_conv_numba

    rng, done = np.random.default_rng(54), 0
    big = np.iinfo(np.int64)
    ints = torch.tensor([0, 1, 5, 2**40, 2**62, big.max, big.min, -1, 7, 2**62, 3], dtype=torch.int64)
    case("sort and search int64 extremes")
    assert torch.equal(sort_keys_numba(ints)[0], torch.sort(ints, stable=True)[0])
    keys = torch.sort(ints[ints >= 0])[0]
    assert torch.equal(search_numba(keys, ints.reshape(1, -1)), torch.searchsorted(keys, ints.reshape(1, -1)))
    done += 1
    for v in EXTREMES + NON_FINITE:
        case(f"features={v}")
        x = torch.from_numpy(rng.normal(0, 1, (40, 6)).astype(np.float32))
        x[::5] = v
        table = torch.from_numpy(rng.integers(0, 41, (30, 9)))  # 40: no row
        assert table_conv_numba(x, table, torch.ones(9, 6, 4), torch.zeros(4)).shape == (30, 4)
        column = torch.from_numpy(rng.integers(-(2**40), 2**40, (2, 20)))
        column[0, :3] = torch.tensor([big.min, big.max, -1])
        cell_table = torch.from_numpy(rng.integers(-1, 12, (16, 3)))
        out = bev_mean_numba(
            x[:40].reshape(2, 20, 6), column, torch.ones(2, 20, dtype=torch.bool), cell_table, 3, 4
        )
        assert out.shape == (2, 3, 4, 6)
        u = x[:, :4].contiguous()  # (T, D) tokens
        dt, a, bc = u.abs(), -torch.ones(4, 3), torch.full((40, 3), float(v))
        segs = stream_segments(torch.arange(40) // 20, torch.arange(40) % 7 != 3, 2)
        y, final = selective_scan_numba(u, dt, a, bc, bc, segs, torch.zeros(2, 4, 3))
        assert y.shape == (40, 4) and bool((y[~segs.valid] == 0).all()) and final.shape == (2, 4, 3)
        y, final = selective_scan_numba(u, dt, a, bc, bc, torch.tensor([0, 25, 40], dtype=torch.int32))
        assert y.shape == (40, 4) and final.shape == (2, 4, 3)
        done += 1
    return done


def model_group() -> int:
    """The default model's eager step on sectors no admission checked (the model, eval and training paths
    call the kernels too): the issue's sector must give boxes (its refiner lookup ran), the rest anything."""
    from model.checkpoint import load_default_model
    from model.stream import StreamingDetector

    det, rng, done = StreamingDetector(load_default_model("cpu")[0]), np.random.default_rng(55), 0
    cases = [("the issue's sector", killer_sector())]
    for c, v in ((0, 1e19), (0, -F32_MAX), (1, 1e30), (2, F32_MAX), (3, F32_MAX), (0, 1e-45)):
        pts = cluster(rng)
        pts[::50, c] = v
        cases.append((f"point[{c}]={v}", pts))
    cases += [
        ("identical", np.tile(cluster(rng, 1), (300, 1))),
        ("at the origin", np.zeros((300, 4), np.float32)),
    ]
    cases += [("one point", cluster(rng, 1)), ("random", spoil(rng, cluster(rng), 4, 0.1))]
    for name, pts in cases:
        case(name)
        state = det.new_state()
        with torch.inference_mode():
            for _ in range(2 if done == 0 else 1):  # the issue's: again with its points buffered
                (result,), (state,) = det.step([torch.from_numpy(pts)], [state])
        boxes = result.detections.boxes
        assert boxes.shape[1] == 7 and (len(boxes) > 0 or name != "the issue's sector"), name
        done += 1
    return done


# each group and the fewest cases it must run (a group that ran none would pass vacuously)
GROUPS: dict[str, tuple[Callable[[], int], int]] = {
    "refine": (refine_group, 200),
    "nms": (nms_group, 150),
    "voxelize": (voxelize_group, 80),
    "graph_ops": (graph_ops_group, 18),
    "model": (model_group, 11),
}
# the child processes: a few, each starting torch once (its import is most of a child's time)
CHILDREN = {"kernels": ("refine", "nms", "voxelize", "graph_ops"), "model": ("model",)}
_CHILD = (
    f"import sys; sys.path.insert(0, {str(TESTS)!r}); import test_extremes as t; t.run_child(sys.argv[1])"
)


def run_child(name: str) -> None:
    torch.set_num_threads(1)  # small ops: two threads' OpenMP barriers cost more than they give on 2 cores
    for group in CHILDREN[name]:
        print(f"group {group}", flush=True)
        print(f"done {group} {GROUPS[group][0]()}", flush=True)


@pytest.mark.parametrize("child", list(CHILDREN))
def test_every_kernel_on_the_serving_path_survives_numeric_extremes(child: str) -> None:
    run = subprocess.run(
        [sys.executable, "-c", _CHILD, child], cwd=REPO, capture_output=True, text=True, timeout=600
    )
    lines = run.stdout.splitlines()
    at = [x for x in lines if x.startswith(("group ", "case "))][-2:]  # the group and case it was in
    assert run.returncode == 0, f"exit code {run.returncode} in {at}:\n{run.stderr[-3000:]}"
    done = {x.split()[1]: int(x.split()[2]) for x in lines if x.startswith("done ")}
    assert done.keys() == set(CHILDREN[child]), lines[-3:]
    assert all(n >= GROUPS[group][1] for group, n in done.items()), done
