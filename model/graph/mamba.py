"""Fixed-shape Mamba over a segmented pack (`Segments`): the eager `model.layers.mamba.Mamba` without
cu_seqlens, host syncs or data-dependent shapes, for torch.compile(fullgraph=True) and CUDA graphs.

Segmented scan: with E_t = exp(delta_t A) and dBu_t = delta_t B_t u_t, a segment start t continues from its
stream's carried state h0[seg[t]] instead of h_{t-1}; set E'_t = 0 and dBu'_t = dBu_t + E_t h0[seg[t]] there
(E' = E elsewhere), and the whole pack becomes one plain linear recurrence h_t = E'_t h_{t-1} + dBu'_t.
It is computed in chunks of K tokens (T padded to a multiple of K):
  1. inside every chunk, from zero state, a loop over the K positions on (chunks, N, D) tensors gives the
     local states and the running decay products P (inductor fuses the unrolled chain);
  2. the states entering the chunks follow from a Hillis-Steele scan over the chunk index of the pairs
     (P_last, h_local_last) composed as (a2, b2) o (a1, b1) = (a2 a1, a2 b1 + b2): ceil(log2(chunks)) steps;
  3. h = h_local + P * entering state.
Padding tokens get delta = 0 (E = 1, dBu = 0) and are segment starts, so they stay finite and never reach a
real token. Causal conv: the input `lag` steps back is x[t - lag] inside the segment, else a column of the
stream's conv state, both gathered from one extended tensor [x; state columns].
"""

from __future__ import annotations

import logging
import math

import torch
import torch.nn.functional as F
from torch import Tensor

from model.graph.scan_cpu import segmented_scan_cpu
from model.graph.segments import Segments
from model.layers.mamba import Mamba, MambaState
from model.ops.scan_torch import compute_dtype
from model.ops.triton_support import triton_available

log = logging.getLogger(__name__)
_announced: set[bool] = set()  # the CUDA scan paths logged so far


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


