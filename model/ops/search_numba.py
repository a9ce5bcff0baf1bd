"""`torch.searchsorted` for the neighbour tables as a CPU kernel (numba), a torch custom op
(`model.ops.search` dispatches).

A table looks up K0*K1 rows of queries (one per kernel offset) among a capacity's sorted site keys. Within
a row the queries are the sites' own keys shifted by one offset, so they come nearly sorted (padding and
out-of-grid entries hold SENTINEL, which sorts last). aten's searchsorted starts every query from scratch
(log2(cap) probes, mostly cache misses and mispredicted branches); here each query starts from the
previous one's answer (a few steps right, else a bisection), and a query at or past the largest key
(SENTINEL) is answered without a search: 0.6 against 2.4 ms for the tables of a `tiny` step on the 2-core
machine. The result is searchsorted's exactly (side left: the first position whose key is >= the query)
for any queries, sorted or not; the parity test holds them equal. One thread and numba, for the reasons
given in `model.ops.scan_numba`; a custom op so that torch.compile calls it as one opaque op.
"""

from __future__ import annotations

import numba
import torch
from torch import Tensor


@numba.njit(cache=True, nogil=True)
def _lower_bound(keys, v, lo, hi):  # pragma: no cover - compiled
    """The first i in [lo, hi) with keys[i] >= v, or hi; keys sorted."""
    while lo < hi:
        mid = (lo + hi) >> 1
        if keys[mid] < v:
            lo = mid + 1
        else:
            hi = mid
    return lo


@numba.njit(cache=True, nogil=True)
def _search(keys, queries, out):  # pragma: no cover - compiled
    """keys (n,) sorted int64; queries (R, Q) int64. Writes out (R, Q): searchsorted(keys, queries)."""
    n = keys.shape[0]
    top = keys[n - 1] if n else 0
    end = _lower_bound(keys, top, 0, n)  # the first position of the largest key (SENTINEL's, if padded)
    for r in range(queries.shape[0]):
        pos = 0  # the previous query's answer: the next one's search starts there
        for j in range(queries.shape[1]):
            v = queries[r, j]
            if n == 0 or v >= top:  # SENTINEL queries (padding, outside the grid): pos stays
                out[r, j] = n if n == 0 or v > top else end
                continue
            if keys[pos] < v:  # the answer is right of pos (and < end, as v < top): a few steps, else bisect
                steps = 0
                while steps < 4 and keys[pos] < v:
                    pos += 1
                    steps += 1
                if keys[pos] < v:
                    pos = _lower_bound(keys, v, pos, end)
            elif pos > 0 and keys[pos - 1] >= v:  # left of pos (rare: the queries come nearly sorted)
                pos = _lower_bound(keys, v, 0, pos)
            out[r, j] = pos


@torch.library.custom_op("phim::sorted_search", mutates_args=(), device_types="cpu")
def search_numba(keys: Tensor, queries: Tensor) -> Tensor:
    """keys (n,) int64 sorted, queries (R, Q) int64 -> (R, Q) int64 = torch.searchsorted(keys, queries)."""
    out = torch.empty(queries.shape, dtype=torch.int64)
    _search(keys.contiguous().numpy(), queries.contiguous().numpy(), out.numpy())
    return out


@search_numba.register_fake
def _(keys, queries):
    return queries.new_empty(queries.shape)
