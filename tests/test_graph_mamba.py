"""Fixed-shape Mamba (model.graph) against the eager layer: segmented scan, frustum packs, streams with
carried state, padding isolation and a fullgraph torch.compile run."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch
from torch import Tensor

from model.config import BackboneConfig, MambaConfig, ScanImpl
from model.geometry.sparse_tensor import SparseTensor, linear_key
from model.graph.segments import frustum_segments, stream_segments
from model.layers.mamba import Mamba, MambaState, Packing
from model.layers.phim_block import LocalPackings, PHiMBlock, frustum_cu_seqlens, reversed_cu_seqlens
from model.ops.scan_numba import selective_scan_numba
from model.ops.scan_torch import selective_scan_chunked, selective_scan_ref
from model.ops.segments import Segments

CFG = MambaConfig(d_state=4, d_conv=4, expand=2, chunk_size=8, scan=ScanImpl.REFERENCE)
LENGTHS = [5, 0, 1, 2, 37, 3, 0, 11]  # per stream: empty, 1, 2, < d_conv - 1 and longer than a chunk
PAD = 9
TOL = {"rtol": 1e-5, "atol": 1e-5}


def _cu(lengths: list[int]) -> Tensor:
    return torch.tensor([0, *lengths], dtype=torch.int64).cumsum(0)


def _stream_pack(lengths: list[int], pad: int) -> tuple[Tensor, Tensor]:
    """Batch ids (T,) sorted with `pad` garbage-id padding rows at the end, valid (T,)."""
    S = len(lengths)
    real = torch.repeat_interleave(torch.arange(S), torch.tensor(lengths))  # (T0,)
    batch = torch.cat([real, torch.randint(0, S, (pad,))])  # (T,)
    valid = torch.arange(batch.numel()) < real.numel()  # (T,)
    return batch, valid


def _layer(d_model: int, shared_decay: bool, **kw) -> Mamba:
    return Mamba(d_model, replace(CFG, shared_decay=shared_decay, **kw))


def _run(m: Mamba, x: Tensor, segs: Segments, state: MambaState | None = None) -> tuple[Tensor, MambaState]:
    """The layer over a segmented pack, as the fixed-shape step runs it."""
    return m(x, Packing.of_segments(segs, m.cfg.d_conv, ScanImpl.AUTO), state)


def _random_state(m: Mamba, S: int) -> MambaState:
    k, n = m.cfg.d_conv, m.cfg.d_state
    return MambaState(conv=torch.randn(S, m.d_inner, k - 1), ssm=torch.randn(S, m.d_inner, n))


def test_stream_segments_flags():
    batch, valid = _stream_pack(LENGTHS, PAD)
    segs = stream_segments(batch, valid, len(LENGTHS))
    cu = _cu(LENGTHS)
    expect_start = torch.zeros(batch.numel(), dtype=torch.bool)
    expect_start[cu[:-1][torch.tensor(LENGTHS) > 0]] = True
    expect_start[~valid] = True
    assert torch.equal(segs.start, expect_start)
    assert torch.equal(segs.last, torch.where(torch.tensor(LENGTHS) > 0, cu[1:] - 1, -1))
    assert torch.equal(segs.seg[valid], batch[valid])


@pytest.mark.parametrize("shared_decay", [False, True])
@pytest.mark.parametrize("with_h0", [False, True])
@pytest.mark.parametrize("chunk_size", [1, 4, 16, 64])
def test_segmented_scan_matches_reference(shared_decay: bool, with_h0: bool, chunk_size: int):
    S, D, N = len(LENGTHS), 3, 4
    batch, valid = _stream_pack(LENGTHS, PAD)
    T, T0 = batch.numel(), int(valid.sum())
    segs = stream_segments(batch, valid, S)
    f64 = {"dtype": torch.float64}
    u, B, C = torch.randn(T, D, **f64), torch.randn(T, N, **f64), torch.randn(T, N, **f64)
    delta = torch.rand(T, D, **f64)
    delta[~valid] = -50.0  # garbage padding: exp(delta A) would overflow there
    A = -torch.rand(D, 1 if shared_decay else N, **f64) * 4
    h0 = torch.randn(S, D, N, **f64) if with_h0 else None
    y, final = selective_scan_chunked(u, delta, A, B, C, segs, h0, chunk_size)
    cu = _cu(LENGTHS)
    y_ref, final_ref = selective_scan_ref(u[:T0], delta[:T0], A, B[:T0], C[:T0], cu, h0)
    torch.testing.assert_close(y[:T0], y_ref, rtol=1e-12, atol=1e-12)
    assert torch.equal(y[T0:], torch.zeros_like(y[T0:]))
    torch.testing.assert_close(final, final_ref, rtol=1e-12, atol=1e-12)  # from zeros without h0
    y_seg, final_seg = selective_scan_ref(u, delta, A, B, C, segs, h0)  # the reference on the pack itself
    torch.testing.assert_close(y, y_seg, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(final, final_seg, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("shared_decay", [False, True])
@pytest.mark.parametrize("with_h0", [False, True])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_cpu_kernel_matches_torch_twin(shared_decay: bool, with_h0: bool, dtype: torch.dtype):
    """The CPU kernel (numba, `model.ops.scan_numba`) against the chunked twin, streams and padding."""
    S, D, N = len(LENGTHS), 5, 4
    batch, valid = _stream_pack(LENGTHS, PAD)
    T = batch.numel()
    segs = stream_segments(batch, valid, S)
    u, B, C = torch.randn(T, D, dtype=dtype), torch.randn(T, N, dtype=dtype), torch.randn(T, N, dtype=dtype)
    delta = torch.rand(T, D, dtype=dtype)
    delta[~valid] = -50.0
    A = -torch.rand(D, 1 if shared_decay else N, dtype=dtype) * 4
    h0 = torch.randn(S, D, N, dtype=dtype) if with_h0 else None
    y_ref, final_ref = selective_scan_chunked(u, delta, A, B, C, segs, h0, 4)
    y, final = selective_scan_numba(u, delta, A, B, C, segs, h0)
    tol = {"rtol": 1e-12, "atol": 1e-12} if dtype == torch.float64 else {"rtol": 1e-5, "atol": 1e-5}
    assert y.dtype == dtype
    torch.testing.assert_close(y, y_ref, **tol)
    assert torch.equal(y[~valid], torch.zeros_like(y[~valid]))
    torch.testing.assert_close(final, final_ref, **tol)  # from zeros without h0


def test_segmented_scan_gradients_match_reference():
    """The autograd path (no in-place accumulation) gives the reference's gradients."""
    S, D, N = len(LENGTHS), 3, 2
    batch, valid = _stream_pack(LENGTHS, PAD)
    T, T0 = batch.numel(), int(valid.sum())
    segs = stream_segments(batch, valid, S)
    f64 = {"dtype": torch.float64}
    u, delta = torch.randn(T, D, **f64), torch.rand(T, D, **f64)
    A, h0 = -torch.rand(D, N, **f64), torch.randn(S, D, N, **f64)
    B, C = torch.randn(T, N, **f64), torch.randn(T, N, **f64)
    leaves = [t.requires_grad_() for t in (u, delta, A, h0)]
    y_ref, final_ref = selective_scan_ref(u[:T0], delta[:T0], A, B[:T0], C[:T0], _cu(LENGTHS), h0)
    grads_ref = torch.autograd.grad(y_ref.sum() + final_ref.square().sum(), leaves)
    for scan in (
        lambda *a: selective_scan_chunked(*a, 8),
        selective_scan_numba,
    ):  # numba: its backward kernel
        y, final = scan(u, delta, A, B, C, segs, h0)
        grads = torch.autograd.grad(y.sum() + final.square().sum(), leaves)
        for g, g_ref in zip(grads, grads_ref, strict=True):
            torch.testing.assert_close(g, g_ref, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("shared_decay", [False, True])
@pytest.mark.parametrize("impl", [ScanImpl.REFERENCE, ScanImpl.CHUNKED])
def test_stream_pack_with_state_matches_eager(shared_decay: bool, impl: ScanImpl):
    S = len(LENGTHS)
    m = _layer(16, shared_decay, scan=impl)
    batch, valid = _stream_pack(LENGTHS, PAD)
    T0 = int(valid.sum())
    x = torch.randn(batch.numel(), 16)
    x[~valid] = 100.0 * torch.randn(PAD, 16)  # garbage-but-finite padding
    state = _random_state(m, S)
    with torch.no_grad():
        y_ref, state_ref = m(x[:T0], _cu(LENGTHS), state)
        y, new = _run(m, x, stream_segments(batch, valid, S), state)
    assert torch.isfinite(y).all()
    torch.testing.assert_close(y[:T0], y_ref, **TOL)
    torch.testing.assert_close(new.conv, state_ref.conv, **TOL)
    torch.testing.assert_close(new.ssm, state_ref.ssm, **TOL)
    # empty streams keep their state exactly
    empty = torch.tensor(LENGTHS) == 0
    assert torch.equal(new.conv[empty], state.conv[empty]) and torch.equal(new.ssm[empty], state.ssm[empty])


def test_stream_pack_without_state_matches_eager():
    m = _layer(8, False)
    batch, valid = _stream_pack(LENGTHS, PAD)
    T0 = int(valid.sum())
    x = torch.randn(batch.numel(), 8)
    with torch.no_grad():
        y_ref, state_ref = m(x[:T0], _cu(LENGTHS))
        y, new = _run(m, x, stream_segments(batch, valid, len(LENGTHS)))
    torch.testing.assert_close(y[:T0], y_ref, **TOL)
    torch.testing.assert_close(new.ssm, state_ref.ssm, **TOL)


def _sites(spatial_shape: tuple[int, int, int], pad: int) -> tuple[Tensor, Tensor, int]:
    """Sorted random sites of 4 sectors (one empty; one with frustums of 1, 2 and 3 sites) + padding rows.

    Returns coords (T, 4) int64, valid (T,), number of real rows."""
    n_r, n_t, n_z = spatial_shape
    grid = torch.stack(torch.meshgrid(torch.arange(n_r), torch.arange(n_t), torch.arange(n_z), indexing="ij"))
    grid = grid.reshape(3, -1).t()  # (R * THETA * Z, 3)
    parts = []
    for b, density in [(0, 0.3), (2, 0.05)]:
        keep = grid[torch.rand(grid.shape[0]) < density]
        parts.append(torch.cat([torch.full((keep.shape[0], 1), b), keep], 1))
    manual = [[0, 1, 0], [1, 9, 2], [3, 10, 0], [0, 18, 1], [2, 18, 2], [5, 19, 0]]  # (r, theta, z)
    parts.append(torch.cat([torch.full((6, 1), 3), torch.tensor(manual)], 1))
    coords = torch.cat(parts)  # (T0, 4)
    coords = coords[linear_key(coords, spatial_shape).argsort()]
    garbage = torch.cat([torch.randint(0, 4, (pad, 1)), torch.randint(0, n_t, (pad, 3))], 1)
    garbage[0] = coords[-1]  # a padding row that repeats the last real site must still start a segment
    valid = torch.arange(coords.shape[0] + pad) < coords.shape[0]
    return torch.cat([coords, garbage]), valid, coords.shape[0]


@pytest.mark.parametrize("shared_decay", [False, True])
def test_frustum_packs_match_local_block(shared_decay: bool):
    cfg = BackboneConfig(d_model=16, frustum_theta_bins=9, mamba=replace(CFG, shared_decay=shared_decay))
    block = PHiMBlock(cfg, kernel=3, stride=1)
    shape = (6, 20, 3)
    coords, valid, T0 = _sites(shape, PAD)
    feats = torch.randn(coords.shape[0], 16)
    feats[~valid] = 50.0 * torch.randn(PAD, 16)
    x = SparseTensor(feats[:T0], coords[:T0], shape, 4)
    fwd_segs, bwd_segs = frustum_segments(coords, valid, shape[1], cfg.frustum_theta_bins)
    cu = frustum_cu_seqlens(x, cfg.frustum_theta_bins)
    assert torch.equal(fwd_segs.start[:T0].nonzero()[:, 0], cu[:-1])
    assert torch.equal(bwd_segs.start[PAD:].nonzero()[:, 0], reversed_cu_seqlens(cu)[:-1])
    assert bool((cu.diff() == 1).any()) and bool((cu.diff() == 2).any())
    assert fwd_segs.start[~valid].all() and bwd_segs.start[:PAD].all()  # every padding row starts one
    with torch.no_grad():
        ref = block.local(x, block.local_packings(x))  # (T0, 16)
        d_conv = cfg.mamba.d_conv
        packs = (Packing.of_segments(s, d_conv, ScanImpl.AUTO) for s in (fwd_segs, bwd_segs))
        out = block.local(feats, LocalPackings(*packs))  # (T, 16)
    assert torch.isfinite(out).all()
    torch.testing.assert_close(out[:T0], ref, **TOL)


def _run_both_packs(m: Mamba, x: Tensor, segs: Segments, state: MambaState) -> list[Tensor]:
    y, new = _run(m, x, segs, state)
    return [y, new.conv, new.ssm]


def test_padding_rows_change_no_valid_output():
    S = len(LENGTHS)
    m = _layer(8, True)
    batch, valid = _stream_pack(LENGTHS, PAD)
    T0 = int(valid.sum())
    state = _random_state(m, S)
    x1 = torch.randn(batch.numel(), 8)
    x2 = x1.clone()
    x2[~valid] = 1e3 * torch.randn(PAD, 8)
    batch2 = batch.clone()
    batch2[~valid] = (batch2[~valid] + 3) % S
    with torch.no_grad():
        a = _run_both_packs(m, x1, stream_segments(batch, valid, S), state)
        b = _run_both_packs(m, x2, stream_segments(batch2, valid, S), state)
        # the backward pack: padding first
        _, bwd = frustum_segments(torch.zeros(batch.numel(), 4, dtype=torch.int64), valid, 1, 1)
        c, _ = _run(m, x1.flip(0), bwd)
        d, _ = _run(m, x2.flip(0), bwd)
    assert not torch.equal(a[0][T0:], b[0][T0:])  # the padding inputs did differ
    assert torch.equal(a[0][:T0], b[0][:T0])
    assert torch.equal(a[1], b[1]) and torch.equal(a[2], b[2])
    assert torch.isfinite(d).all()
    assert torch.equal(c[PAD:], d[PAD:])


# torch's inductor imports a module that warns about its own use of torch.jit (torch 2.13)
def test_compiled_stream_step_equals_eager():
    S, T, d = 6, 256, 16
    m = _layer(d, True, chunk_size=32)
    lengths = [60, 0, 1, 2, 100, 40]
    batch, valid = _stream_pack(lengths, T - sum(lengths))
    x = torch.randn(T, d)
    state = _random_state(m, S)

    def step(x: Tensor, batch: Tensor, valid: Tensor, conv: Tensor, ssm: Tensor) -> tuple[Tensor, ...]:
        y, new = _run(m, x, stream_segments(batch, valid, S), MambaState(conv, ssm))
        return y, new.conv, new.ssm

    compiled = torch.compile(step, fullgraph=True, dynamic=False)
    with torch.no_grad():
        expect = step(x, batch, valid, state.conv, state.ssm)
        got = compiled(x, batch, valid, state.conv, state.ssm)
    for e, g in zip(expect, got, strict=True):
        torch.testing.assert_close(g, e, **TOL)
