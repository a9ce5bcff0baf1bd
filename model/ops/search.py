"""Lower-bound search of queries among sorted int64 keys (the neighbour tables' lookups): the numba kernel
(`model.ops.search_numba`, CPU tensors) or its plain-torch twin, `torch.searchsorted`; the dispatch rule is
`numba_support.numba_kernel`'s. tests/test_graph_sparse.py holds them equal."""

from __future__ import annotations

import torch
from torch import Tensor

from model.ops.numba_support import numba_kernel
from model.ops.search_numba import search_numba


def search_torch(keys: Tensor, queries: Tensor) -> Tensor:
    """keys (n,) int64 sorted, queries (R, Q) int64 -> (R, Q) int64: the plain twin."""
    return torch.searchsorted(keys, queries)


def search(keys: Tensor, queries: Tensor, fast: bool | None = None) -> Tensor:
    """torch.searchsorted(keys, queries) (side left) for (R, Q) queries; `fast`: see `numba_kernel`."""
    if numba_kernel("sorted_search", keys.device, fast):
        return search_numba(keys, queries)
    return search_torch(keys, queries)
