"""A stable sort of the step's int64 keys as a CPU kernel (numba), a torch custom op: the fast twin of
`torch.sort(keys, stable=True)` (`model.ops.sort` dispatches).

The step sorts linear site keys: the voxelizer its points' keys, a strided conv its candidate output keys.
Real keys are small (below the batch's cell count: 2^19 cells a stream for `tiny`) and padding holds
SENTINEL (2^62). aten's sort walks all 64 bits of every key; here the SENTINEL keys go last in their order
and the rest take an LSD radix sort over only the bits their largest key has (11 bits a pass: two passes
for up to eight `tiny` streams):
0.09 against 0.55-1.35 ms for 26-41k keys on the 2-core machine. Stable, so the order is torch's exactly;
negative keys (never made by the step) go through torch.sort. One thread and numba, for the reasons given
in `model.ops.scan_numba`.
"""

from __future__ import annotations

import numba
import numpy as np
import torch
from torch import Tensor

from model.geometry.sparse_tensor import SENTINEL

DIGIT = 11  # bits per radix pass


@numba.njit(cache=True, nogil=True)
def _radix_sort(keys, last, values, order):  # pragma: no cover - compiled
    """keys (n,) int64; `last` the key that goes after all others in input order. Writes values (n,) and
    order (n,) int64: keys sorted (stable) and their input positions; False (nothing written) if a key is
    negative."""
    n = keys.shape[0]
    for i in range(n):
        if keys[i] < 0:
            return False
    m, top = 0, 0
    for i in range(n):  # the keys other than `last`, in input order
        if keys[i] != last:
            values[m] = keys[i]
            order[m] = i
            m += 1
            top = max(top, keys[i])
    tail = m
    for i in range(n):
        if keys[i] == last:
            values[tail] = last
            order[tail] = i
            tail += 1
    bits = 0
    while (top >> bits) > 0:
        bits += 1
    radix = 1 << DIGIT
    count = np.empty(radix + 1, dtype=np.int64)
    src_v, src_o = values, order
    dst_v, dst_o = np.empty(m, dtype=np.int64), np.empty(m, dtype=np.int64)
    for shift in range(0, bits, DIGIT):
        count[:] = 0
        for i in range(m):
            count[((src_v[i] >> shift) & (radix - 1)) + 1] += 1
        for r in range(radix):
            count[r + 1] += count[r]
        for i in range(m):
            d = (src_v[i] >> shift) & (radix - 1)
            dst_v[count[d]] = src_v[i]
            dst_o[count[d]] = src_o[i]
            count[d] += 1
        src_v, dst_v = dst_v, src_v
        src_o, dst_o = dst_o, src_o
    if src_v is not values:  # an odd number of passes: the result is in the scratch arrays
        values[:m] = src_v[:m]
        order[:m] = src_o[:m]
    return True


@torch.library.custom_op("phim::sort_keys", mutates_args=(), device_types="cpu")
def sort_keys_numba(keys: Tensor) -> tuple[Tensor, Tensor]:
    """keys (n,) int64 -> (values, order) = torch.sort(keys, stable=True)."""
    values, order = torch.empty_like(keys), torch.empty_like(keys)
    if not _radix_sort(keys.contiguous().numpy(), SENTINEL, values.numpy(), order.numpy()):
        values, order = torch.sort(keys, stable=True)  # negative keys
    return values, order


@sort_keys_numba.register_fake
def _(keys):
    return keys.new_empty(keys.shape), keys.new_empty(keys.shape)
