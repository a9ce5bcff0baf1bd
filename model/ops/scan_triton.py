"""The selective scan as three Triton kernels (CUDA): the fast twin of `model.ops.scan_torch` (same contract,
see its docstring), a torch custom op (`phim::scan_triton`) that torch.compile calls as one opaque op.

The chunked twin materialises the decays and inputs of every token and state, (T, N, D) tensors several
times over (a paper-config pack of 16k tokens: ~270 MB each, per scan); here nothing that size exists:

1. `_chunk_kernel` (one program per chunk of K tokens x channel block): scan the chunk from zero state,
   honouring the segment starts (a start continues its stream's carried state h0[seg], or zero), and keep
   the chunk's final state and the product of its decays since its last start (0 when it holds one).
2. `_carry_kernel` (one program per channel block): walk the chunks in order, writing the state entering
   each (the whole pack is one linear recurrence once the starts are folded in, as in the reference).
3. `_chunk_kernel` again from each chunk's entering state, writing y (zero on padding) and the final state
   of every stream at its last token.

Fixed shapes and no host synchronisation: the grid follows from T alone, so the op can run inside a
captured CUDA graph. float32 compute (`model.ops.scan` runs float64 inputs on the chunked twin). Backward:
recomputed through `selective_scan_chunked` under autograd, so training runs on this path with the chunked
path's backward cost.
"""

from __future__ import annotations

import torch
import triton
import triton.language as tl
from torch import Tensor

from model.ops.scan_torch import check_inputs, selective_scan_chunked
from model.ops.segments import Segments
from model.ops.triton_support import grads_by_recompute

MAX_CHUNKS = 512  # the carry kernel walks the chunks one by one: the chunk grows with T to keep this bound


@triton.jit
def _chunk_kernel(
    u_ptr, delta_ptr, a_ptr, b_ptr, c_ptr,  # (T, D), (T, D), (D, N), (T, N), (T, N)
    start_ptr, valid_ptr, seg_ptr, last_ptr, h0_ptr,  # (T,) x 3 int8/int64, (S,), (S, D, N) (HAS_H0)
    h_in_ptr, y_ptr, final_ptr,  # (NC, D, N) entering states, (T, D), (S, D, N) (FROM_STATE)
    fin_ptr, prod_ptr,  # (NC, D, N) local final states and decay products (not FROM_STATE)
    T, D, N, K,
    BLOCK_D: tl.constexpr, BLOCK_N: tl.constexpr, HAS_H0: tl.constexpr, FROM_STATE: tl.constexpr,
):  # fmt: skip
    c = tl.program_id(0).to(tl.int64)
    d = tl.program_id(1) * BLOCK_D + tl.arange(0, BLOCK_D)  # (BD,)
    n = tl.arange(0, BLOCK_N)  # (BN,)
    dm, nm = d < D, n < N
    dn = d[:, None] * N + n[None, :]  # (BD, BN) offsets into a (D, N) state
    m2 = dm[:, None] & nm[None, :]
    a = tl.load(a_ptr + dn, mask=m2, other=0.0)
    if FROM_STATE:
        h = tl.load(h_in_ptr + c * D * N + dn, mask=m2, other=0.0)
    else:
        h = tl.zeros((BLOCK_D, BLOCK_N), dtype=tl.float32)
    prod = tl.full((BLOCK_D, BLOCK_N), 1.0, dtype=tl.float32)
    zero = tl.zeros((BLOCK_D,), dtype=tl.int64)  # per-token values as (BD,) vectors (interpreter-safe)
    for i in range(0, K):
        t = c * K + i + zero  # (BD,)
        inside = t < T
        st = tl.load(start_ptr + t, mask=inside, other=0) != 0  # (BD,)
        ok = tl.load(valid_ptr + t, mask=inside, other=0) != 0  # padding: delta 0, so h passes unchanged
        dt = tl.load(delta_ptr + t * D + d, mask=dm & ok, other=0.0)  # (BD,)
        x = tl.load(u_ptr + t * D + d, mask=dm & ok, other=0.0)  # (BD,)
        b = tl.load(b_ptr + t[:, None] * N + n[None, :], mask=nm[None, :] & inside[:, None], other=0.0)
        e = tl.exp(dt[:, None] * a)  # (BD, BN)
        s = tl.load(seg_ptr + t, mask=inside, other=0)  # (BD,)
        if HAS_H0:  # a start continues its stream's carried state (read only where st)
            carried = tl.load(h0_ptr + s[:, None] * D * N + dn, mask=m2 & st[:, None], other=0.0)
        else:
            carried = tl.zeros((BLOCK_D, BLOCK_N), dtype=tl.float32)
        h_new = e * tl.where(st[:, None], carried, h) + (dt * x)[:, None] * b
        h = tl.where(inside[:, None], h_new, h)
        prod = tl.where(inside[:, None], tl.where(st[:, None], 0.0, prod * e), prod)
        if FROM_STATE:
            cc = tl.load(c_ptr + t[:, None] * N + n[None, :], mask=nm[None, :] & inside[:, None], other=0.0)
            y = tl.where(ok, tl.sum(h * cc, axis=1), 0.0)  # (BD,)
            tl.store(y_ptr + t * D + d, y, mask=dm & inside)
            if HAS_H0:  # the stream's last token: its final state
                is_last = tl.load(last_ptr + s, mask=inside & ok, other=-1) == t  # (BD,)
                tl.store(final_ptr + s[:, None] * D * N + dn, h, mask=m2 & is_last[:, None])
    if not FROM_STATE:
        tl.store(fin_ptr + c * D * N + dn, h, mask=m2)
        tl.store(prod_ptr + c * D * N + dn, prod, mask=m2)


