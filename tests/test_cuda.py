"""On a CUDA device the model computes what it computes on the CPU; skipped where no GPU is present.

CI has no GPU, so these run on a lent GPU machine (scripts/gpu_session.sh). Each compares a CUDA result
with the CPU (float64 where the op allows) on the same random or real inputs.
"""

from __future__ import annotations

import copy
import csv
import functools
from pathlib import Path

import pytest
import torch
from conftest import kitti_scan
from test_scan import _inputs
from test_sparse_conv import BATCH, SHAPE, random_sparse
from test_streaming import assert_same_detections, make_model, stream

from model.config import ScanImpl
from model.geometry.rulebook import Plane
from model.geometry.sparse_tensor import SparseTensor
from model.layers.sparse_conv import SparseConv2d, SparseInverseConv2d
from model.ops.scan import scan_available, selective_scan
from model.ops.scan_torch import selective_scan_ref
from model.ops.sparse_conv import gather_mm_scatter
from model.sectors import split_turn
from model.stream import StreamingDetector
from model.train.distributed import Dist
from model.train.loop import TrainConfig, train

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
CUDA = torch.device("cuda")
# The fixed-shape step against the eager detector on the GPU: both sum with atomics (scatters whose order
# varies) and the compiled step fuses its sums in other orders, so over eight steps of two streams a few
# of the buffered features differ by up to 6.4e-4 and the paper config's scores by 1.7e-4 (H200, 2026-12-04:
# 18 of 84,672 features, 2 of 500 scores); on the CPU they agree within 1e-4 (test_graph_step)
CUDA_ATOL = 1e-3
SCAN_LENGTHS = [[], [0, 0], [1], [0, 3, 0], [31, 32, 33, 64, 65], [300, 0, 1, 129], [4000, 17, 900]]
FAST_IMPLS = [i for i in ScanImpl if i not in (ScanImpl.REFERENCE, ScanImpl.NUMBA)]  # numba: CPU only


def _rel(a: torch.Tensor, ref: torch.Tensor) -> float:
    a, ref = a.detach().double().cpu(), ref.detach().double().cpu()
    assert torch.isfinite(a).all()
    return float((a - ref).norm() / ref.norm().clamp_min(1e-30))


@pytest.mark.parametrize("impl", FAST_IMPLS)
@pytest.mark.parametrize("lengths", SCAN_LENGTHS)
@pytest.mark.parametrize("shared_decay", [False, True])
@pytest.mark.parametrize("with_h0", [False, True])
def test_fast_scan_on_cuda_matches_reference(impl, lengths, shared_decay, with_h0):
    if not scan_available(impl, CUDA):
        pytest.fail(f"{impl.value} scan unavailable on this CUDA machine")
    u, delta, A, B, C, cu, h0 = _inputs(lengths, D=48, N=8, with_h0=with_h0, seed=sum(lengths))
    if shared_decay:
        A = A[:, :1]
    y_ref, h_ref = selective_scan_ref(u, delta, A, B, C, cu, h0)
    args = [t.float().to(CUDA) if t is not None and t.is_floating_point() else t for t in (u, delta, A, B, C)]
    h0_dev = None if h0 is None else h0.float().to(CUDA)
    y, h = selective_scan(*args, cu.to(CUDA), h0_dev, impl=impl, chunk_size=32)
    assert y.device.type == "cuda" and y.dtype == torch.float32
    assert _rel(y, y_ref) < 1e-5 and _rel(h, h_ref) < 1e-5


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])  # float32 runs the fused Triton path
@pytest.mark.parametrize("subm", [False, True])
@pytest.mark.parametrize("plane", list(Plane))
def test_sparse_conv_on_cuda_equals_cpu(plane, subm, dtype):
    x = random_sparse(SHAPE, BATCH, 0.2, 24, seed=5, dtype=dtype)
    stride = (1, 1) if subm else (2, 2)
    conv = SparseConv2d(24, 40, 3, stride, plane, bias=True, subm=subm).to(dtype)
    inv = SparseInverseConv2d(40, 24, 3, plane).to(dtype)
    y, rb = conv(x)
    back = inv(y, rb)
    conv_d, inv_d = copy.deepcopy(conv).to(CUDA), copy.deepcopy(inv).to(CUDA)
    x_d = SparseTensor(x.features.to(CUDA), x.coords.to(CUDA), x.spatial_shape, x.batch_size)
    y_d, rb_d = conv_d(x_d)
    back_d = inv_d(y_d, rb_d)
    assert torch.equal(y_d.coords.cpu(), y.coords) and torch.equal(back_d.coords.cpu(), x.coords)
    assert _rel(y_d.features, y.features) < 1e-6 and _rel(back_d.features, back.features) < 1e-6


