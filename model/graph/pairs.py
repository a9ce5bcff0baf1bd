"""Sparse convs over compacted pairs, in tiles that share one kernel offset (a fixed-shape grouped GEMM).

A neighbour table (cap_out, KK) (`model.graph.sparse_conv`) is mostly empty: on LiDAR sites a 3 x 3 plane
kernel finds 1-3 of its 9 neighbours, so the implicit GEMM over it (`conv_fixed`, the reference twin)
multiplies zero rows most of the time. Here the table's real entries become (input row, output row) pairs,
ordered by offset and laid out in tiles of TILE pairs; each offset's pairs start a new tile, so every tile
has one offset and one weight matrix. A fixed `cap` on the pairs gives a fixed tile count (cap / TILE + KK
tiles hold any cap pairs), so the conv is one gather, one batched matmul and one scatter-add of fixed shape:

    y[tile] = x[inp[tile]] @ weight[offset[tile]];   out[out_row] += y

The transposed conv of a strided conv has the same pairs with input and output swapped (`inverse`). More
pairs than `cap`: `count` says how many (the step runs again with a larger capacity).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from model.graph.sites import scatter_sum

TILE = 64  # pairs per tile: a tile's offset padding wastes at most TILE - 1 rows per offset


@dataclass(frozen=True)
class PairTiles:
    """A conv's pairs in tiles: pair j of tile t reads input row inp[t * TILE + j] and adds to output row
    out[t * TILE + j]; padding pairs read the zero row in_rows and write the dump row out_rows."""

    inp: Tensor  # (tiles * TILE,) int64 in [0, in_rows]
    out: Tensor  # (tiles * TILE,) int64 in [0, out_rows]
    offset: Tensor  # (tiles,) int64 flat kernel offset of each tile
    in_rows: int
    out_rows: int
    count: Tensor  # () int64 real pairs there are (> cap: overflow; some were dropped)

    def inverse(self) -> PairTiles:
        """The transposed conv's pairs (same offsets, input and output swapped)."""
        return PairTiles(self.out, self.inp, self.offset, self.out_rows, self.in_rows, self.count)


def pair_tiles(table: Tensor, in_rows: int, cap: int) -> PairTiles:
    """table (out_rows, KK) int64, entries in [0, in_rows] (in_rows: no neighbour) -> the pairs of its real
    entries in ceil(cap / TILE) + KK tiles, ordered by offset, then output row."""
    out_rows, kk = table.shape
    dev = table.device
    by_offset = table.t()  # (KK, out_rows)
    real = by_offset < in_rows  # (KK, out_rows)
    per_offset = real.sum(1)  # (KK,)
    tiles_per = (per_offset + TILE - 1) // TILE  # (KK,) tiles each offset needs
    first_tile = torch.cumsum(tiles_per, 0) - tiles_per  # (KK,)
    tiles = -(-cap // TILE) + kk
    dump = tiles * TILE  # one slot past the tiles
    pos = first_tile[:, None] * TILE + torch.cumsum(real, 1) - 1  # (KK, out_rows) slot of each pair
    pos = torch.where(real & (pos < dump), pos, dump).reshape(-1)  # (KK * out_rows,)
    rows = torch.arange(out_rows, device=dev).expand(kk, out_rows).reshape(-1)  # (KK * out_rows,)
    slots = torch.full((dump + 1,), in_rows, dtype=torch.int64, device=dev)
    inp = slots.scatter(0, pos, by_offset.reshape(-1))
    out = torch.full_like(slots, out_rows).scatter(0, pos, rows)
    ends = torch.cumsum(tiles_per, 0)  # (KK,) tile after each offset's last
    offset = torch.searchsorted(ends, torch.arange(tiles, device=dev), right=True).clamp_max(kk - 1)
    # the dump slot got many writes (any value): cut it off
    return PairTiles(inp[:dump], out[:dump], offset, in_rows, out_rows, per_offset.sum())


def conv_tiles(x: Tensor, pairs: PairTiles, weight: Tensor, bias: Tensor | None) -> Tensor:
    """x (in_rows, C_in), weight (KK, C_in, C_out), bias (C_out,) or None -> (out_rows, C_out), equal to
    `conv_fixed` over the table the pairs came from (when they fit their capacity)."""
    c_in, c_out = weight.shape[1], weight.shape[2]
    ext = torch.cat((x, x.new_zeros(1, c_in)))  # (in_rows + 1, C_in)
    tiles = pairs.offset.shape[0]
    xs = ext.index_select(0, pairs.inp).view(tiles, -1, c_in)  # (tiles, TILE, C_in)
    y = torch.bmm(xs, weight.index_select(0, pairs.offset))  # (tiles, TILE, C_out)
    out = x.new_zeros(pairs.out_rows + 1, c_out)  # + the dump row; sums in x's dtype (bf16 y under autocast)
    out = scatter_sum(out, pairs.out, y.view(-1, c_out).to(out.dtype))[: pairs.out_rows]  # (out_rows, C_out)
    return out if bias is None else out + bias
