"""Selective scan: reference against a hand-computed case, chunked and numba against the reference."""

from __future__ import annotations

import logging
import math
import sys

import pytest
import torch

from model.config import ScanImpl
from model.ops import scan
from model.ops import triton_support as runtime
from model.ops.scan import resolve_scan, scan_available, selective_scan
from model.ops.scan_numba import selective_scan_numba
from model.ops.scan_torch import selective_scan_chunked, selective_scan_ref

CPU_IMPLS = [impl for impl in ScanImpl if scan_available(impl, torch.device("cpu"))]


def _cu(lengths: list[int]) -> torch.Tensor:
    return torch.tensor([0, *lengths], dtype=torch.int64).cumsum(0)


def _inputs(
    lengths: list[int], D: int = 5, N: int = 3, with_h0: bool = True, seed: int = 0, dtype=torch.float64
):
    """Random scan inputs: u, delta (positive), A (negative), B, C, cu_seqlens, h0."""
    g = torch.Generator().manual_seed(seed)
    T, S = sum(lengths), len(lengths)
    u = torch.randn(T, D, generator=g, dtype=torch.float64)
    delta = torch.rand(T, D, generator=g, dtype=torch.float64) * 0.6 + 0.01
    A = -(torch.rand(D, N, generator=g, dtype=torch.float64) * 4 + 0.05)
    B = torch.randn(T, N, generator=g, dtype=torch.float64)
    C = torch.randn(T, N, generator=g, dtype=torch.float64)
    h0 = torch.randn(S, D, N, generator=g, dtype=torch.float64) if with_h0 else None
    return u, delta, A, B, C, _cu(lengths), h0


def test_reference_matches_hand_computed_two_steps():
    # one sequence of 2 tokens, D = 1, N = 2, with an initial state; closed form with python floats
    u1, u2, d1, d2 = 0.7, -1.3, 0.2, 0.5
    a = (-1.0, -3.0)
    b1, b2, c1, c2 = (0.4, -0.6), (1.1, 0.3), (0.9, -0.2), (-0.5, 1.5)
    h0 = (0.25, -0.75)
    h1 = [math.exp(d1 * a[n]) * h0[n] + d1 * b1[n] * u1 for n in range(2)]
    h2 = [math.exp(d2 * a[n]) * h1[n] + d2 * b2[n] * u2 for n in range(2)]
    y1 = sum(c1[n] * h1[n] for n in range(2))
    y2 = sum(c2[n] * h2[n] for n in range(2))
    t = lambda *v: torch.tensor(v, dtype=torch.float64)  # noqa: E731
    y, hT = selective_scan_ref(t([u1], [u2]), t([d1], [d2]), t(a), t(b1, b2), t(c1, c2), _cu([2]), t([h0]))
    torch.testing.assert_close(y, t([y1], [y2]), rtol=1e-14, atol=1e-14)
    torch.testing.assert_close(hT, t([h2]), rtol=1e-14, atol=1e-14)


LENGTHS = [
    [1],
    [0],
    [0, 3, 0],
    [15, 16, 17, 1, 0, 2],
    [31, 32, 33, 64, 65],
    [300, 0, 1, 129, 7],
]


