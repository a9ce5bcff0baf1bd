"""Packs of tokens cut into segments, the one sequence description every selective scan takes
(`model.ops.scan`): per-token flags instead of cu_seqlens, so that a fixed-length pack needs no host sync.

A pack has T tokens: real tokens in segment order, padding (if any) after them. A segment is a run of
consecutive real tokens; its first token (a start) continues the carried state of stream `seg[t]`
(h0[seg[t]], zeros where there is none). Every padding token is a segment of its own, so padding never feeds
into a real token. Packed variable-length sequences (cu_seqlens) are the special case of one segment per
sequence with no padding (`Segments.of_cu_seqlens`); the fixed-shape step builds its packs in
`model.graph.segments`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor


@dataclass(frozen=True)
class Segments:
    """T tokens of a pack cut into segments; S streams whose states the segments continue."""

    start: Tensor  # (T,) bool: the token starts a segment (every padding token is a start)
    valid: Tensor  # (T,) bool: a real token
    seg: Tensor  # (T,) int64: stream whose state a token's segment continues, in [0, S) (any for padding)
    last: Tensor  # (S,) int64: index of the last token of stream s's segment, -1 when the stream has no token

    @property
    def total(self) -> int:
        return self.start.shape[0]

    @property
    def num_streams(self) -> int:
        return self.last.shape[0]

    def segment_start(self) -> Tensor:
        """Index of the first token of every token's segment -> (T,) int64."""
        t = torch.arange(self.total, device=self.start.device)  # (T,)
        return torch.where(self.start, t, 0).cummax(0).values  # (T,)

    @staticmethod
    def of_cu_seqlens(cu_seqlens: Tensor, total: int) -> Segments:
        """Packed sequences (cu_seqlens (S + 1,) over `total` tokens): sequence s is stream s's one segment.
        A CPU cu_seqlens is checked (start at 0, non-decreasing, end at total); a device one is trusted (no
        host sync)."""
        if cu_seqlens.dim() != 1 or cu_seqlens.numel() < 1:
            raise ValueError("cu_seqlens must be a non-empty 1-D tensor")
        if cu_seqlens.device.type == "cpu":
            check_cu(cu_seqlens.numpy(), total)
        cu = cu_seqlens.to(torch.int64)
        lengths = cu.diff()  # (S,)
        streams = torch.arange(lengths.numel(), device=cu.device)  # (S,)
        seg = torch.repeat_interleave(streams, lengths, output_size=total)  # (T,)
        t = torch.arange(total, device=cu.device)  # (T,)
        start = t == cu.index_select(0, seg)  # (T,)
        last = torch.where(lengths > 0, cu[1:] - 1, -1)  # (S,)
        return Segments(start, torch.ones_like(start), seg, last)


def check_cu(cu: np.ndarray, total: int) -> None:
    if cu[0] != 0 or cu[-1] != total or (np.diff(cu) < 0).any():
        raise ValueError(f"cu_seqlens must start at 0, be non-decreasing and end at T={total}")


def as_segments(seqs: Tensor | Segments, total: int) -> Segments:
    """cu_seqlens (S + 1,) or Segments over `total` tokens -> Segments."""
    return seqs if isinstance(seqs, Segments) else Segments.of_cu_seqlens(seqs, total)
