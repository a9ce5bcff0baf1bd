"""Mamba layer: packed calls against a naive per-sequence implementation, carried state, gradients."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch
import torch.nn.functional as F
from test_scan import CPU_IMPLS

from model.config import MambaConfig, ScanImpl
from model.layers.mamba import Mamba, MambaState, Packing, conv_gather_indices
from model.ops.scan_torch import selective_scan_ref
from model.ops.segments import Segments

CFG = MambaConfig(d_state=4, d_conv=4, expand=2, chunk_size=8)


def _cu(lengths: list[int]) -> torch.Tensor:
    return torch.tensor([0, *lengths], dtype=torch.int64).cumsum(0)


def _layer(impl: ScanImpl = ScanImpl.CHUNKED, d_model: int = 8, seed: int = 0, **kw) -> Mamba:
    torch.manual_seed(seed)
    return Mamba(d_model, replace(CFG, scan=impl, **kw)).double()


def _naive(m: Mamba, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One sequence from zero state, the mamba_simple way (F.conv1d with left padding, sequential scan).

    Returns (y (L, d_model), conv input xi (L, d_inner), final ssm state (d_inner, d_state)).
    """
    L, k = x.shape[0], m.cfg.d_conv
    xi, z = m.in_proj(x).chunk(2, dim=-1)
    xc = F.conv1d(xi.t()[None], m.conv1d.weight, m.conv1d.bias, padding=k - 1, groups=m.d_inner)[0, :, :L]
    xc = F.silu(xc.t())  # (L, d_inner)
    dt, B, C = m.x_proj(xc).split([m.dt_rank, m.cfg.d_state, m.cfg.d_state], dim=-1)
    delta = F.softplus(m.dt_proj(dt))
    y, h = selective_scan_ref(xc, delta, -torch.exp(m.A_log.double()), B, C, _cu([L]))
    y = (y + xc * m.D) * F.silu(z)
    return m.out_proj(y), xi, h[0]


@pytest.mark.parametrize("impl", CPU_IMPLS)
def test_packed_call_equals_naive_per_sequence(impl):
    m = _layer(impl)
    lengths = [7, 0, 1, 2, 13, 40]
    cu = _cu(lengths)
    x = torch.randn(sum(lengths), 8, dtype=torch.float64)
    with torch.no_grad():
        y, state = m(x, cu)
        for s, L in enumerate(lengths):
            if L == 0:
                assert (state.ssm[s] == 0).all() and (state.conv[s] == 0).all()
                continue
            xs = x[cu[s] : cu[s + 1]]
            y_ref, xi, h = _naive(m, xs)
            torch.testing.assert_close(y[cu[s] : cu[s + 1]], y_ref, rtol=1e-10, atol=1e-10)
            torch.testing.assert_close(state.ssm[s], h, rtol=1e-10, atol=1e-10)
            last = torch.cat([xi.new_zeros(3, m.d_inner), xi])[
                -3:
            ]  # (3, d_inner) last conv inputs, zero-padded
            torch.testing.assert_close(state.conv[s], last.t(), rtol=1e-12, atol=1e-12)


PIECES = [(1,), (2,), (1, 2), (2, 1), (3, 0, 1), (1, 1, 1), (17, 5)]