@pytest.mark.parametrize("lengths", LENGTHS)
@pytest.mark.parametrize("with_h0", [False, True])
@pytest.mark.parametrize("chunk_size", [1, 4, 16, 32, 64])
def test_chunked_matches_reference_float64(lengths, with_h0, chunk_size):
    args = _inputs(lengths, with_h0=with_h0, seed=len(lengths) + chunk_size)
    y_ref, h_ref = selective_scan_ref(*args)
    with torch.no_grad():
        y, h = selective_scan_chunked(*args, chunk_size=chunk_size)
    assert y.shape == y_ref.shape and h.shape == h_ref.shape
    torch.testing.assert_close(y, y_ref, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(h, h_ref, rtol=1e-10, atol=1e-10)
    if not with_h0:  # empty sequences end in the zero state
        empty = _cu(lengths).diff() == 0
        assert (h[empty] == 0).all()
    else:
        empty = _cu(lengths).diff() == 0
        assert torch.equal(h[empty], args[6][empty])


@pytest.mark.parametrize("lengths", LENGTHS)
@pytest.mark.parametrize("with_h0", [False, True])
@pytest.mark.parametrize("shared", [False, True])
def test_numba_matches_reference_float64(lengths, with_h0, shared):
    u, delta, A, B, C, cu, h0 = _inputs(lengths, with_h0=with_h0, seed=len(lengths) + 40)
    A = A[:, :1] if shared else A
    y_ref, h_ref = selective_scan_ref(u, delta, A, B, C, cu, h0)
    y, h = selective_scan_numba(u, delta, A, B, C, cu, h0)
    assert y.dtype == h.dtype == torch.float64 and h.is_contiguous()
    torch.testing.assert_close(y, y_ref, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(h, h_ref, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("shared", [False, True])
@pytest.mark.parametrize("with_h0", [False, True])
def test_numba_gradients_pass_gradcheck(shared, with_h0):
    """Every input's gradient, y's and the final states' paths, against finite differences."""
    u, delta, A, B, C, cu, h0 = _inputs([6, 0, 9, 1], D=3, N=2, with_h0=with_h0, seed=41)
    A = A[:, :1] if shared else A
    leaves = [t.requires_grad_() for t in (u, delta, A, B, C, *([h0] if with_h0 else []))]

    def fn(*t):
        return selective_scan_numba(*t[:5], cu, t[5] if with_h0 else None)

    assert torch.autograd.gradcheck(fn, leaves, eps=1e-6, atol=1e-7)


def test_numba_float32_forward_and_backward_match_chunked():
    args64 = _inputs([200, 33, 0, 64], D=16)
    args = [a.float() if a is not None and a.is_floating_point() else a for a in args64]
    grads = []
    for fn in (lambda *a: selective_scan_chunked(*a, chunk_size=32), selective_scan_numba):
        leaves = [a.clone().requires_grad_() if a is not None and a.is_floating_point() else a for a in args]
        y, h = fn(*leaves)
        assert y.dtype == h.dtype == torch.float32
        (y.sin().sum() + h.cos().sum()).backward()
        grads.append([y.detach(), h.detach(), *(leaves[i].grad for i in (0, 1, 2, 3, 4, 6))])  # not cu
    for a, b in zip(*grads, strict=True):
        torch.testing.assert_close(b, a, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("chunk_size", [4, 32])
def test_shared_decay_equals_the_decay_repeated_per_state(chunk_size):
    """A (D, 1) (one decay per channel, broadcast over N) against the same decay written out as (D, N)."""
    u, delta, A, B, C, cu, h0 = _inputs([31, 0, 70, 5], seed=11)
    shared = A[:, :1]  # (D, 1)
    y_ref, h_ref = selective_scan_ref(u, delta, shared.expand_as(A).contiguous(), B, C, cu, h0)
    for impl in CPU_IMPLS:
        y, h = selective_scan(u, delta, shared, B, C, cu, h0, impl=impl, chunk_size=chunk_size)
        torch.testing.assert_close(y, y_ref, rtol=1e-10, atol=1e-10)
        torch.testing.assert_close(h, h_ref, rtol=1e-10, atol=1e-10)
    with pytest.raises(ValueError, match="expected"):
        selective_scan_ref(u, delta, A[:, :2], B, C, cu, h0)  # neither (D, N) nor (D, 1)


@pytest.mark.parametrize("chunk_size", [8, 32])
def test_chunked_float32_matches_float64_reference(chunk_size):
    args64 = _inputs([200, 33, 1, 0, 64, 90], D=16, N=8, seed=3)
    args32 = [a.float() if a is not None and a.is_floating_point() else a for a in args64]
    y_ref, h_ref = selective_scan_ref(*args64)
    y, h = selective_scan_chunked(*args32, chunk_size=chunk_size)
    assert y.dtype == torch.float32 and h.dtype == torch.float32
    torch.testing.assert_close(y.double(), y_ref, rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(h.double(), h_ref, rtol=1e-4, atol=1e-4)


def test_half_inputs_computed_in_float32():
    args = [a.float() if a is not None and a.is_floating_point() else a for a in _inputs([40, 9], seed=4)]
    y32, h32 = selective_scan_chunked(*args, chunk_size=8)
    half = [a.half() if a is not None and a.is_floating_point() else a for a in args]
    y16, h16 = selective_scan_chunked(*half, chunk_size=8)
    assert y16.dtype == torch.float16 and h16.dtype == torch.float32
    y_ref = selective_scan_ref(*half)[0]
    torch.testing.assert_close(y16, y_ref, rtol=1e-3, atol=1e-3)
    torch.testing.assert_close(y16.float(), y32, rtol=2e-2, atol=2e-2)
    torch.testing.assert_close(h16, h32, rtol=2e-2, atol=2e-2)


@pytest.mark.parametrize("with_h0", [False, True])
def test_chunked_gradients_match_reference(with_h0):
    args = _inputs([9, 0, 20, 1, 8], D=3, N=2, with_h0=with_h0, seed=5)
    grads = []
    for fn in (selective_scan_ref, lambda *a: selective_scan_chunked(*a, chunk_size=4)):
        leaves = [a.clone().requires_grad_() if a is not None and a.is_floating_point() else a for a in args]
        y, h = fn(*leaves)
        w_y = torch.linspace(-1, 1, y.numel(), dtype=y.dtype).view_as(y)
        w_h = torch.linspace(1, 2, h.numel(), dtype=h.dtype).view_as(h)
        ((y * w_y).sum() + (h * w_h).sum()).backward()
        grads.append([a.grad for a in leaves if a is not None and a.is_floating_point()])
    for g_ref, g in zip(*grads, strict=True):
        assert g_ref is not None and g_ref.abs().sum() > 0
        torch.testing.assert_close(g, g_ref, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("impl", CPU_IMPLS)
@pytest.mark.parametrize("cut", [1, 31, 32, 33, 100])
def test_split_with_carried_state_equals_one_call(impl, cut):
    u, delta, A, B, C, _, h0 = _inputs([150, 70], seed=6)
    y_full, h_full = selective_scan(u, delta, A, B, C, _cu([150, 70]), h0, impl=impl, chunk_size=32)
    # first call: the first `cut` tokens of both sequences (at most 69 of the second one); second call: the
    # rest, from the carried state
    c2 = min(cut, 69)
    first = torch.cat([torch.arange(cut), 150 + torch.arange(c2)])
    rest = torch.cat([torch.arange(cut, 150), 150 + torch.arange(c2, 70)])
    y1, h1 = selective_scan(u[first], delta[first], A, B[first], C[first], _cu([cut, c2]), h0, impl)
    y2, h2 = selective_scan(u[rest], delta[rest], A, B[rest], C[rest], _cu([150 - cut, 70 - c2]), h1, impl)
    y = torch.empty_like(y_full)
    y[first], y[rest] = y1, y2
    torch.testing.assert_close(y, y_full, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(h2, h_full, rtol=1e-10, atol=1e-10)


def test_stable_for_strong_decay():
    u, delta, A, B, C, cu, h0 = _inputs([70, 3], seed=7)
    delta = delta * 200  # delta * A down to about -500: exp would overflow for positive arguments
    y, h = selective_scan_chunked(u, delta, A, B, C, cu, h0, chunk_size=16)
    y_ref, h_ref = selective_scan_ref(u, delta, A, B, C, cu, h0)
    assert torch.isfinite(y).all() and torch.isfinite(h).all()
    torch.testing.assert_close(y, y_ref, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(h, h_ref, rtol=1e-10, atol=1e-10)


def test_no_sequences_and_all_empty():
    for lengths in ([], [0, 0]):
        u, delta, A, B, C, cu, h0 = _inputs(lengths, seed=8)
        for impl in CPU_IMPLS:
            y, h = selective_scan(u, delta, A, B, C, cu, h0, impl=impl)
            assert y.shape == (0, 5) and torch.equal(h, h0)


def test_invalid_inputs_raise():
    u, delta, A, B, C, _, _ = _inputs([4, 4], seed=9)
    with pytest.raises(ValueError, match="cu_seqlens"):
        selective_scan_chunked(u, delta, A, B, C, torch.tensor([0, 5, 7]))
    with pytest.raises(ValueError, match="cu_seqlens"):
        selective_scan_ref(u, delta, A, B, C, torch.tensor([0, 5, 4, 8]))
    with pytest.raises(ValueError, match="shapes"):
        selective_scan_chunked(u, delta[:, :3], A, B, C, _cu([4, 4]))
    with pytest.raises(ValueError, match="h0"):
        selective_scan_chunked(u, delta, A, B, C, _cu([4, 4]), torch.zeros(3, 5, 3, dtype=u.dtype))


def test_triton_needs_cuda_and_a_c_compiler(monkeypatch, tmp_path):
    monkeypatch.delenv("CC", raising=False)
    monkeypatch.setenv("PATH", str(tmp_path))  # no gcc, no clang
    assert not runtime.has_c_compiler()
    monkeypatch.setenv("CC", sys.executable)  # any executable stands in for one
    assert runtime.has_c_compiler()
    assert not runtime.triton_available(torch.device("cpu"))


def test_dispatch_logs_once_and_rejects_unavailable(monkeypatch, caplog):
    args = _inputs([5, 6], seed=10)
    monkeypatch.setattr(scan, "_announced", set())
    with caplog.at_level(logging.INFO, logger="model.ops.scan"):
        for impl in (ScanImpl.AUTO, ScanImpl.NUMBA):  # AUTO on the CPU is the numba scan
            y_c, _ = selective_scan(*args, impl=impl)
        y_r, _ = selective_scan(*args, impl=ScanImpl.REFERENCE)
    messages = [r.getMessage() for r in caplog.records if r.name == "model.ops.scan"]
    assert messages == ["selective scan implementation: numba", "selective scan implementation: reference"]
    torch.testing.assert_close(y_c, y_r, rtol=1e-10, atol=1e-10)
    with pytest.raises(RuntimeError, match="'triton' is not available on cpu"):  # asked for, so no fallback
        selective_scan(*args, impl=ScanImpl.TRITON)
    assert resolve_scan(ScanImpl.AUTO, torch.device("meta")) is ScanImpl.CHUNKED  # neither kernel there
    assert not scan_available(ScanImpl.NUMBA, torch.device("meta"))
