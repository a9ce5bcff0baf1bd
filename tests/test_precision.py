"""bf16 autocast inference (`model.precision`): the scan's recurrence and the Mamba states stay float32 under
autocast, and on real KITTI scans the shipped model's bf16 detections agree with its fp32 ones (eager and
fixed-shape engines)."""

from __future__ import annotations

import logging
from dataclasses import fields

import pytest
import torch
from conftest import kitti_scan
from precision_helpers import REFINED, assert_agree
from pydantic import ValidationError

from lidar.sources import SimSource
from model.checkpoint import load_default_model
from model.config import MambaConfig, Precision, ScanImpl, tiny
from model.eval.runner import predict_scan
from model.geometry.boxes import Detections
from model.graph.engine import GraphStreamingDetector
from model.graph.segments import stream_segments
from model.layers.mamba import Mamba, MambaState, Packing
from model.ops.scan import scan_available, selective_scan
from model.ops.sparse_conv_torch import gather_mm_scatter_torch
from model.precision import autocast, check_precision
from model.sectors import split_turn
from model.stream import StreamingDetector, StreamState
from server.app import build_detector
from server.settings import Settings
from server.warmup import model_info

CPU = torch.device("cpu")
CPU_IMPLS = [impl for impl in ScanImpl if scan_available(impl, CPU)]
BF16 = {"device_type": "cpu", "dtype": torch.bfloat16}


def test_fp32_is_no_autocast_and_bf16_is():
    a, b = torch.randn(4, 8), torch.randn(8, 3)
    with autocast(Precision.FP32, CPU):
        assert (a @ b).dtype == torch.float32
    with autocast(Precision.BF16, CPU):
        assert (a @ b).dtype == torch.bfloat16


def test_bf16_is_checked_against_the_device(caplog):
    with pytest.raises(ValueError, match="runs on cpu or cuda"):
        check_precision(Precision.BF16, torch.device("meta"))
    check_precision(Precision.FP32, torch.device("meta"))  # fp32 runs anywhere
    with caplog.at_level(logging.WARNING, logger="model.precision"):
        check_precision(Precision.BF16, CPU)
    assert "meant for CUDA" in caplog.text


def test_serve_setting_takes_fp32_or_bf16_only(monkeypatch):
    monkeypatch.setenv("PHIM_PRECISION", "bf16")
    assert Settings().precision == "bf16"
    with pytest.raises(ValidationError, match="precision"):
        Settings(precision="fp16")


def _scan_inputs(T: int = 70, D: int = 6, N: int = 4) -> tuple[torch.Tensor, ...]:
    """bf16 scan inputs (what the projections give under autocast), two sequences with carried states."""
    g = torch.Generator().manual_seed(3)
    u, B, C = (torch.randn(T, k, generator=g).bfloat16() for k in (D, N, N))
    delta = (torch.rand(T, D, generator=g) * 0.5 + 0.01).bfloat16()
    A = -(torch.rand(D, N, generator=g) * 3 + 0.1)
    cu = torch.tensor([0, 45, T])
    h0 = torch.randn(2, D, N, generator=g)
    return u, delta, A, B, C, cu, h0


@pytest.mark.parametrize("impl", CPU_IMPLS)
def test_scan_recurrence_is_float32_under_autocast(impl: ScanImpl):
    """The same bits inside an autocast region as outside (the reference's per-step h @ C would otherwise
    run in bf16), and the final states in float32."""
    args = _scan_inputs()
    y, h = selective_scan(*args, impl=impl, chunk_size=16)
    with torch.autocast(**BF16):
        y_ac, h_ac = selective_scan(*args, impl=impl, chunk_size=16)
    assert h_ac.dtype == torch.float32 and y_ac.dtype == torch.bfloat16
    assert torch.equal(y_ac, y) and torch.equal(h_ac, h)


def test_mamba_states_stay_float32_under_autocast():
    """Eager layer and the graph step's segmented form: bf16 activations, float32 conv and ssm states."""
    m = Mamba(16, MambaConfig(d_state=4, expand=2)).eval()
    lengths = [9, 0, 14]
    S, T = len(lengths), sum(lengths)
    state = MambaState.zeros(S, m.d_inner, m.cfg.d_conv, m.cfg.d_state, CPU)
    x = torch.randn(T, 16)
    batch = torch.repeat_interleave(torch.arange(S), torch.tensor(lengths))  # (T,)
    with torch.no_grad(), torch.autocast(**BF16):
        y, eager = m(x, torch.tensor([0, *lengths]).cumsum(0), state)
        segs = stream_segments(batch, torch.ones(T, dtype=torch.bool), S)
        _, graph = m(x, Packing.of_segments(segs, m.cfg.d_conv, ScanImpl.AUTO), state)
    assert y.dtype == torch.bfloat16  # autocast ran
    assert graph is not None
    for s in (eager, graph):
        assert (s.conv.dtype, s.ssm.dtype) == (torch.float32, torch.float32)
    torch.testing.assert_close(graph.conv, eager.conv, rtol=0, atol=0)


