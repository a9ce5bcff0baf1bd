"""Selective scan as three Triton kernels (CUDA): the fast twin of `scan_torch.selective_scan_chunked`.

Same contract and the same chunked algorithm as the chunked scan (model/ops/scan_torch.py), but each phase is
one kernel launch instead of a Python loop of small torch ops, and no step waits on the host:

1. `_chunk_kernel` (one program per chunk x channel block): scan the chunk from zero, keep its final state
   and the sum of its deltas (the chunk's decay is exp(A * sum delta)).
2. `_carry_kernel` (one program per sequence x channel block): walk the sequence's chunks in order, write
   the state entering each chunk, and the sequence's final state.
3. `_chunk_kernel` again, from each chunk's entering state, writing the outputs y.

The chunk table is computed on the device for an upper bound of T // chunk + S chunks (each sequence adds
at most one partial chunk), so the grid is known without reading cu_seqlens on the host. Unused programs
see a chunk of length 0. cu_seqlens is trusted here (the Mamba layer builds it); the reference and chunked
scans check it.

Backward: `TritonScan` recomputes with `selective_scan_chunked` under autograd, so training runs on this
path with the chunked path's backward cost.
"""

from __future__ import annotations

import torch
import triton
import triton.language as tl
from torch import Tensor

from model.ops.scan_torch import selective_scan_chunked
from model.ops.triton_support import grads_by_recompute


@triton.jit
def _chunk_kernel(
    u_ptr, delta_ptr, a_ptr, b_ptr, c_ptr,  # (T, D), (T, D), (D, N), (T, N), (T, N)
    start_ptr, len_ptr,  # (NC,) first token and length of each chunk
    h_in_ptr,  # (NC, D, N) entering states (FROM_STATE)
    y_ptr,  # (T, D) outputs (FROM_STATE)
    fin_ptr, dsum_ptr,  # (NC, D, N) local final states, (NC, D) delta sums (not FROM_STATE)
    D, N,
    BLOCK_D: tl.constexpr, BLOCK_N: tl.constexpr, FROM_STATE: tl.constexpr,
):  # fmt: skip
    c = tl.program_id(0).to(tl.int64)
    d = tl.program_id(1) * BLOCK_D + tl.arange(0, BLOCK_D)  # (BD,)
    n = tl.arange(0, BLOCK_N)  # (BN,)
    dm, nm = d < D, n < N
    dn = d[:, None] * N + n[None, :]  # (BD, BN) offsets into a (D, N) state
    m2 = dm[:, None] & nm[None, :]
    a = tl.load(a_ptr + dn, mask=m2, other=0.0)
    start = tl.load(start_ptr + c)
    length = tl.load(len_ptr + c)
    if FROM_STATE:
        h = tl.load(h_in_ptr + c * D * N + dn, mask=m2, other=0.0)
    else:
        h = tl.zeros((BLOCK_D, BLOCK_N), dtype=a.dtype)
    dsum = tl.zeros((BLOCK_D,), dtype=a.dtype)
    for t in range(0, length):
        row = start + t
        dt = tl.load(delta_ptr + row * D + d, mask=dm, other=0.0)  # (BD,)
        x = tl.load(u_ptr + row * D + d, mask=dm, other=0.0)  # (BD,)
        b = tl.load(b_ptr + row * N + n, mask=nm, other=0.0)  # (BN,)
        h = tl.exp(dt[:, None] * a) * h + (dt * x)[:, None] * b[None, :]
        if FROM_STATE:
            cc = tl.load(c_ptr + row * N + n, mask=nm, other=0.0)  # (BN,)
            tl.store(y_ptr + row * D + d, tl.sum(h * cc[None, :], axis=1), mask=dm)
        else:
            dsum += dt
    if not FROM_STATE:
        tl.store(fin_ptr + c * D * N + dn, h, mask=m2)
        tl.store(dsum_ptr + c * D + d, dsum, mask=dm)


@triton.jit
def _carry_kernel(
    a_ptr, h0_ptr,  # (D, N), (S, D, N) (HAS_H0)
    cptr_ptr,  # (S + 1,) first chunk of each sequence
    fin_ptr, dsum_ptr,  # (NC, D, N), (NC, D) from the first phase
    h_in_ptr, final_ptr,  # (NC, D, N) entering states, (S, D, N) final states
    D, N,
    BLOCK_D: tl.constexpr, BLOCK_N: tl.constexpr, HAS_H0: tl.constexpr,
):  # fmt: skip
    s = tl.program_id(0).to(tl.int64)
    d = tl.program_id(1) * BLOCK_D + tl.arange(0, BLOCK_D)
    n = tl.arange(0, BLOCK_N)
    dm, nm = d < D, n < N
    dn = d[:, None] * N + n[None, :]
    m2 = dm[:, None] & nm[None, :]
    a = tl.load(a_ptr + dn, mask=m2, other=0.0)
    if HAS_H0:
        h = tl.load(h0_ptr + s * D * N + dn, mask=m2, other=0.0)
    else:
        h = tl.zeros((BLOCK_D, BLOCK_N), dtype=a.dtype)
    first = tl.load(cptr_ptr + s)
    last = tl.load(cptr_ptr + s + 1)
    for j in range(first, last):
        tl.store(h_in_ptr + j * D * N + dn, h, mask=m2)
        ds = tl.load(dsum_ptr + j * D + d, mask=dm, other=0.0)
        h = tl.exp(ds[:, None] * a) * h + tl.load(fin_ptr + j * D * N + dn, mask=m2, other=0.0)
    tl.store(final_ptr + s * D * N + dn, h, mask=m2)


