"""The polar->BEV scatter-mean of the fixed-shape step as a CPU kernel (numba), a torch custom op.

Its plain twin is `model.ops.bev_mean.bev_mean_torch`; `bev_mean` there dispatches (the parity tests hold
them equal). The twin scatters every buffered row once per cell it feeds
through aten's scatter-reduce (an index expanded to the rows' shape, a product per pair first): 3.6 ms of a
`tiny` step on the 2-core machine. Here one pass adds each valid row into its cells and a second divides by
the counts: 0.35-0.55 ms. One thread, like the scan (`model.ops.scan_numba`), numba for the reasons given
there; sums run in another order than the twin's, so results agree to float rounding. A custom op so that
torch.compile calls it as one opaque op (dynamo cannot trace numba); it exists for CPU tensors only.
"""

from __future__ import annotations

import numba
import numpy as np
import torch
from torch import Tensor


@numba.njit(cache=True, nogil=True)
def _bev_mean(feats, column, valid, table, cells_per_item, out):  # pragma: no cover - compiled
    """feats (B, L, C); column (B, L) int64 polar column; valid (B, L) bool; table (R * THETA, W) int64 cell
    ids, -1 past a column's cells. Writes out (B * cells_per_item, C): the mean of the rows each cell gets."""
    n_b, length, c = feats.shape
    count = np.zeros(out.shape[0], dtype=out.dtype)
    out[:] = 0.0
    for b in range(n_b):
        base = b * cells_per_item
        for r in range(length):
            if not valid[b, r]:
                continue
            col = min(max(column[b, r], 0), table.shape[0] - 1)
            for d in range(table.shape[1]):
                cell = table[col, d]
                if cell < 0:
                    continue
                cell += base
                count[cell] += 1.0
                row = out[cell]
                f = feats[b, r]
                for j in range(c):
                    row[j] += f[j]
    for cell in range(out.shape[0]):
        if count[cell] > 1.0:
            inv = 1.0 / count[cell]
            for j in range(c):
                out[cell, j] *= inv


@torch.library.custom_op("phim::bev_mean", mutates_args=(), device_types="cpu")
def bev_mean_numba(feats: Tensor, column: Tensor, valid: Tensor, table: Tensor, ny: int, nx: int) -> Tensor:
    """`bev_mean`'s contract on CPU tensors."""
    cd = torch.float64 if feats.dtype == torch.float64 else torch.float32
    out = torch.empty(feats.shape[0] * ny * nx, feats.shape[2], dtype=cd)
    arrays = (feats.to(cd).contiguous(), column.contiguous(), valid.contiguous(), table.contiguous())
    _bev_mean(*(a.numpy() for a in arrays), ny * nx, out.numpy())
    return out.view(feats.shape[0], ny, nx, -1).to(feats.dtype)


@bev_mean_numba.register_fake
def _(feats, column, valid, table, ny, nx):
    return feats.new_empty(feats.shape[0], ny, nx, feats.shape[2])