def test_sparse_conv_sums_stay_float32_under_autocast():
    g = torch.Generator().manual_seed(0)
    src, weight = torch.randn(50, 8, generator=g), torch.randn(3, 8, 5, generator=g)  # (N, Ci), (K, Ci, Co)
    src_idx, dst_idx = torch.randint(0, 50, (90,), generator=g), torch.randint(0, 20, (90,), generator=g)
    ptr = (0, 30, 60, 90)
    ref = gather_mm_scatter_torch(src, weight, src_idx, dst_idx, ptr, 20)
    with torch.autocast(**BF16):
        out = gather_mm_scatter_torch(src, weight, src_idx, dst_idx, ptr, 20)
    assert out.dtype == torch.float32
    assert not torch.equal(out, ref)  # the products ran in bf16
    torch.testing.assert_close(out, ref, rtol=0.03, atol=0.1)


def test_head_maps_are_float32_under_autocast():
    head = load_default_model("cpu")[0].head.eval()
    bev = torch.randn(1, head.shared[0].in_channels, 24, 32)  # (B, C, H, W)
    with torch.no_grad(), torch.autocast(**BF16):
        out = head(bev)
        per_branch = head.forward_per_branch(bev)
    for maps in (out, per_branch):
        assert {f.name: getattr(maps, f.name).dtype for f in fields(maps)} == dict.fromkeys(
            (f.name for f in fields(maps)), torch.float32
        )


def test_served_precision_is_reported():
    settings = Settings(device="cpu", engine="graph", precision="bf16", zenoh_enabled=False)
    det, source = build_detector(settings)
    assert det.precision is Precision.BF16
    assert model_info(det, source, "w")["precision"] == "bf16"


def test_eval_predicts_in_bf16():
    """`phim eval --precision bf16`: a simulator scan's full-turn boxes agree with fp32's."""
    model, scan = load_default_model("cpu")[0].eval(), SimSource(7)(0)
    fp32, bf16 = (predict_scan(model, scan, p).predictions[-1] for p in Precision)
    as_dets = [
        Detections(*(torch.from_numpy(a) for a in (p.boxes, p.scores, p.labels))) for p in (fp32, bf16)
    ]
    assert_agree(*as_dets, min_boxes=5)


Engines = type[StreamingDetector] | type[GraphStreamingDetector]


def _turn(engine: Engines, precision: Precision, sectors: list[torch.Tensor], refiner: bool = True):
    """The eager engine, or the fixed-shape step op by op (the graph engine's plain twin); the shipped
    model, or its detector alone."""
    model = load_default_model("cpu")[0]
    if not refiner:
        model.drop_refiner()
    det = engine(model, precision=precision)
    assert det.precision is precision
    state = det.new_state()
    for s in sectors:
        (result,), (state,) = det.step([s], [state])
    return result.detections, (state if isinstance(det, StreamingDetector) else det.read_state(state))


def _float_tensors(state) -> list[torch.Tensor]:
    if isinstance(state, StreamState):
        return [t for m in state.mamba for t in (m.conv, m.ssm)] + [b.features for b in state.buffer]
    return [*state.conv, *state.ssm, state.feats, state.maps]  # GraphStreamState: a slot's tensors


@pytest.mark.samples
@pytest.mark.parametrize("engine", [StreamingDetector, GraphStreamingDetector], ids=["eager", "fixed-shape"])
@pytest.mark.parametrize("refiner", [False, True], ids=["detector", "refined"])
def test_bf16_detections_agree_with_fp32_on_kitti(engine: Engines, refiner: bool):
    """A turn and one sector more (the fixed step runs that one's dense part on crops)."""
    sectors = split_turn(kitti_scan(0), tiny().sectors_per_turn)
    sectors += sectors[:1]
    fp32, _ = _turn(engine, Precision.FP32, sectors, refiner)
    bf16, state = _turn(engine, Precision.BF16, sectors, refiner)
    assert (bf16.boxes.dtype, bf16.scores.dtype) == (torch.float32, torch.float32)
    assert all(t.dtype == torch.float32 for t in _float_tensors(state))
    if refiner:
        assert_agree(fp32, bf16, **REFINED)
    else:
        assert_agree(fp32, bf16)
