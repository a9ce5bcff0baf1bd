"""The segmented selective scan as a CPU kernel (numba): the fast twin of `model.graph.mamba.segmented_scan`.

The torch twin materialises (T, N, D) tensors a few times over and runs a chunk loop of small ops; here one
loop walks the T tokens once, keeping the (D, N) state in cache. The recurrence is the twin's, token by
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
def _scan(u, dt, E, B, C, start, seg, owner, h0, y, final):  # pragma: no cover - compiled
    """u, dt (T, D); E (T, D, N | 1) = exp(dt A); B, C (T, N); start (T,) bool; seg (T,) int64; owner (T,)
    int64 stream whose last token t is (-1: none); h0 (S | 0, D, N). Writes y (T, D) and final (S, D, N).
    Padding tokens are starts with dt = 0: they never reach a real token."""
    T, D = u.shape
    N = B.shape[1]
    shared = E.shape[2] == 1
    h = np.zeros((D, N), dtype=y.dtype)
    for t in range(T):
        if start[t]:
            s = seg[t]
            carried = 0 <= s < h0.shape[0]  # numba does not check bounds (padding may hold any seg)
            for d in range(D):
                for n in range(N):
                    h[d, n] = h0[s, d, n] if carried else 0.0
        for d in range(D):
            x = dt[t, d] * u[t, d]
            acc = 0.0
            for n in range(N):
                hn = E[t, d, 0 if shared else n] * h[d, n] + x * B[t, n]
                h[d, n] = hn
                acc += C[t, n] * hn
            y[t, d] = acc
        s = owner[t]
        if 0 <= s < final.shape[0]:
            for d in range(D):
                for n in range(N):
                    final[s, d, n] = h[d, n]


def segmented_scan_cpu(
    u: Tensor, delta: Tensor, A: Tensor, B: Tensor, C: Tensor, segs: Segments, h0: Tensor | None = None
) -> tuple[Tensor, Tensor | None]:
    """`segmented_scan`'s contract (without chunks) on CPU tensors: y (T, D) in u's dtype, zeros on padding;
    final states (S, D, N) in the compute dtype (float32, float64 for float64 inputs) or None without h0."""
    cd = compute_dtype(u, delta, A, B, C)
    start, valid, seg, last = segs.start, segs.valid, segs.seg, segs.last
    T, D = u.shape
    N = B.shape[1]
    dt = torch.where(valid[:, None], delta.to(cd), 0.0).contiguous()  # (T, D)
    E = torch.exp(dt[:, :, None] * A.to(cd)[None]).contiguous()  # (T, D, N | 1)
    owner = torch.full((T + 1,), -1, dtype=torch.int64)  # row T: where streams without tokens point
    if h0 is not None:  # no final states without h0
        owner[torch.where(last >= 0, last, T)] = torch.arange(last.shape[0])
    y = torch.empty(T, D, dtype=cd)
    init = h0.to(cd).contiguous() if h0 is not None else torch.zeros(0, D, N, dtype=cd)
    final = init.clone()
    arrays = (u.to(cd).contiguous(), dt, E, B.to(cd).contiguous(), C.to(cd).contiguous(), start, seg, owner)
    args = [a.contiguous().numpy() for a in arrays] + [init.numpy(), y.numpy(), final.numpy()]
    _scan(*args)
    return torch.where(valid[:, None], y, 0.0).to(u.dtype), final if h0 is not None else None