@pytest.mark.parametrize("ident", [None, 4])
def test_fused_gather_mm_scatter_matches_torch_in_values_and_gradients(ident):
    from model.ops.sparse_conv_triton import gather_mm_scatter_triton  # triton: only where CUDA is

    x = random_sparse(SHAPE, BATCH, 0.3, 48, seed=9, dtype=torch.float32)
    conv = SparseConv2d(48, 136, 3, (1, 1), Plane.RZ, subm=True)
    rb = conv.rulebook(x)
    assert rb.identity_offset == 4
    results = []
    torch_twin = functools.partial(gather_mm_scatter, fused=False)
    for fn in (torch_twin, gather_mm_scatter_triton):
        src = x.features.to(CUDA).requires_grad_()
        w = conv.weight.detach().to(CUDA).requires_grad_()
        idx = (rb.in_idx.to(CUDA), rb.out_idx.to(CUDA))
        out = fn(src, w, *idx, rb.offset_ptr, rb.num_out, ident)
        out.pow(2).sum().backward()
        results.append((out.detach(), src.grad, w.grad))
    for got, ref in zip(results[1], results[0], strict=True):
        assert _rel(got, ref) < 1e-5


@pytest.fixture(scope="module")
def models():
    cpu = make_model()
    return cpu, copy.deepcopy(cpu).to(CUDA)


def test_detector_on_cuda_equals_cpu(models):
    cpu, gpu = models
    sectors = split_turn(kitti_scan(0), cpu.cfg.sectors_per_turn)
    on_cpu, _ = stream(StreamingDetector(cpu), sectors)
    on_gpu, _ = stream(StreamingDetector(gpu), [s.to(CUDA) for s in sectors])
    assert len(on_cpu[-1].detections) > 0
    for a, b in zip(on_cpu, on_gpu, strict=True):
        assert a.context_sectors == b.context_sectors
        assert_same_detections(b.detections.to(torch.device("cpu")), a.detections, atol=2e-3)


def test_streaming_equals_whole_turn_on_cuda(models):
    _, gpu = models
    sectors = [s.to(CUDA) for s in split_turn(kitti_scan(1), gpu.cfg.sectors_per_turn)]
    results, state = stream(StreamingDetector(gpu), sectors)
    with torch.inference_mode():
        whole, enc = gpu.forward_turn(sectors)
    for s_state, ref in zip(state.mamba, enc.states, strict=True):
        torch.testing.assert_close(s_state.ssm, ref.ssm, rtol=1e-4, atol=1e-5)
    assert len(whole[0]) > 0
    # the GPU's scatter-adds (atomics) sum in any order: scores agree to ~2e-4, not the CPU's 1e-4
    assert_same_detections(results[-1].detections, whole[0], atol=1e-3)


def test_batched_equals_alone_on_cuda(models):
    _, gpu = models
    det = StreamingDetector(gpu)
    turns = [split_turn(kitti_scan(i), gpu.cfg.sectors_per_turn) for i in (0, 1)]
    turns = [[s.to(CUDA) for s in t] for t in turns]
    alone = [stream(det, t)[0] for t in turns]
    states = [det.new_state() for _ in turns]
    for k in range(gpu.cfg.sectors_per_turn):
        results, states = det.step([turns[1][k], turns[0][k]], states)
        assert_same_detections(results[0].detections, alone[1][k].detections)
        assert_same_detections(results[1].detections, alone[0][k].detections)


