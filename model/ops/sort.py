"""Stable sort of int64 keys, the fixed-shape step's (voxel keys, strided conv candidates): the numba kernel
(`model.ops.sort_numba`, CPU tensors) or its plain-torch twin, `torch.sort(keys, stable=True)`; the dispatch
rule is `numba_support.numba_kernel`'s. tests/test_graph_sparse.py holds them equal."""

from __future__ import annotations

import torch
from torch import Tensor

from model.ops.numba_support import numba_kernel
from model.ops.sort_numba import sort_keys_numba


def sort_keys_torch(keys: Tensor) -> tuple[Tensor, Tensor]:
    """keys (n,) int64 -> (values, order): the plain twin."""
    return torch.sort(keys, stable=True)


def sort_keys(keys: Tensor, fast: bool | None = None) -> tuple[Tensor, Tensor]:
    """torch.sort(keys, stable=True) for (n,) int64 keys; `fast`: see `numba_kernel`."""
    if numba_kernel("sort_keys", keys.device, fast):
        return sort_keys_numba(keys)
    return sort_keys_torch(keys)