def _chunk_table(cu: Tensor, chunk: int, max_chunks: int) -> tuple[Tensor, Tensor, Tensor]:
    """Device-side chunk table: (start (NCmax,), length (NCmax,), first chunk per sequence (S + 1,))."""
    lens = cu[1:] - cu[:-1]  # (S,)
    cptr = torch.zeros_like(cu)
    torch.cumsum((lens + chunk - 1) // chunk, 0, out=cptr[1:])  # (S + 1,)
    ids = torch.arange(max_chunks, device=cu.device)  # (NCmax,)
    seq = torch.searchsorted(cptr[1:], ids, right=True).clamp_(max=lens.numel() - 1)  # (NCmax,)
    start = cu[seq] + (ids - cptr[seq]) * chunk
    length = (cu[seq + 1] - start).clamp_(0, chunk)  # 0 past the last chunk
    return start, length, cptr


def _forward(
    u: Tensor, delta: Tensor, A: Tensor, B: Tensor, C: Tensor, cu: Tensor, h0: Tensor | None, chunk: int
) -> tuple[Tensor, Tensor]:
    """The three launches; inputs already in the compute dtype, contiguous, A expanded to (D, N)."""
    T, D = u.shape
    N, S = B.shape[1], cu.numel() - 1
    max_chunks = T // chunk + S
    start, length, cptr = _chunk_table(cu.to(torch.int64), chunk, max_chunks)
    fin = u.new_empty((max_chunks, D, N))
    dsum = u.new_empty((max_chunks, D))
    h_in = u.new_empty((max_chunks, D, N))
    y = u.new_empty((T, D))
    final = u.new_empty((S, D, N))
    block_n = triton.next_power_of_2(N)
    block_d = max(1, min(triton.next_power_of_2(D), 512 // block_n))  # about 512 state values per program
    grid = (max_chunks, triton.cdiv(D, block_d))
    common = dict(D=D, N=N, BLOCK_D=block_d, BLOCK_N=block_n, num_warps=1)
    _chunk_kernel[grid](u, delta, A, B, C, start, length, fin, y, fin, dsum, FROM_STATE=False, **common)
    h0_arg = final if h0 is None else h0
    _carry_kernel[(S, grid[1])](A, h0_arg, cptr, fin, dsum, h_in, final, HAS_H0=h0 is not None, **common)
    _chunk_kernel[grid](u, delta, A, B, C, start, length, h_in, y, fin, dsum, FROM_STATE=True, **common)
    return y, final


class TritonScan(torch.autograd.Function):
    """Forward on the Triton kernels; backward through the chunked torch scan, recomputed."""

    @staticmethod
    def forward(ctx, u, delta, A, B, C, cu, h0, chunk):  # type: ignore[override]
        cd = torch.float64 if any(t.dtype == torch.float64 for t in (u, delta, A, B, C)) else torch.float32
        D, N = A.shape[0], B.shape[1]
        args = [t.to(cd).contiguous() for t in (u, delta, A.expand(D, N), B, C)]
        h0c = None if h0 is None else h0.to(cd).contiguous()
        ctx.save_for_backward(u, delta, A, B, C, cu, h0)
        ctx.chunk = chunk
        if u.shape[0] == 0:
            y = u.new_zeros((0, D), dtype=cd)
            final = u.new_zeros((cu.numel() - 1, D, N), dtype=cd) if h0c is None else h0c.clone()
        else:
            y, final = _forward(*args, cu, h0c, chunk)
        return y.to(u.dtype), final

    @staticmethod
    def backward(ctx, gy, gfinal):  # type: ignore[override]
        u, delta, A, B, C, cu, h0 = ctx.saved_tensors

        def twin(u, delta, A, B, C, h0):
            return selective_scan_chunked(u, delta, A, B, C, cu, h0, ctx.chunk)

        g_u, g_delta, g_A, g_B, g_C, g_h0 = grads_by_recompute(twin, (u, delta, A, B, C, h0), (gy, gfinal))
        return g_u, g_delta, g_A, g_B, g_C, None, g_h0, None


def selective_scan_triton(
    u: Tensor, delta: Tensor, A: Tensor, B: Tensor, C: Tensor, cu: Tensor, h0: Tensor | None, chunk: int
) -> tuple[Tensor, Tensor]:
    """Same contract as `scan_torch.selective_scan_ref`, on CUDA tensors."""
    if chunk < 1:
        raise ValueError("chunk_size must be >= 1")
    return TritonScan.apply(u, delta, A, B, C, cu, h0, chunk)