@triton.jit
def _carry_kernel(
    fin_ptr, prod_ptr, h_in_ptr,  # (NC, D, N) each
    NC, DN,
    BLOCK: tl.constexpr,
):  # fmt: skip
    j = (tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)).to(tl.int64)  # (BLOCK,) flat (D, N) offsets
    m = j < DN
    h = tl.zeros((BLOCK,), dtype=tl.float32)
    for c in range(0, NC):
        off = c * DN + j
        tl.store(h_in_ptr + off, h, mask=m)
        h = tl.load(prod_ptr + off, mask=m, other=0.0) * h + tl.load(fin_ptr + off, mask=m, other=0.0)


def chunk_length(tokens: int) -> int:
    """Tokens per chunk: 64, doubled until the pack has at most MAX_CHUNKS chunks."""
    k = 64
    while -(-tokens // k) > MAX_CHUNKS:
        k *= 2
    return k


@torch.library.custom_op("phim::scan_triton", mutates_args=())  # any device: the interpreter runs on CPU
def _scan(
    u: Tensor,
    delta: Tensor,
    A: Tensor,
    B: Tensor,
    C: Tensor,
    h0: Tensor,
    start: Tensor,
    valid: Tensor,
    seg: Tensor,
    last: Tensor,
) -> tuple[Tensor, Tensor]:
    """float32 contiguous u, delta (T, D), A (D, N), B, C (T, N), h0 (S, D, N) and the pack's flags (int8
    start and valid, int64 seg and last) -> y (T, D), final (S, D, N)."""
    T, D = u.shape
    N = B.shape[1]
    k = chunk_length(T)
    nc = max(-(-T // k), 1)
    y = torch.empty(T, D, device=u.device)
    final = h0.clone()
    fin, prod, h_in = (torch.empty(nc, D, N, device=u.device) for _ in range(3))
    block_n = triton.next_power_of_2(N)
    block_d = max(1, min(triton.next_power_of_2(D), 512 // block_n))  # about 512 state values per program
    grid = (nc, triton.cdiv(D, block_d))
    common = dict(BLOCK_D=block_d, BLOCK_N=block_n, HAS_H0=h0.shape[0] > 0, num_warps=2)
    args = (u, delta, A, B, C, start, valid, seg, last, h0, h_in, y, final, fin, prod, T, D, N, k)
    if T:
        _chunk_kernel[grid](*args, FROM_STATE=False, **common)
        _carry_kernel[(triton.cdiv(D * N, 256),)](fin, prod, h_in, nc, D * N, BLOCK=256)
        _chunk_kernel[grid](*args, FROM_STATE=True, **common)
    return y, final


@_scan.register_fake
def _(u, delta, A, B, C, h0, start, valid, seg, last):
    return torch.empty_like(u), torch.empty_like(h0)


def _setup(ctx, inputs, output) -> None:
    ctx.save_for_backward(*inputs)


def _grads(ctx, dy, dfinal):
    u, delta, A, B, C, h0, start, valid, seg, last = ctx.saved_tensors
    segs = Segments(start.bool(), valid.bool(), seg, last)

    def twin(u, delta, A, B, C, h0):
        return selective_scan_chunked(u, delta, A, B, C, segs, h0)

    dy = torch.zeros_like(u) if dy is None else dy
    dfinal = torch.zeros_like(h0) if dfinal is None else dfinal
    return (*grads_by_recompute(twin, (u, delta, A, B, C, h0), (dy, dfinal)), None, None, None, None)


_scan.register_autograd(_grads, setup_context=_setup)


def selective_scan_triton(
    u: Tensor,
    delta: Tensor,
    A: Tensor,
    B: Tensor,
    C: Tensor,
    seqs: Tensor | Segments,
    h0: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """`selective_scan_ref`'s contract on CUDA tensors, float32 compute: y (T, D) in u's dtype and the final
    states (S, D, N) float32 (h0[s], or zeros, for a stream without tokens)."""
    segs = check_inputs(u, delta, A, B, C, seqs, h0)
    D = u.shape[1]
    N, S = B.shape[1], segs.num_streams
    f32 = [t.float().contiguous() for t in (u, delta, A.expand(D, N), B, C)]
    h_init = u.new_zeros(S, D, N, dtype=torch.float32) if h0 is None else h0.float().contiguous()
    flags = [
        t.contiguous() for t in (segs.start.to(torch.int8), segs.valid.to(torch.int8), segs.seg, segs.last)
    ]
    y, final = _scan(*f32, h_init, *flags)
    return y.to(u.dtype), final