def segmented_scan(
    u: Tensor,
    delta: Tensor,
    A: Tensor,
    B: Tensor,
    C: Tensor,
    segs: Segments,
    h0: Tensor | None = None,
    chunk_size: int = 32,
) -> tuple[Tensor, Tensor | None]:
    """Selective scan (`model.ops.scan_torch` contract) over a segmented pack, state reset at every start.

    u, delta (T, D); A (D, N) or (D, 1); B, C (T, N); h0 (S, D, N) or None (zeros). A start token t
    continues from h0[seg[t]]. Returns y (T, D) in u's dtype (zeros on padding) and, when h0 is given, the
    final states (S, D, N) (float32, float64 for float64 inputs): h at last[s], or h0[s] where last[s] = -1.
    """
    T, D = u.shape
    N = B.shape[1]
    cd = compute_dtype(u, delta, A, B, C)
    nc = max(-(-T // chunk_size), 1)  # chunks; the tail of the last one is padding
    inplace = not (torch.is_grad_enabled() and any(t.requires_grad for t in (u, delta, A, B, C)))
    valid = segs.valid[:, None]  # (T, 1)
    dt = torch.where(valid, delta.to(cd), 0.0)  # (T, D): padding decays by exp(0) = 1, adds nothing
    du = _position_major(torch.where(valid, dt * u.to(cd), 0.0), nc)  # (K, C, D)
    Bp = _position_major(B.to(cd), nc)  # (K, C, N)
    start = _position_major(segs.start, nc, True)[:, :, None, None]  # (K, C, 1, 1)
    E = torch.exp(_position_major(dt, nc)[:, :, None, :] * A.to(cd).t())  # (K, C, N | 1, D)
    dBu = du[:, :, None, :] * Bp[..., None]  # (K, C, N, D)
    if h0 is not None:
        seg = _position_major(segs.seg, nc)  # (K, C)
        h_in = h0.to(cd).transpose(1, 2)[seg]  # (K, C, N, D)
        dBu = torch.where(start, torch.addcmul(dBu, E, h_in), dBu)  # (K, C, N, D)
    E = torch.where(start, 0.0, E)  # (K, C, N | 1, D)
    H, P = _chunk_states(E, dBu, inplace)  # (K, C, N, D), (K, C, N | 1, D) decay from the chunk's start
    entering = _entering_states(P[-1], H[-1])  # (C, N, D)
    H = H.addcmul_(P, entering) if inplace else torch.addcmul(H, P, entering)  # (K, C, N, D)
    y = (H * _position_major(C.to(cd), nc)[..., None]).sum(2)  # (K, C, D)
    y = y.transpose(0, 1).reshape(-1, D)[:T]  # (T, D)
    y = torch.where(valid, y, 0.0).to(u.dtype)
    if h0 is None:
        return y, None
    last = segs.last.clamp(min=0)  # (S,)
    K = H.shape[0]
    h_last = H.view(-1, N, D).index_select(0, (last % K) * nc + last // K).transpose(1, 2)  # (S, D, N)
    return y, torch.where((segs.last >= 0)[:, None, None], h_last, h0.to(cd))


@torch.library.custom_op("phim::segmented_scan", mutates_args=())
def segmented_scan_op(
    u: Tensor,
    delta: Tensor,
    A: Tensor,
    B: Tensor,
    C: Tensor,
    start: Tensor,
    valid: Tensor,
    seg: Tensor,
    last: Tensor,
    h0: Tensor | None,
    chunk_size: int,
) -> tuple[Tensor, Tensor]:
    """`segmented_scan` as a torch custom op: torch.compile calls it as one opaque op (inductor's CPU code
    for the unrolled chunk loop recomputes the chain and runs 3-4x slower than these aten ops). On CPU it
    runs the numba kernel (`model.graph.scan_cpu`), on CUDA the Triton kernels (`model.graph.scan_triton`)
    where triton is installed, elsewhere `segmented_scan`, their reference twin.
    Returns (y (T, D), final states (S, D, N), or (0,) without h0)."""
    y, final = segmented_scan(u, delta, A, B, C, Segments(start, valid, seg, last), h0, chunk_size)
    return y.contiguous(), final.contiguous() if final is not None else u.new_zeros(0)


@segmented_scan_op.register_kernel("cpu")
def _(u, delta, A, B, C, start, valid, seg, last, h0, chunk_size):
    y, final = segmented_scan_cpu(u, delta, A, B, C, Segments(start, valid, seg, last), h0)
    return y, final if final is not None else u.new_zeros(0)


@segmented_scan_op.register_kernel("cuda")
def _(u, delta, A, B, C, start, valid, seg, last, h0, chunk_size):
    fast = triton_available(u.device) and compute_dtype(u, delta, A, B, C) == torch.float32
    if fast not in _announced:
        _announced.add(fast)
        log.info("graph step's segmented scan on %s: %s", u.device, "triton" if fast else "torch (reference)")
    segs = Segments(start, valid, seg, last)
    if not fast:  # float64 (tests), or no triton: the torch twin
        y, final = segmented_scan(u, delta, A, B, C, segs, h0, chunk_size)
    else:
        from model.graph.scan_triton import segmented_scan_triton

        y, final = segmented_scan_triton(u, delta, A, B, C, segs, h0)
    return y.contiguous(), final.contiguous() if final is not None else u.new_zeros(0)


@segmented_scan_op.register_fake
def _(u, delta, A, B, C, start, valid, seg, last, h0, chunk_size):
    T, D = u.shape
    final = u.new_empty(0) if h0 is None else h0.new_empty(h0.shape, dtype=compute_dtype(u, delta, A, B, C))
    return u.new_empty(T, D), final


def _conv_indices(segs: Segments, w: int) -> tuple[Tensor, Tensor]:
    """Gather indices into ext = [x (T, di); state columns (S' * w, di)] (row T + s * w + c = column c of
    stream s's conv state, oldest first). Returns (older (w, T): row i = the input w - i steps before each
    token; new_state (S, w): the last w inputs of each stream's segment, oldest first)."""
    T = segs.total
    dev = segs.start.device
    t = torch.arange(T, device=dev)  # (T,)
    pos = t - segs.segment_start()  # (T,) position inside the segment
    lag = torch.arange(w, 0, -1, device=dev)[:, None]  # (w, 1)
    back = pos[None, :] - lag  # (w, T) < 0: before the segment's start
    older = torch.where(back >= 0, t[None, :] - lag, T + segs.seg[None, :] * w + w + back)  # (w, T)
    last = segs.last  # (S,)
    has = last >= 0  # (S,)
    lengths = torch.where(has, pos.index_select(0, last.clamp(min=0)) + 1, 0)  # (S,)
    col = torch.arange(w, device=dev)[None, :]  # (1, w)
    p = lengths[:, None] - w + col  # (S, w) position inside the segment
    s_idx = torch.arange(last.shape[0], device=dev)[:, None]  # (S, 1)
    new_state = torch.where(p >= 0, last[:, None] - (w - 1) + col, T + s_idx * w + col + lengths[:, None])
    return older, new_state


def _conv(layer: Mamba, x: Tensor, segs: Segments, conv_state: Tensor) -> tuple[Tensor, Tensor]:
    """Causal depthwise conv: x (T, di), conv_state (S', di, w) -> (T, di), new conv state (S, di, w)."""
    di = x.shape[1]
    k = layer.cfg.d_conv
    older, new_idx = _conv_indices(segs, k - 1)  # (k - 1, T), (S, k - 1)
    state_rows = conv_state.to(x.dtype).transpose(1, 2).reshape(-1, di)  # (S' * (k - 1), di)
    ext = torch.cat([x, state_rows])  # (T + S' * (k - 1), di)
    weight = layer.conv1d.weight.view(di, k).t()  # (k, di), row k - 1 multiplies the current token
    out = torch.addcmul(layer.conv1d.bias, x, weight[k - 1])  # (T, di)
    for i in range(k - 1):
        out = torch.addcmul(out, ext.index_select(0, older[i]), weight[i])
    new_state = ext.index_select(0, new_idx.reshape(-1)).view(-1, k - 1, di)  # (S, k - 1, di)
    return out, new_state.transpose(1, 2).to(conv_state.dtype)  # keeps its dtype (float32 under autocast)


def mamba_forward(
    layer: Mamba, x: Tensor, segs: Segments, state: MambaState | None = None
) -> tuple[Tensor, MambaState | None]:
    """`Mamba.forward` over a segmented pack: x (T, d_model); state with S = segs.num_streams rows or None
    (zeros, no state returned). Every segment start continues its stream's conv and ssm state.
    Returns (T, d_model) (padding rows: finite, meaningless) and the new MambaState when state is given."""
    cfg = layer.cfg
    xi, z = layer.in_proj(x).chunk(2, dim=-1)  # (T, di) each
    if state is None:  # one zero row serves every segment (seg is in range of it for frustum packs)
        rows = max(segs.num_streams, 1)
        conv_state = x.new_zeros(rows, layer.d_inner, cfg.d_conv - 1)  # (S', di, d_conv - 1)
    else:
        conv_state = state.conv  # (S, di, d_conv - 1)
    xc, new_conv = _conv(layer, xi, segs, conv_state)
    xc = F.silu(xc)  # (T, di)
    dt, B, C = layer.x_proj(xc).split([layer.dt_rank, cfg.d_state, cfg.d_state], dim=-1)
    delta = F.softplus(layer.dt_proj(dt))  # (T, di)
    A = -torch.exp(layer.A_log.to(torch.promote_types(layer.A_log.dtype, torch.float32)))  # (di, n | 1)
    h0 = None if state is None else state.ssm
    y, ssm = segmented_scan_op(
        xc, delta, A, B, C, segs.start, segs.valid, segs.seg, segs.last, h0, cfg.chunk_size
    )  # (T, di), (S, di, N) or (0,)
    y = (y + xc * layer.D.to(y.dtype)) * F.silu(z)  # (T, di)
    out = layer.out_proj(y)  # (T, d_model)
    if state is None:
        return out, None
    return out, MambaState(conv=new_conv, ssm=ssm)