@pytest.mark.parametrize("impl", CPU_IMPLS)
@pytest.mark.parametrize("pieces", PIECES)
@pytest.mark.parametrize("shared_decay", [False, True])
def test_pieces_with_carried_state_equal_one_call(impl, pieces, shared_decay):
    """Two sequences (30 and 9 tokens) fed piece by piece; piece lengths as given, the rest in a last call."""
    m = _layer(impl, seed=1, shared_decay=shared_decay)
    lengths = [30, 9]
    x = torch.randn(sum(lengths), 8, dtype=torch.float64)
    with torch.no_grad():
        y_full, s_full = m(x, _cu(lengths))
        state, done, outs = None, [0, 0], torch.empty_like(y_full)
        for p in [*pieces, None]:
            take = [L - d if p is None else min(p, L - d) for L, d in zip(lengths, done, strict=True)]
            idx = torch.cat(
                [torch.arange(o + d, o + d + t) for o, d, t in zip((0, 30), done, take, strict=True)]
            )
            y, state = m(x[idx], _cu(take), state)
            outs[idx] = y
            done = [d + t for d, t in zip(done, take, strict=True)]
    torch.testing.assert_close(outs, y_full, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(state.ssm, s_full.ssm, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(state.conv, s_full.conv, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("impl", [ScanImpl.CHUNKED, ScanImpl.NUMBA])
@pytest.mark.parametrize("shared_decay", [False, True])
def test_fast_scan_layers_agree_with_the_reference_in_outputs_and_gradients(impl, shared_decay):
    lengths = [50, 3, 0, 17, 1, 33]
    cu = _cu(lengths)
    x = torch.randn(sum(lengths), 8, dtype=torch.float64)
    layers = [
        _layer(ScanImpl.REFERENCE, seed=2, shared_decay=shared_decay),
        _layer(impl, seed=2, shared_decay=shared_decay),
    ]
    assert layers[0].A_log.shape == ((16, 1) if shared_decay else (16, 4))
    init = MambaState(
        conv=torch.randn(6, 16, 3, dtype=torch.float64), ssm=torch.randn(6, 16, 4, dtype=torch.float64)
    )
    results = []
    for m in layers:
        y, st = m(x, cu, init)
        (y.square().sum() + st.ssm.sum() + st.conv.sum()).backward()
        results.append((y, st, {n: p.grad for n, p in m.named_parameters()}))
    (y_r, st_r, g_r), (y_c, st_c, g_c) = results
    torch.testing.assert_close(y_c, y_r, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(st_c.ssm, st_r.ssm, rtol=1e-10, atol=1e-10)
    for name, g in g_c.items():
        assert g is not None and torch.isfinite(g).all() and g.abs().sum() > 0, name
        torch.testing.assert_close(g, g_r[name], rtol=1e-8, atol=1e-10, msg=name)


@pytest.mark.parametrize("impl", [ScanImpl.CHUNKED, ScanImpl.NUMBA])
def test_float32_backward_reaches_every_parameter(impl):
    torch.manual_seed(3)
    m = Mamba(16, MambaConfig(d_state=8, chunk_size=16, scan=impl))
    x = torch.randn(120, 16, requires_grad=True)
    y, state = m(x, _cu([70, 20, 30]))
    assert y.dtype == torch.float32 and state.ssm.dtype == torch.float32
    y.sum().backward()
    for name, p in m.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0, name
    assert x.grad is not None and x.grad.abs().sum() > 0


def test_empty_sequence_leaves_state_unchanged():
    m = _layer(seed=4)
    state = MambaState(
        conv=torch.randn(3, 16, 3, dtype=torch.float64), ssm=torch.randn(3, 16, 4, dtype=torch.float64)
    )
    x = torch.randn(7, 8, dtype=torch.float64)
    with torch.no_grad():
        _, new = m(x, _cu([5, 0, 2]), state)
    assert torch.equal(new.ssm[1], state.ssm[1]) and torch.equal(new.conv[1], state.conv[1])
    assert not torch.equal(new.ssm[0], state.ssm[0])
    # a 2-token sequence keeps the newest old conv input and appends its own two
    assert torch.equal(new.conv[2, :, 0], state.conv[2, :, 2])


def test_conv_gather_indices_hand_example():
    # sequences of 2, 0 and 4 tokens (T = 6), d_conv = 3: state rows start at 6, two per sequence
    older, new_state = conv_gather_indices(Segments.of_cu_seqlens(_cu([2, 0, 4]), 6), 3)
    # row 0: two steps back, row 1: one step back
    assert older.tolist() == [[6, 7, 10, 11, 2, 3], [7, 0, 11, 2, 3, 4]]
    assert new_state.tolist() == [[0, 1], [8, 9], [4, 5]]


def test_init_and_state_helpers():
    m = Mamba(40, MambaConfig(d_state=6))
    assert m.d_inner == 80 and m.dt_rank == math.ceil(40 / 16)
    torch.testing.assert_close(-torch.exp(m.A_log), -torch.arange(1.0, 7.0).repeat(80, 1))
    assert torch.equal(m.D, torch.ones(80))
    assert m.A_log._no_weight_decay and m.D._no_weight_decay
    dt = F.softplus(m.dt_proj.bias)
    assert dt.min() >= 0.001 * 0.999 and dt.max() <= 0.1 * 1.001
    assert m.dt_proj.weight.abs().max() <= m.dt_rank**-0.5
    z = MambaState.zeros(3, 80, 4, 6, "cpu")
    assert z.conv.shape == (3, 80, 3) and z.ssm.shape == (3, 80, 6) and z.ssm.dtype == torch.float32
    a = MambaState(conv=torch.randn(3, 2, 3), ssm=torch.randn(3, 2, 4))
    b = MambaState.cat([a, a.index(torch.tensor([2, 0]))])
    assert b.num_seqs == 5 and torch.equal(b.ssm[3], a.ssm[2]) and torch.equal(b.conv[4], a.conv[0])


def test_state_with_wrong_number_of_sequences_raises():
    m = _layer()
    with pytest.raises(ValueError, match="sequences"):
        m(
            torch.randn(4, 8, dtype=torch.float64),
            _cu([4]),
            MambaState.zeros(2, 16, 4, 4, "cpu", torch.float64),
        )


def test_a_shared_packing_gives_the_same_outputs_and_must_fit():
    m = _layer()
    x, cu = torch.randn(7, 8, dtype=torch.float64), _cu([3, 0, 4])
    packing = m.packing(cu, 7)
    y, state = m(x, packing)
    y_ref, state_ref = m(x, cu)
    assert torch.equal(y, y_ref) and torch.equal(state.conv, state_ref.conv)
    with pytest.raises(ValueError, match="packing for 7 tokens"):
        m(x[:6], packing)
    with pytest.raises(ValueError, match="d_conv"):
        m(x, Packing.of(cu, 7, m.cfg.d_conv + 1))
