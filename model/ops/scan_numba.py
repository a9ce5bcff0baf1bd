"""The selective scan on the CPU as two numba kernels, forward and backward: the fast twin of
`model.ops.scan_torch` (same contract, see its docstring) for training and both engines' steps.

The torch twins materialise (T, N, D) tensors a few times over and run loops of small ops, which autograd
records one by one; here one loop walks the T tokens once with the state (N, D) in cache, every inner loop
over the D contiguous channels. Only the recurrence is in the kernels:

    h = h0[seg[t]] (zeros without a carried state)  where t starts a segment
    h_t = E_t * h_{t-1} + x_t B_t,   y_t = C_t . h_t  (0 on padding),  E_t = exp(delta_t A), x_t = delta_t u_t

E and x are computed by torch outside them, so autograd carries their gradients to delta, u and A. The
backward kernel walks the tokens in reverse with g = dL/dh_t (zero past a segment's end, plus dfinal at a
stream's last token):

    g += C_t dy_t;  dE_t = g * h_{t-1} (summed over N for a shared decay);  dx_t = g . B_t;
    dB_t = g . x_t;  dC_t = dy_t . h_t;  then g = E_t * g  (dL/dh_{t-1}; dL/dh0[seg] at a segment's start)

reading the states h_t that the forward kept (T, N, D) when a gradient was needed. The forward is a torch
custom op (`phim::scan_numba`, its backward registered), so torch.compile calls it as one opaque op:
inductor's CPU code for the chunked twin's unrolled loop recomputes the chain and runs 3-4x slower.

numba rather than a C++ extension or inductor: it compiles at first use without a compiler on the machine and
caches the result. One thread: splitting the channels over two (plain threads; numba's own pool spins beside
torch's OpenMP team and slowed every op around it 100x) measured the same on the 2-core machine.
"""

from __future__ import annotations

import numba
import numpy as np
import torch
from torch import Tensor

from model.ops.scan_torch import check_inputs, compute_dtype
from model.ops.segments import Segments


@numba.njit(cache=True, nogil=True)
def _owners(last, total):  # pragma: no cover - compiled
    """The stream whose last token t is, -1 for none -> (T,) int64."""
    owner = np.full(total, -1, dtype=np.int64)
    for s in range(last.shape[0]):
        if last[s] >= 0:
            owner[last[s]] = s
    return owner


@numba.njit(cache=True, nogil=True)
def _forward(x, E, B, C, h0, start, valid, seg, last, y, final, H):  # pragma: no cover - compiled
    """x (T, D); E (T, N | 1, D); B, C (T, N); h0 (S, N, D); start, valid (T,) bool; seg (T,), last (S,)
    int64. Writes y (T, D) (zeros on padding), final (S, N, D) (h0 where a stream has no token) and, when H
    has T rows, every state h_t into H (T, N, D)."""
    T, D = x.shape
    N = B.shape[1]
    shared = E.shape[1] == 1
    keep = H.shape[0] > 0
    owner = _owners(last, T)
    final[:] = h0
    h = np.zeros((N, D), dtype=y.dtype)
    acc = np.empty(D, dtype=y.dtype)
    for t in range(T):
        if not valid[t]:  # padding: a segment of its own, feeds nothing
            y[t] = 0.0
            continue
        if start[t]:
            s = seg[t]
            if 0 <= s < h0.shape[0]:  # numba does not check bounds
                h[:] = h0[s]
            else:
                h[:] = 0.0
        acc[:] = 0.0
        for n in range(N):
            e = E[t, 0 if shared else n]
            b = B[t, n]
            c = C[t, n]
            hn = h[n]
            for d in range(D):
                v = e[d] * hn[d] + x[t, d] * b
                hn[d] = v
                acc[d] += c * v
        y[t] = acc
        if keep:
            H[t] = h
        if owner[t] >= 0:
            final[owner[t]] = h


@numba.njit(cache=True, nogil=True)
def _backward(
    x, E, B, C, h0, start, valid, seg, last, H, dy, dfinal, dx, dE, dB, dC, dh0
):  # pragma: no cover - compiled
    """Gradients of the forward's outputs (dy (T, D), dfinal (S, N, D)) -> dx, dE, dB, dC, dh0 (written,
    shaped as x, E, B, C, h0); H (T, N, D) the forward's states."""
    T, D = x.shape
    N = B.shape[1]
    shared = E.shape[1] == 1
    owner = _owners(last, T)
    g = np.zeros((N, D), dtype=x.dtype)
    prev = np.zeros((N, D), dtype=x.dtype)
    dh0[:] = 0.0
    for s in range(last.shape[0]):
        if last[s] < 0:  # final = h0
            dh0[s] += dfinal[s]
    for t in range(T - 1, -1, -1):
        dx[t] = 0.0
        dE[t] = 0.0
        dB[t] = 0.0
        dC[t] = 0.0
        if not valid[t]:
            continue
        if t == T - 1 or start[t + 1]:  # the segment's last token: nothing after it reads h_t
            g[:] = 0.0
        if owner[t] >= 0:
            g += dfinal[owner[t]]
        s = seg[t]
        carried = start[t] and 0 <= s < h0.shape[0]
        if not start[t]:
            prev[:] = H[t - 1]
        elif carried:
            prev[:] = h0[s]
        else:
            prev[:] = 0.0
        for n in range(N):  # g becomes dL/dh_t: add y_t's share
            c = C[t, n]
            gn = g[n]
            db = 0.0
            dc = 0.0
            for d in range(D):
                gn[d] += c * dy[t, d]
                db += gn[d] * x[t, d]
                dc += dy[t, d] * H[t, n, d]
            dB[t, n] = db
            dC[t, n] = dc
        for n in range(N):  # dE_t, dx_t; then g becomes dL/dh_{t-1}
            b = B[t, n]
            k = 0 if shared else n
            e = E[t, k]
            gn = g[n]
            pn = prev[n]
            for d in range(D):
                dE[t, k, d] += gn[d] * pn[d]
                dx[t, d] += gn[d] * b
                gn[d] *= e[d]
        if carried:
            dh0[s] += g


