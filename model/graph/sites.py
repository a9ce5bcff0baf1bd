"""The active sites of a fixed-capacity sparse tensor: sorted linear keys padded to a capacity.

A capacity (`cap`) is a Python int chosen by the caller (the bucket), so every shape below depends only on
input shapes and capacities: nothing here synchronises with the host. Real sites come first, sorted by
`linear_key` (batch, theta, r, z); padding rows hold the key SENTINEL, which sorts after every real key.
When more sites would exist than fit, `count` says how many (> cap): the sites beyond cap are dropped and
the caller must run again with a larger capacity.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from model.geometry.rulebook import keys_to_coords
from model.geometry.sparse_tensor import SENTINEL


@dataclass(frozen=True)
class Sites:
    """The active sites of a fixed-capacity sparse tensor: rows [0, n) are real sites sorted by linear_key
    (batch, theta, r, z), padding rows after them."""

    keys: Tensor  # (cap,) int64 sorted; SENTINEL on padding rows
    coords: Tensor  # (cap, 4) int64 (batch, r, theta, z); padding rows hold (batch_size, 0, 0, 0)
    spatial_shape: tuple[int, int, int]  # (R, THETA, Z)
    batch_size: int
    count: Tensor  # () int64: the number of real sites there would be; > cap means overflow

    @property
    def cap(self) -> int:
        return int(self.keys.shape[0])

    @property
    def valid(self) -> Tensor:
        """(cap,) bool: real site rows."""
        return self.keys != SENTINEL

    @property
    def overflow(self) -> Tensor:
        """() bool: more sites than rows (the extra ones were dropped)."""
        return self.count > self.cap


def compact_sorted(keys_sorted: Tensor, cap: int) -> tuple[Tensor, Tensor, Tensor]:
    """Unique keys of a sorted key list, compacted into `cap` rows.

    keys_sorted (n,) int64 sorted, SENTINEL on padding entries (they sort last) ->
    (cap,) unique keys padded with SENTINEL, (n,) row of each input key in the output (`cap` for SENTINEL
    inputs and for keys that did not fit), () int64 count of unique real keys (> cap: overflow).
    """
    real = keys_sorted != SENTINEL  # (n,)
    differs = torch.ones_like(real)
    differs[1:] = keys_sorted[1:] != keys_sorted[:-1]
    first = real & differs  # (n,) first occurrence of each real key
    rank = torch.cumsum(first, 0) - 1  # (n,) output row of each input's key
    row = torch.where(real & (rank < cap), rank, cap)  # (n,)
    dst = torch.where(first, row, cap)  # (n,) only first occurrences write; the rest go to the dump row
    out = torch.full((cap + 1,), SENTINEL, dtype=keys_sorted.dtype, device=keys_sorted.device)
    out = out.scatter(0, dst, keys_sorted)  # (cap + 1,); row cap is the dump row
    return out[:cap], row, first.sum()


def decode_keys(keys: Tensor, spatial_shape: tuple[int, int, int], batch_size: int) -> Tensor:
    """(cap,) keys, SENTINEL on padding -> (cap, 4) int64 coords (batch, r, theta, z); padding rows decode to
    (batch_size, 0, 0, 0) (the key of that position is batch_size * R * THETA * Z)."""
    n_r, n_t, n_z = spatial_shape
    pad_key = batch_size * n_r * n_t * n_z
    return keys_to_coords(torch.where(keys == SENTINEL, pad_key, keys), spatial_shape)


def make_sites(keys: Tensor, spatial_shape: tuple[int, int, int], batch_size: int, count: Tensor) -> Sites:
    """Sites of compacted keys (cap,) (from `compact_sorted`), their coords decoded."""
    return Sites(keys, decode_keys(keys, spatial_shape, batch_size), spatial_shape, batch_size, count)


def scatter_sum(out: Tensor, index: Tensor, src: Tensor) -> Tensor:
    """out[index[i]] += src[i] along dim 0, in place: out (M, ...) , index (n,) int64, src (n, ...).

    `scatter_reduce_(..., "sum")` rather than `index_add_`: inductor's CPU code for index_add_ is a loop of
    atomic adds, 4x slower than aten's, while the scatter-reduce falls back to aten's kernel."""
    idx = index.view(-1, *([1] * (src.dim() - 1))).expand_as(src)
    return out.scatter_reduce_(0, idx, src, "sum")