def test_short_training_run_on_cuda_with_bf16_autocast(tmp_path: Path):
    cfg = TrainConfig(steps=4, checkpoint_every=2, log_every=1, workers=0, amp=True)
    model_path = train(cfg, tmp_path / "run", device="cuda", progress=False)
    assert model_path.is_file()
    with (tmp_path / "run" / "metrics.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 4 and all(torch.isfinite(torch.tensor(float(r["loss"]))) for r in rows)


def test_more_ranks_than_gpus_is_a_clear_error(monkeypatch):
    local = torch.cuda.device_count()
    monkeypatch.setenv("WORLD_SIZE", str(local + 1))
    monkeypatch.setenv("RANK", str(local))
    monkeypatch.setenv("LOCAL_RANK", str(local))
    with pytest.raises(RuntimeError, match=f"LOCAL_RANK {local} but only {local} CUDA device"):
        Dist.from_env("cuda")


@pytest.mark.parametrize("compile", [False, True])
def test_graph_step_on_cuda_equals_eager_on_cuda(models, compile):
    """The fixed-shape step on the GPU (op by op, and through torch.compile: Triton kernels, each bucket
    replayed as a CUDA graph) equals the eager detector there, over two turns of two streams (the second
    turn's dense part on crops)."""
    from test_graph_step import run_both

    from model.graph.engine import GraphStreamingDetector

    _, gpu = models
    turns = [split_turn(kitti_scan(i), gpu.cfg.sectors_per_turn) for i in (0, 1)]
    graph = GraphStreamingDetector(gpu, compile=compile)
    graph.calibrate([s.cuda() for s in turns[0]])
    batches = [[t[k].cuda() for t in turns] for k in range(gpu.cfg.sectors_per_turn)] * 2
    run_both(graph, StreamingDetector(gpu), batches, atol=CUDA_ATOL)


@pytest.mark.parametrize("compile", [False, True])
def test_bf16_graph_step_on_cuda_agrees_with_fp32(compile):
    """`--precision bf16` on the graph engine (op by op, and compiled): the shipped model's detections on a
    KITTI turn agree with its fp32 ones as on the CPU (test_precision), states and outputs stay float32."""
    from precision_helpers import REFINED, assert_agree

    from model.checkpoint import load_default_model
    from model.config import Precision
    from model.graph.engine import GraphStreamingDetector

    model = load_default_model(CUDA)[0]
    sectors = [s.cuda() for s in split_turn(kitti_scan(0), model.cfg.sectors_per_turn)]
    fp32, _ = stream(StreamingDetector(model), sectors)
    det = GraphStreamingDetector(model, compile=compile, precision=Precision.BF16)
    det.calibrate(sectors)
    bf16, state = stream(det, sectors)
    st = det.read_state(state)
    assert all(t.dtype == torch.float32 for t in (*st.conv, *st.ssm, st.feats))
    got = bf16[-1].detections
    assert (got.boxes.dtype, got.scores.dtype) == (torch.float32, torch.float32)
    assert_agree(fp32[-1].detections.to(torch.device("cpu")), got.to(torch.device("cpu")), **REFINED)


@pytest.mark.parametrize("compile", [False, True])
def test_paper_graph_step_on_cuda_equals_eager(compile):
    """The paper config (strides 1, 2, 4, kernels 3 and 5) on the GPU: the fixed-shape step, op by op and
    compiled (CUDA graphs), equals the eager detector there on real KITTI sectors, two streams batched (the
    fifth sector's dense part on crops)."""
    from test_graph_step import paper_model, run_both

    from model.graph.engine import GraphStreamingDetector

    model = paper_model().to(CUDA)
    cfg = model.cfg
    turns = []
    for i in (0, 1):
        scan = kitti_scan(i)
        scan = torch.cat([scan, scan.new_zeros(scan.shape[0], 1)], 1)  # elongation column
        turns.append([s.cuda() for s in split_turn(scan, cfg.sectors_per_turn)])
    graph = GraphStreamingDetector(model, compile=compile)
    graph.calibrate(turns[0])
    batches = [[turns[0][k], turns[1][k]] for k in range(cfg.sectors_per_turn)]
    run_both(graph, StreamingDetector(model), batches + batches[:1], atol=CUDA_ATOL)
    assert graph.crop_misses == 0 and any(cap.bev_crop for _, cap in graph.compiled_buckets) == compile


def test_triton_segmented_scan_on_cuda_equals_its_twin():
    """The selective-scan Triton kernels compiled for the GPU (test_ops_scan_triton runs them in
    Triton's interpreter)."""
    from scan_triton_cases import cases
    from test_ops_scan_triton import check_cases

    check_cases(cases("cuda"))
