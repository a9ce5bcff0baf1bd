"""Selective scan (Mamba's S6 recurrence) over a segmented pack (`model.ops.segments`): the plain-torch twins.

For every token t of the pack, with h the state of t's segment:

    h = h0[seg[t]] (zeros without h0)                                  where t starts a segment
    h = exp(delta_t * A) * h + delta_t * B_t * u_t    (ZOH for A, Euler for B)          # (D, N)
    y_t = sum_n C_t,n * h_:,n                         (0 on padding tokens)             # (D,)

and stream s's final state is h at its last token (h0[s], or zeros, where it has none). No D skip and no
gating here. A is (D, N), or (D, 1) when the N states of a channel share one decay
(`MambaConfig.shared_decay`): then exp(delta_t * A) is computed once per channel and broadcast over N.
Packed variable-length sequences with initial states (cu_seqlens, h0) are the special case of one segment per
sequence; every function here takes either.

Implementations (`ScanImpl`; `model.ops.scan.selective_scan` dispatches):
- `selective_scan_ref`: a plain sequential loop; slow, the ground truth.
- `selective_scan_chunked`: fixed shapes and no host sync (torch.compile takes it whole). With
  E_t = exp(delta_t A) and dBu_t = delta_t B_t u_t, a start t continues from h0[seg[t]] instead of h_{t-1}:
  set E'_t = 0 and dBu'_t = dBu_t + E_t h0[seg[t]] there, and the whole pack becomes one plain linear
  recurrence h_t = E'_t h_{t-1} + dBu'_t, computed in chunks of K tokens (T padded to a multiple of K):
    1. inside every chunk, from zero state, a loop over the K positions on (chunks, N, D) tensors gives the
       local states and the running decay products P;
    2. the states entering the chunks follow from a Hillis-Steele scan over the chunk index of the pairs
       (P_last, h_local_last) composed as (a2, b2) o (a1, b1) = (a2 a1, a2 b1 + b2): ceil(log2(chunks)) steps;
    3. h = h_local + P * entering state.
  Padding tokens get delta = 0 (E = 1, dBu = 0) and are starts, so they stay finite and never reach a real
  token. Only exponentials of non-positive numbers appear.
- `model.ops.scan_numba` (CPU) and `model.ops.scan_triton` (CUDA): the fast twins.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from model.ops.segments import Segments, as_segments


def compute_dtype(*tensors: Tensor) -> torch.dtype:
    """float64 if any input is float64, else float32 (half inputs are computed in float32)."""
    return torch.float64 if any(t.dtype == torch.float64 for t in tensors) else torch.float32


def check_inputs(
    u: Tensor, delta: Tensor, A: Tensor, B: Tensor, C: Tensor, seqs: Tensor | Segments, h0: Tensor | None
) -> Segments:
    """The shapes of the contract (module docstring) -> the pack as Segments (from cu_seqlens, checked)."""
    T, D = u.shape
    N = B.shape[1] if B.dim() == 2 else -1
    if delta.shape != (T, D) or A.shape not in ((D, N), (D, 1)) or B.shape != (T, N) or C.shape != (T, N):
        raise ValueError(
            f"selective scan shapes: u {tuple(u.shape)}, delta {tuple(delta.shape)}, A {tuple(A.shape)}, "
            f"B {tuple(B.shape)}, C {tuple(C.shape)}; "
            "expected (T, D), (T, D), (D, N) or (D, 1), (T, N), (T, N)"
        )
    segs = as_segments(seqs, T)
    if segs.total != T:
        raise ValueError(f"segments describe {segs.total} tokens, the inputs have {T}")
    S = segs.num_streams
    if h0 is not None and h0.shape != (S, D, N):
        raise ValueError(f"h0 has shape {tuple(h0.shape)}, expected {(S, D, N)}")
    return segs


def selective_scan_ref(
    u: Tensor,
    delta: Tensor,
    A: Tensor,
    B: Tensor,
    C: Tensor,
    seqs: Tensor | Segments,
    h0: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """Sequential reference. u, delta (T, D); A (D, N), or (D, 1) for a decay shared by the N states of a
    channel; B, C (T, N); seqs: cu_seqlens (S + 1,) or Segments over T tokens and S streams; h0 (S, D, N) or
    None (zeros).

    Returns y (T, D) in u's dtype and the final states (S, D, N) (float32, float64 for float64 inputs).
    """
    segs = check_inputs(u, delta, A, B, C, seqs, h0)
    cd = compute_dtype(u, delta, A, B, C)
    start, valid, seg, last = (t.tolist() for t in (segs.start, segs.valid, segs.seg, segs.last))
    u_, delta_, A_, B_, C_ = (t.to(cd) for t in (u, delta, A, B, C))
    D, N = A.shape[0], B.shape[1]
    zero = u.new_zeros((D, N), dtype=cd)
    owner = {t: s for s, t in enumerate(last) if t >= 0}  # the stream whose last token t is
    finals: list[Tensor] = [zero if h0 is None else h0[s].to(cd) for s in range(len(last))]
    ys: list[Tensor] = []
    h = zero
    for t in range(len(start)):
        if not valid[t]:
            ys.append(u.new_zeros(D, dtype=cd))
            continue
        if start[t]:
            h = zero if h0 is None else h0[seg[t]].to(cd)  # (D, N)
        decay = torch.exp(delta_[t, :, None] * A_)  # (D, N) or (D, 1)
        h = decay * h + (delta_[t] * u_[t])[:, None] * B_[t][None, :]  # (D, N)
        ys.append(h @ C_[t])  # (D,)
        if t in owner:
            finals[owner[t]] = h
    y = torch.stack(ys) if ys else u.new_zeros((0, D), dtype=cd)  # (T, D)
    final = torch.stack(finals) if finals else u.new_zeros((0, D, N), dtype=cd)  # (S, D, N)
    return y.to(u.dtype), final


def _chunk_states(E: Tensor, dBu: Tensor, inplace: bool) -> tuple[Tensor, Tensor]:
    """Scan every chunk from zero state, position-major: E (K, C, N | 1, D), dBu (K, C, N, D) -> (local
    states (K, C, N, D), running products of E (K, C, N | 1, D)). With `inplace` (no autograd) they are
    accumulated into dBu's and E's storage (a loop of small products beats cumprod over dim 0 on CPU)."""
    if inplace:
        for k in range(1, dBu.shape[0]):
            dBu[k].addcmul_(E[k], dBu[k - 1])
            E[k].mul_(E[k - 1])
        return dBu, E
    hs = [dBu[0]]  # (C, N, D) each
    for k in range(1, dBu.shape[0]):
        hs.append(torch.addcmul(dBu[k], E[k], hs[-1]))
    return torch.stack(hs), E.cumprod(0)


def _entering_states(decay: Tensor, final: Tensor) -> Tensor:
    """States entering every chunk from the chunks' total decay (C, N | 1, D) and local final states
    (C, N, D): an inclusive Hillis-Steele scan over the chunk index, shifted by one -> (C, N, D)."""
    n = decay.shape[0]
    a, b = decay, final
    step = 1
    for _ in range(math.ceil(math.log2(n)) if n > 1 else 0):
        a_prev = torch.cat([torch.ones_like(a[:step]), a[:-step]])  # (C, N | 1, D) identity before chunk 0
        b_prev = torch.cat([torch.zeros_like(b[:step]), b[:-step]])  # (C, N, D)
        a, b = a * a_prev, torch.addcmul(b, a, b_prev)
        step *= 2
    return torch.cat([torch.zeros_like(b[:1]), b[:-1]])  # (C, N, D): zero state enters chunk 0


def _position_major(t: Tensor, n_chunks: int, value: float | bool = 0) -> Tensor:
    """(T, ...) -> (K, C, ...): token c * K + k at [k, c]; the n_chunks * K - T tail filled with value."""
    shape = (n_chunks * (-(-t.shape[0] // n_chunks)) - t.shape[0], *t.shape[1:])
    full = torch.cat([t, torch.full(shape, value, dtype=t.dtype, device=t.device)])  # (C * K, ...)
    return full.view(n_chunks, -1, *t.shape[1:]).transpose(0, 1).contiguous()


def selective_scan_chunked(
    u: Tensor,
    delta: Tensor,
    A: Tensor,
    B: Tensor,
    C: Tensor,
    seqs: Tensor | Segments,
    h0: Tensor | None = None,
    chunk_size: int = 32,
) -> tuple[Tensor, Tensor]:
    """Chunked parallel scan, fixed shapes; same contract as `selective_scan_ref`."""
    if chunk_size < 1:
        raise ValueError("chunk_size must be >= 1")
    segs = check_inputs(u, delta, A, B, C, seqs, h0)
    T, D = u.shape
    N, S = B.shape[1], segs.num_streams
    cd = compute_dtype(u, delta, A, B, C)
    h_init = u.new_zeros((S, D, N), dtype=cd) if h0 is None else h0.to(cd)  # (S, D, N)
    if T == 0:
        return u.new_zeros((0, D)), h_init
    nc = -(-T // chunk_size)  # chunks; the tail of the last one is padding
    inplace = not (torch.is_grad_enabled() and any(t.requires_grad for t in (u, delta, A, B, C, h_init)))
    valid = segs.valid[:, None]  # (T, 1)
    dt = torch.where(valid, delta.to(cd), 0.0)  # (T, D): padding decays by exp(0) = 1, adds nothing
    du = _position_major(torch.where(valid, dt * u.to(cd), 0.0), nc)  # (K, C, D)
    Bp = _position_major(B.to(cd), nc)  # (K, C, N)
    start = _position_major(segs.start, nc, True)[:, :, None, None]  # (K, C, 1, 1)
    E = torch.exp(_position_major(dt, nc)[:, :, None, :] * A.to(cd).t())  # (K, C, N | 1, D)
    dBu = du[:, :, None, :] * Bp[..., None]  # (K, C, N, D)
    if h0 is not None:
        seg = _position_major(segs.seg.clamp(0, max(S - 1, 0)), nc)  # (K, C)
        h_in = h_init.transpose(1, 2)[seg] if S else torch.zeros_like(dBu)  # (K, C, N, D)
        dBu = torch.where(start, torch.addcmul(dBu, E, h_in), dBu)  # (K, C, N, D)
    E = torch.where(start, 0.0, E)  # (K, C, N | 1, D)
    H, P = _chunk_states(E, dBu, inplace)  # (K, C, N, D), (K, C, N | 1, D) decay from the chunk's start
    entering = _entering_states(P[-1], H[-1])  # (C, N, D)
    H = H.addcmul_(P, entering) if inplace else torch.addcmul(H, P, entering)  # (K, C, N, D)
    y = (H * _position_major(C.to(cd), nc)[..., None]).sum(2)  # (K, C, D)
    y = y.transpose(0, 1).reshape(-1, D)[:T]  # (T, D)
    y = torch.where(valid, y, 0.0).to(u.dtype)
    last = segs.last.clamp(min=0)  # (S,)
    K = H.shape[0]
    h_last = H.view(-1, N, D).index_select(0, (last % K) * nc + last // K).transpose(1, 2)  # (S, D, N)
    return y, torch.where((segs.last >= 0)[:, None, None], h_last, h_init)