def _scan_eager(
    x: Tensor,
    E: Tensor,
    B: Tensor,
    C: Tensor,
    h0: Tensor,
    start: Tensor,
    valid: Tensor,
    seg: Tensor,
    last: Tensor,
    keep: bool,
) -> tuple[Tensor, Tensor, Tensor]:
    """(x (T, D), E (T, N | 1, D), B, C (T, N), h0 (S, N, D), the pack's flags) -> (y (T, D), final
    (S, N, D), the states (T, N, D) when `keep`, else (0, N, D)), all contiguous in the compute dtype."""
    T, D = x.shape
    y, final = x.new_empty(T, D), torch.empty_like(h0)
    H = x.new_empty(T if keep else 0, B.shape[1], D)
    _forward(*(a.numpy() for a in (x, E, B, C, h0, start, valid, seg, last, y, final, H)))
    return y, final, H


# the kernel as an op torch.compile and autograd see; the eager forward without gradients calls
# `_scan_eager` itself (the op's first call imports torch._dynamo, and with it triton where installed)
_scan = torch.library.custom_op("phim::scan_numba", _scan_eager, mutates_args=(), device_types="cpu")


@_scan.register_fake
def _(x, E, B, C, h0, start, valid, seg, last, keep):
    T, D = x.shape
    return x.new_empty(T, D), torch.empty_like(h0), x.new_empty(T if keep else 0, B.shape[1], D)


def _setup(ctx, inputs, output) -> None:
    x, E, B, C, h0, start, valid, seg, last, _ = inputs
    ctx.save_for_backward(x, E, B, C, h0, start, valid, seg, last, output[2])


def _grads(ctx, dy, dfinal, _dH):
    x, E, B, C, h0, start, valid, seg, last, H = ctx.saved_tensors
    if H.shape[0] != x.shape[0]:
        raise RuntimeError("the numba scan kept no states for a backward (called with keep=False)")
    dy = torch.zeros_like(x) if dy is None else dy.contiguous()
    dfinal = torch.zeros_like(h0) if dfinal is None else dfinal.contiguous()
    grads = [torch.empty_like(a) for a in (x, E, B, C, h0)]
    arrays = (x, E, B, C, h0, start, valid, seg, last, H, dy, dfinal, *grads)
    _backward(*(a.numpy() for a in arrays))
    return (*grads, None, None, None, None, None)


_scan.register_autograd(_grads, setup_context=_setup)


def selective_scan_numba(
    u: Tensor,
    delta: Tensor,
    A: Tensor,
    B: Tensor,
    C: Tensor,
    seqs: Tensor | Segments,
    h0: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """`selective_scan_ref`'s contract on CPU tensors, differentiable: y (T, D) in u's dtype, final states
    (S, D, N) in the compute dtype (float32, float64 for float64 inputs)."""
    segs = check_inputs(u, delta, A, B, C, seqs, h0)
    S, D, N = segs.num_streams, u.shape[1], B.shape[1]
    cd = compute_dtype(u, delta, A, B, C)
    dt = torch.where(segs.valid[:, None], delta.to(cd), 0.0)  # (T, D): padding may hold anything
    E = torch.exp(dt[:, None, :] * A.to(cd).t()[None]).contiguous()  # (T, N | 1, D)
    x = (dt * u.to(cd)).contiguous()  # (T, D)
    h_init = u.new_zeros(S, N, D, dtype=cd) if h0 is None else h0.to(cd).transpose(1, 2).contiguous()
    Bc, Cc = B.to(cd).contiguous(), C.to(cd).contiguous()
    flags = [t.contiguous() for t in (segs.start, segs.valid, segs.seg, segs.last)]
    keep = torch.is_grad_enabled() and any(t.requires_grad for t in (x, E, Bc, Cc, h_init))
    run = _scan if keep or torch.compiler.is_compiling() else _scan_eager
    y, final, _ = run(x, E, Bc, Cc, h_init, *flags, keep)
    return y.to(u.dtype), final.transpose(1, 2).contiguous()
