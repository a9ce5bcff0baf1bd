"""The fixed-shape step's segmented packs (`model.ops.segments.Segments`): frustums and streams.

A pack has T tokens (its bucket size): real tokens first, in segment order, then padding. A segment is a
run of consecutive real tokens with the same key (frustum, stream); every padding token is a segment of its
own, so padding never feeds into a real token. All builders use only fixed-shape ops (no host sync).
"""

from __future__ import annotations

import torch
from torch import Tensor

from model.geometry.sparse_tensor import BATCH, THETA
from model.ops.segments import Segments


def _starts(key: Tensor, valid: Tensor) -> Tensor:
    """Segment starts of a pack whose real tokens are grouped by key (T,) -> (T,) bool."""
    prev_key = torch.cat([key[:1], key[:-1]])  # (T,)
    prev_valid = torch.cat([valid.new_zeros(1), valid[:-1]])  # (T,) the first token has no predecessor
    return ~valid | ~prev_valid | (key != prev_key)


def frustum_segments(
    coords: Tensor, valid: Tensor, theta_bins: int, frustum_theta_bins: int
) -> tuple[Segments, Segments]:
    """Frustum segments of a pack sorted by (batch, theta, r, z), padding rows at the end.

    coords (T, 4) int64 (batch, r, theta, z), valid (T,) bool. A segment = one frustum's rows
    (batch, theta // frustum_theta_bins), as `frustum_cu_seqlens`. Returns (forward pack, backward pack),
    the backward one for the tokens flipped along dim 0. No carried state: seg is zeros, last is empty.
    """
    n_frustums = -(-theta_bins // frustum_theta_bins)
    key = coords[:, BATCH] * n_frustums + coords[:, THETA] // frustum_theta_bins  # (T,)
    seg = torch.zeros_like(key)  # (T,)
    last = key.new_zeros(0)  # (0,)
    fwd = Segments(_starts(key, valid), valid, seg, last)
    valid_b = valid.flip(0)  # (T,)
    bwd = Segments(_starts(key.flip(0), valid_b), valid_b, seg, last)
    return fwd, bwd


def stream_segments(batch: Tensor, valid: Tensor, num_streams: int) -> Segments:
    """One segment per stream: tokens sorted by batch (T,) int64 in [0, num_streams), padding at the end.

    Stream s's tokens continue state s; last[s] is its last token, -1 when it has none.
    """
    key = torch.where(valid, batch, num_streams)  # (T,) sorted: padding keys after every stream
    streams = torch.arange(num_streams, device=batch.device)  # (S,)
    lo = torch.searchsorted(key, streams)  # (S,)
    hi = torch.searchsorted(key, streams, right=True)  # (S,)
    last = torch.where(hi > lo, hi - 1, -1)  # (S,)
    seg = batch.clamp(0, max(num_streams - 1, 0))  # (T,)
    return Segments(_starts(key, valid), valid, seg, last)
