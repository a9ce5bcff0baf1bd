"""Selective scan (Mamba's S6 recurrence) over packed variable-length sequences: the plain-torch twins.

For every sequence of the pack (tokens concatenated along dim 0, described by `cu_seqlens`):

    h_t = exp(delta_t * A) * h_{t-1} + delta_t * B_t * u_t      (ZOH for A, Euler for B)   # (D, N)
    y_t = sum_n C_t,n * h_t,:,n                                                           # (D,)

with h_{-1} = h0 of that sequence (zeros when h0 is None). No D skip and no gating here. A is (D, N), or
(D, 1) when the N states of a channel share one decay (`MambaConfig.shared_decay`): then exp(delta_t * A) is
computed once per channel and broadcast over N.

Implementations (`ScanImpl`; `model.ops.scan.selective_scan` dispatches, AUTO picks TRITON on CUDA where
Triton is installed, else CHUNKED):
- `selective_scan_ref`: a plain sequential loop; slow, the ground truth.
- `selective_scan_chunked`: every sequence is cut into chunks of `chunk_size` tokens; all chunks are laid
  out position-major without padding (chunks sorted by length, like a PackedSequence); the chunks that are
  not the last of their sequence are scanned from zero in parallel (a loop over chunk positions) to get
  their local final states; the state entering every chunk follows in closed form by a loop over the
  chunk index (c_{j+1} = exp(A * sum(delta over chunk j)) * c_j + local_final_j, all sequences at once);
  then all chunks are scanned in parallel from their entering states, which gives the outputs and the
  final states. Only exponentials of non-positive numbers appear.
- `model.ops.scan_triton.selective_scan_triton` (CUDA): the same chunked algorithm as three Triton kernels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor


def compute_dtype(*tensors: Tensor) -> torch.dtype:
    """float64 if any input is float64, else float32 (half inputs are computed in float32)."""
    return torch.float64 if any(t.dtype == torch.float64 for t in tensors) else torch.float32


def check_inputs(u: Tensor, delta: Tensor, A: Tensor, B: Tensor, C: Tensor, cu: Tensor, h0: Tensor | None):
    T, D = u.shape
    N = B.shape[1] if B.dim() == 2 else -1
    if delta.shape != (T, D) or A.shape not in ((D, N), (D, 1)) or B.shape != (T, N) or C.shape != (T, N):
        raise ValueError(
            f"selective scan shapes: u {tuple(u.shape)}, delta {tuple(delta.shape)}, A {tuple(A.shape)}, "
            f"B {tuple(B.shape)}, C {tuple(C.shape)}; "
            "expected (T, D), (T, D), (D, N) or (D, 1), (T, N), (T, N)"
        )
    if cu.dim() != 1 or cu.numel() < 1:
        raise ValueError("cu_seqlens must be a non-empty 1-D tensor")
    S = cu.numel() - 1
    if h0 is not None and h0.shape != (S, D, N):
        raise ValueError(f"h0 has shape {tuple(h0.shape)}, expected {(S, D, N)}")


def check_cu(cu: np.ndarray, total: int) -> None:
    if cu[0] != 0 or cu[-1] != total or (np.diff(cu) < 0).any():
        raise ValueError(f"cu_seqlens must start at 0, be non-decreasing and end at T={total}")


def selective_scan_ref(
    u: Tensor, delta: Tensor, A: Tensor, B: Tensor, C: Tensor, cu_seqlens: Tensor, h0: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """Sequential reference. u, delta (T, D); A (D, N), or (D, 1) for a decay shared by the N states of a
    channel; B, C (T, N); h0 (S, D, N) or None.

    Returns y (T, D) in u's dtype and the final states (S, D, N) (float32, float64 for float64 inputs).
    """
    check_inputs(u, delta, A, B, C, cu_seqlens, h0)
    cd = compute_dtype(u, delta, A, B, C)
    bounds = cu_seqlens.tolist()
    check_cu(np.asarray(bounds), u.shape[0])
    u_, delta_, A_, B_, C_ = (t.to(cd) for t in (u, delta, A, B, C))
    D, N = A.shape[0], B.shape[1]
    ys: list[Tensor] = []
    finals: list[Tensor] = []
    for s in range(len(bounds) - 1):
        h = u.new_zeros((D, N), dtype=cd) if h0 is None else h0[s].to(cd)  # (D, N)
        for t in range(bounds[s], bounds[s + 1]):
            decay = torch.exp(delta_[t, :, None] * A_)  # (D, N) or (D, 1)
            h = decay * h + (delta_[t] * u_[t])[:, None] * B_[t][None, :]  # (D, N)
            ys.append(h @ C_[t])  # (D,)
        finals.append(h)
    y = torch.stack(ys) if ys else u.new_zeros((0, D), dtype=cd)  # (T, D)
    final = torch.stack(finals) if finals else u.new_zeros((0, D, N), dtype=cd)  # (S, D, N)
    return y.to(u.dtype), final


@dataclass(frozen=True)
class _Layout:
    """Chunks of all sequences laid out position-major: block k holds position k of the chunks longer
    than k, chunks sorted by length (descending), so each block is a prefix of the previous one.

    Chunk order: first the "full" chunks (not the last of their sequence; all chunk_size long) in
    j-major carry order (chunk index j, then sequence rank), then the last chunk of every non-empty
    sequence, by length descending. Sequence "rank" = position in the carry order (chunk count desc).
    """

    block_sizes: list[int]  # (W,) chunks active at position k
    num_full: int  # chunks that are not the last of their sequence
    seq_counts: list[int]  # sequences with more than j chunks, j = 0..max_chunks-1
    packed_to_token: Tensor  # (T,) int64
    token_to_packed: Tensor  # (T,) int64
    full_positions: Tensor  # (chunk_size * num_full,) packed index of position k of full chunk c, k-major
    rank_seq: Tensor  # (R,) sequence id of rank r (non-empty sequences only)
    last_seq: Tensor  # (R,) sequence id of each last chunk
    last_rank: Tensor  # (R,) rank of each last chunk's sequence
    last_pos: Tensor  # (R,) packed index of each sequence's final token, last-chunk order


def _excl_cumsum(a: np.ndarray) -> np.ndarray:
    out = np.zeros_like(a)
    np.cumsum(a[:-1], out=out[1:])
    return out


def _build_layout(cu_seqlens: Tensor, chunk_size: int, total: int) -> _Layout:
    """Index arithmetic on the host (one transfer of cu_seqlens), results moved to cu_seqlens' device."""
    K = chunk_size
    cu = cu_seqlens.cpu().numpy().astype(np.int64)
    check_cu(cu, total)
    lengths = np.diff(cu)  # (S,)
    n_chunks = (lengths + K - 1) // K  # (S,)
    rank_seq = np.argsort(-n_chunks, kind="stable")[: int((n_chunks > 0).sum())]  # (R,)
    R = rank_seq.size
    max_chunks = int(n_chunks.max()) if lengths.size else 0
    seq_counts = (n_chunks[None, :] > np.arange(max_chunks)[:, None]).sum(1)  # (J,)
    # full chunks, j-major: chunk j of the sequences of rank < seq_counts[j + 1]
    full_counts = seq_counts[1:]
    n_full = int(full_counts.sum())
    full_j = np.repeat(np.arange(full_counts.size), full_counts)  # (NF,)
    full_seq = rank_seq[np.arange(n_full) - _excl_cumsum(full_counts)[full_j]]  # (NF,)
    # last chunks, longest first
    last_len_all = np.where(n_chunks > 0, lengths - (n_chunks - 1) * K, -1)  # (S,)
    last_seq = np.argsort(-last_len_all, kind="stable")[:R]  # (R,)
    last_len = last_len_all[last_seq]  # (R,)
    start = np.concatenate([cu[full_seq] + full_j * K, cu[last_seq] + (n_chunks[last_seq] - 1) * K])  # (NC,)
    chunk_len = np.concatenate([np.full(n_full, K), last_len])  # (NC,) non-increasing
    width = int(chunk_len[0]) if chunk_len.size else 0
    block_sizes = (chunk_len[None, :] > np.arange(width)[:, None]).sum(1)  # (W,)
    block_starts = _excl_cumsum(block_sizes)  # (W,)
    pos_k = np.repeat(np.arange(width), block_sizes)  # (T,)
    packed_to_token = start[np.arange(total) - block_starts[pos_k]] + pos_k  # (T,)
    token_to_packed = np.empty(total, dtype=np.int64)
    token_to_packed[packed_to_token] = np.arange(total)
    full_positions = (block_starts[:, None] + np.arange(n_full)[None, :]).reshape(-1) if n_full else pos_k[:0]
    rank_of_seq = np.zeros(lengths.size, dtype=np.int64)
    rank_of_seq[rank_seq] = np.arange(R)
    last_pos = block_starts[last_len - 1] + n_full + np.arange(R)  # (R,)

    last_rank = rank_of_seq[last_seq]  # (R,)
    index_arrays = [packed_to_token, token_to_packed, full_positions, rank_seq, last_seq, last_rank, last_pos]
    flat = np.concatenate(index_arrays).astype(np.int64)
    flat = torch.from_numpy(flat).to(cu_seqlens.device)  # one host-to-device transfer
    p2t, t2p, full_pos, r_seq, l_seq, l_rank, l_pos = flat.split([a.size for a in index_arrays])
    return _Layout(
        block_sizes=block_sizes.tolist(),
        num_full=n_full,
        seq_counts=seq_counts.tolist(),
        packed_to_token=p2t,
        token_to_packed=t2p,
        full_positions=full_pos,
        rank_seq=r_seq,
        last_seq=l_seq,
        last_rank=l_rank,
        last_pos=l_pos,
    )


