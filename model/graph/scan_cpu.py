"""The segmented selective scan as a CPU kernel (numba): the fast twin of `model.graph.mamba.segmented_scan`.

The torch twin materialises (T, N, D) tensors a few times over and runs a chunk loop of small ops; here one
loop walks the T tokens once, keeping the state (N, D) in cache. The recurrence is the twin's, token by
token:

    h = h0[seg[t]] (zeros without h0)  where start[t]
    h = exp(delta_t * A) * h + delta_t * u_t * B_t;   y_t = C_t . h;   y_t = 0 on padding

and a stream's final state is h at its last token (h0 where it has none). One thread: splitting the
channels over two (plain threads; numba's own pool spins beside torch's OpenMP team and slowed every op
around it 100x) measured the same on the 2-core machine. numba rather than a C++ extension or inductor: it
compiles at first use without a compiler on the machine and caches the result; inductor's CPU code for a
sequential recurrence recomputes the chain (mamba.py).
"""

from __future__ import annotations

import numba
import numpy as np
import torch
from torch import Tensor

from model.graph.segments import Segments
from model.ops.scan_torch import compute_dtype


@numba.njit(cache=True, nogil=True)
def _scan(u, dt, E, B, C, start, valid, seg, last, h0, y, final):  # pragma: no cover - compiled
    """u, dt (T, D); E (T, N | 1, D) = exp(dt A); B, C (T, N); start, valid (T,) bool; seg (T,) int64; last
    (S,) int64; h0 (S | 0, D, N). Writes y (T, D) (zeros on padding) and final (S, D, N) (h0 where a stream
    has no token). The state is kept (N, D) so that the inner loops run over the D contiguous channels."""
    T, D = u.shape
    N = B.shape[1]
    S = final.shape[0]
    shared = E.shape[1] == 1
    owner = np.full(T, -1, dtype=np.int64)  # the stream whose last token t is
    for s in range(S):
        if last[s] >= 0:
            owner[last[s]] = s
        for d in range(D):
            for n in range(N):
                final[s, d, n] = h0[s, d, n]
    h = np.zeros((N, D), dtype=y.dtype)
    x = np.empty(D, dtype=y.dtype)
    acc = np.empty(D, dtype=y.dtype)
    for t in range(T):
        if not valid[t]:  # padding: a segment of its own, feeds nothing
            for d in range(D):
                y[t, d] = 0.0
            continue
        if start[t]:
            s = seg[t]
            carried = 0 <= s < h0.shape[0]  # numba does not check bounds
            for n in range(N):
                for d in range(D):
                    h[n, d] = h0[s, d, n] if carried else 0.0
        for d in range(D):
            x[d] = dt[t, d] * u[t, d]
            acc[d] = 0.0
        for n in range(N):
            e = E[t, 0 if shared else n]
            b = B[t, n]
            c = C[t, n]
            hn = h[n]
            for d in range(D):
                v = e[d] * hn[d] + x[d] * b
                hn[d] = v
                acc[d] += c * v
        for d in range(D):
            y[t, d] = acc[d]
        s = owner[t]
        if s >= 0:
            for n in range(N):
                for d in range(D):
                    final[s, d, n] = h[n, d]


def segmented_scan_cpu(
    u: Tensor, delta: Tensor, A: Tensor, B: Tensor, C: Tensor, segs: Segments, h0: Tensor | None = None
) -> tuple[Tensor, Tensor | None]:
    """`segmented_scan`'s contract (without chunks) on CPU tensors: y (T, D) in u's dtype, zeros on padding;
    final states (S, D, N) in the compute dtype (float32, float64 for float64 inputs) or None without h0."""
    cd = compute_dtype(u, delta, A, B, C)
    T, D = u.shape
    N = B.shape[1]
    dt = delta.to(cd)  # (T, D)
    E = torch.exp(dt[:, None, :] * A.to(cd).t()[None])  # (T, N | 1, D); padding rows are never read
    y = torch.empty(T, D, dtype=cd)
    init = h0.to(cd).contiguous() if h0 is not None else torch.zeros(0, D, N, dtype=cd)
    last = segs.last if h0 is not None else segs.last[:0]  # no final states without h0
    final = torch.empty_like(init)
    arrays = (u.to(cd), dt, E, B.to(cd), C.to(cd), segs.start, segs.valid, segs.seg, last, init, y, final)
    _scan(*(a.numpy() for a in arrays))
    return y.to(u.dtype), final if h0 is not None else None
