"""The selective scan on the CPU as two numba kernels, forward and backward: the fast twin of
`model.ops.scan_torch` (same contract, see its docstring) for training and the eager step.

The chunked twin materialises several (T, N, D) tensors and runs a loop of small ops per chunk position, and
autograd records every one of them; here one loop walks each sequence's tokens once with its state (N, D) in
cache, every inner loop over the D contiguous channels. Only the recurrence is in the kernels:

    h_t = E_t * h_{t-1} + x_t B_t,   y_t = C_t . h_t      with E_t = exp(delta_t A), x_t = delta_t u_t

E and x are computed by torch outside them, so autograd carries their gradients to delta, u and A. The
backward kernel walks each sequence in reverse with g = dL/dh_t:

    g += C_t dy_t;  dE_t = g * h_{t-1} (summed over N for a shared decay);  dx_t = g . B_t;
    dB_t = g . x_t;  dC_t = dy_t . h_t;  then g = E_t * g  (dL/dh_{t-1}; dL/dh0 at the sequence's start)

reading the states h_t that the forward kept (T, N, D) when a gradient was needed. numba rather than a C++
extension: it compiles at first use without a build step and caches the result (as `model.graph.scan_cpu`).
The forward's token loop is written out as in that kernel rather than shared: a helper called per token ran
2x slower there, and numba's on-disk cache does not see a change to a helper in another file.
"""

from __future__ import annotations

import numba
import numpy as np
import torch
from torch import Tensor

from model.ops.scan_torch import check_cu, check_inputs, compute_dtype


@numba.njit(cache=True, nogil=True)
def _forward(x, E, B, C, cu, h0, y, final, H):  # pragma: no cover - compiled
    """x (T, D); E (T, N | 1, D); B, C (T, N); cu (S + 1,); h0 (S, N, D). Writes y (T, D), final (S, N, D)
    and, when H has T rows, every state h_t into H (T, N, D)."""
    D = x.shape[1]
    N = B.shape[1]
    shared = E.shape[1] == 1
    keep = H.shape[0] > 0
    h = np.empty((N, D), dtype=y.dtype)
    acc = np.empty(D, dtype=y.dtype)
    for s in range(cu.shape[0] - 1):
        h[:] = h0[s]
        for t in range(cu[s], cu[s + 1]):
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
        final[s] = h


@numba.njit(cache=True, nogil=True)
def _backward(x, E, B, C, cu, h0, H, dy, dfinal, dx, dE, dB, dC, dh0):  # pragma: no cover - compiled
    """Gradients of the forward's outputs (dy (T, D), dfinal (S, N, D)) -> dx, dE, dB, dC, dh0 (written,
    shaped as x, E, B, C, h0); H (T, N, D) the forward's states."""
    D = x.shape[1]
    N = B.shape[1]
    shared = E.shape[1] == 1
    g = np.empty((N, D), dtype=x.dtype)
    for s in range(cu.shape[0] - 1):
        g[:] = dfinal[s]
        for t in range(cu[s + 1] - 1, cu[s] - 1, -1):
            prev = H[t - 1] if t > cu[s] else h0[s]  # h_{t-1}
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
            dx[t] = 0.0
            if shared:
                dE[t, 0] = 0.0
            for n in range(N):  # dE_t, dx_t; then g becomes dL/dh_{t-1}
                b = B[t, n]
                k = 0 if shared else n
                e = E[t, k]
                gn = g[n]
                pn = prev[n]
                for d in range(D):
                    if shared:
                        dE[t, 0, d] += gn[d] * pn[d]
                    else:
                        dE[t, n, d] = gn[d] * pn[d]
                    dx[t, d] += gn[d] * b
                    gn[d] *= e[d]
        dh0[s] = g


class _Recurrence(torch.autograd.Function):
    """(x, E, B, C, h0 (S, N, D), cu) -> (y (T, D), final (S, N, D)) on the numba kernels."""

    @staticmethod
    def forward(ctx, x, E, B, C, h0, cu):  # type: ignore[override]
        T, D = x.shape
        keep = any(ctx.needs_input_grad[:5])
        y = x.new_empty(T, D)
        final = torch.empty_like(h0)
        H = x.new_empty(T if keep else 0, B.shape[1], D)  # (T, N, D) kept for the backward
        _forward(*(a.numpy() for a in (x, E, B, C, cu, h0, y, final, H)))
        if keep:
            ctx.save_for_backward(x, E, B, C, cu, h0, H)
        return y, final

    @staticmethod
    def backward(ctx, dy, dfinal):  # type: ignore[override]
        x, E, B, C, cu, h0, H = ctx.saved_tensors
        grads = [torch.empty_like(a) for a in (x, E, B, C, h0)]
        arrays = (x, E, B, C, cu, h0, H, dy.contiguous(), dfinal.contiguous(), *grads)
        _backward(*(a.numpy() for a in arrays))
        return (*grads, None)


def selective_scan_numba(
    u: Tensor, delta: Tensor, A: Tensor, B: Tensor, C: Tensor, cu_seqlens: Tensor, h0: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """`selective_scan_ref`'s contract on CPU tensors, differentiable: y (T, D) in u's dtype, final states
    (S, D, N) in the compute dtype (float32, float64 for float64 inputs)."""
    check_inputs(u, delta, A, B, C, cu_seqlens, h0)
    cu = cu_seqlens.to(torch.int64).contiguous()
    check_cu(cu.numpy(), u.shape[0])
    S, D, N = cu.numel() - 1, u.shape[1], B.shape[1]
    cd = compute_dtype(u, delta, A, B, C)
    dt = delta.to(cd)  # (T, D)
    E = torch.exp(dt[:, None, :] * A.to(cd).t()[None]).contiguous()  # (T, N | 1, D)
    x = (dt * u.to(cd)).contiguous()  # (T, D)
    h_init = u.new_zeros(S, N, D, dtype=cd) if h0 is None else h0.to(cd).transpose(1, 2).contiguous()
    Bc, Cc = B.to(cd).contiguous(), C.to(cd).contiguous()
    y, final = _Recurrence.apply(x, E, Bc, Cc, h_init, cu)
    return y.to(u.dtype), final.transpose(1, 2).contiguous()