def _local_finals(E: list[Tensor], dBu: list[Tensor], num_full: int) -> Tensor:
    """Final state of every full chunk scanned from zero state -> (NF, N, D), j-major order.

    E, dBu: the position blocks of the packed (T, N, D) tensors (block k: (m_k, N, D)).
    """
    h = dBu[0][:num_full]  # (NF, N, D)
    for e, b in zip(E[1:], dBu[1:], strict=True):
        h = torch.addcmul(b[:num_full], e[:num_full], h)
    return h


def _carry(
    decay: Tensor, local_final: Tensor, h_start: Tensor, seq_counts: list[int]
) -> tuple[Tensor, Tensor]:
    """States entering the chunks, in closed form over the chunk index.

    decay, local_final (NF, N, D) for the full chunks (j-major); h_start (R, N, D) by rank.
    Returns (entering states of the full chunks (NF, N, D), of the last chunks by rank (R, N, D)).
    """
    counts = seq_counts[1:]  # full chunks per chunk index j
    entering_full: list[Tensor] = []
    entering_last: list[Tensor] = []  # pieces by descending rank ranges
    state = h_start  # (n_j, N, D)
    for n_next, dec, fin in zip(counts, decay.split(counts), local_final.split(counts), strict=True):
        entering_last.append(state[n_next:])  # chunk j is the last one of these sequences
        entering_full.append(state[:n_next])
        state = torch.addcmul(fin, dec, state[:n_next])
    entering_last.append(state)
    full = torch.cat(entering_full) if entering_full else local_final[:0]
    return full, torch.cat(entering_last[::-1])


def _scan_all(E: list[Tensor], dBu: list[Tensor], h_in: Tensor, inplace: bool) -> list[Tensor]:
    """Scan every chunk from its entering state h_in (NC, N, D) -> states, position blocks (m_k, N, D).

    With `inplace` (no autograd) the states are accumulated into dBu's storage.
    """
    if inplace:
        dBu[0].addcmul_(E[0], h_in)
        for k in range(1, len(dBu)):
            dBu[k].addcmul_(E[k], dBu[k - 1][: dBu[k].shape[0]])
        return dBu
    hs = [torch.addcmul(dBu[0], E[0], h_in)]
    for e, b in zip(E[1:], dBu[1:], strict=True):
        hs.append(torch.addcmul(b, e, hs[-1][: b.shape[0]]))
    return hs


def selective_scan_chunked(
    u: Tensor,
    delta: Tensor,
    A: Tensor,
    B: Tensor,
    C: Tensor,
    cu_seqlens: Tensor,
    h0: Tensor | None = None,
    chunk_size: int = 32,
) -> tuple[Tensor, Tensor]:
    """Chunked parallel scan; same contract as `selective_scan_ref`."""
    check_inputs(u, delta, A, B, C, cu_seqlens, h0)
    if chunk_size < 1:
        raise ValueError("chunk_size must be >= 1")
    T, D = u.shape
    N = B.shape[1]
    S = cu_seqlens.numel() - 1
    cd = compute_dtype(u, delta, A, B, C)
    h_init = u.new_zeros((S, D, N), dtype=cd) if h0 is None else h0.to(cd)  # (S, D, N)
    lay = _build_layout(cu_seqlens, chunk_size, T)
    if T == 0:
        return u.new_zeros((0, D)), h_init
    inplace = not (torch.is_grad_enabled() and any(t.requires_grad for t in (u, delta, A, B, C, h_init)))
    # internal layout: states (.., N, D) so that the long channel dim is the contiguous one
    p2t = lay.packed_to_token
    dp = delta.index_select(0, p2t).to(cd)  # (T, D) packed order
    At = A.to(cd).t().contiguous()  # (N, D), or (1, D) for a shared decay (broadcast over N below)
    E = torch.mul(dp[:, None, :], At)  # (T, N, D) or (T, 1, D)
    E = E.exp_() if inplace else E.exp()
    du = dp * u.index_select(0, p2t).to(cd)  # (T, D)
    dBu = du[:, None, :] * B.index_select(0, p2t).to(cd)[:, :, None]  # (T, N, D)
    E_blocks, dBu_blocks = E.split(lay.block_sizes), dBu.split(lay.block_sizes)  # views, (m_k, N, D) each
    nf = lay.num_full
    h_rank = h_init.transpose(1, 2).index_select(0, lay.rank_seq).contiguous()  # (R, N, D)
    if nf:
        delta_sum = dp.index_select(0, lay.full_positions).view(-1, nf, D).sum(0)  # (NF, D)
        decay = torch.exp(delta_sum[:, None, :] * At)  # (NF, N, D) or (NF, 1, D)
        entering_full, entering_last = _carry(
            decay, _local_finals(E_blocks, dBu_blocks, nf), h_rank, lay.seq_counts
        )
    else:
        entering_full, entering_last = h_rank[:0], h_rank
    h_in = torch.cat([entering_full, entering_last.index_select(0, lay.last_rank)])  # (NC, N, D)
    H_blocks = _scan_all(E_blocks, dBu_blocks, h_in, inplace)
    H = dBu if inplace else torch.cat(H_blocks)  # (T, N, D) packed
    Cp = C.index_select(0, p2t).to(cd)  # (T, N)
    y = (H * Cp[:, :, None]).sum(1)  # (T, D) packed (a batch of (1, N) @ (N, D) matmuls is slower on CPU)
    final = h_init.index_copy(0, lay.last_seq, H.index_select(0, lay.last_pos).transpose(1, 2))  # (S, D, N)
    return y.index_select(0, lay.token_to_packed).to(u.dtype), final
