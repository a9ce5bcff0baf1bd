"""Mamba-1 layer (selective SSM block of the Mamba paper) over packed sequences, with carried state.

    x, z   = split(in_proj(x))                        # (T, d_inner) each
    x      = SiLU(causal depthwise conv1d(x))         # per sequence, continuing from state.conv
    dt, B, C = split(x_proj(x));  delta = softplus(dt_proj(dt))
    y      = selective_scan(x, delta, A=-exp(A_log), B, C) + D * x     # continuing from state.ssm
    out    = out_proj(y * SiLU(z))

A sequence cut into pieces and fed piece by piece with the returned state carried gives exactly the
outputs of one call over the whole sequence (any piece lengths, including 1 and < d_conv - 1).

The layer runs over a `Packing`: packed variable-length sequences (cu_seqlens: the eager model), or a
fixed-length segmented pack with padding (`model.ops.segments.Segments`: the fixed-shape step, with no host
sync and no data-dependent shape). Both are the same segmented pack to the causal conv's gathers and to the
selective scan (`model.ops.scan`), so the layer is written once for both engines.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from model.config import MambaConfig, ScanImpl
from model.ops.scan import selective_scan
from model.ops.segments import Segments


@dataclass
class MambaState:
    """Per-sequence recurrent state of one Mamba layer."""

    conv: Tensor  # (S, d_inner, d_conv - 1): last d_conv - 1 conv inputs, oldest first
    ssm: Tensor  # (S, d_inner, d_state)

    @staticmethod
    def zeros(
        num_seqs: int,
        d_inner: int,
        d_conv: int,
        d_state: int,
        device: torch.device | str | None,
        dtype: torch.dtype = torch.float32,
    ) -> MambaState:
        return MambaState(
            conv=torch.zeros(num_seqs, d_inner, d_conv - 1, device=device, dtype=dtype),
            ssm=torch.zeros(num_seqs, d_inner, d_state, device=device, dtype=dtype),
        )

    @property
    def num_seqs(self) -> int:
        return self.ssm.shape[0]

    def index(self, idx: Tensor) -> MambaState:
        """Select sequences: idx (K,) int64 -> state with K rows."""
        return MambaState(conv=self.conv.index_select(0, idx), ssm=self.ssm.index_select(0, idx))

    @staticmethod
    def cat(states: list[MambaState]) -> MambaState:
        return MambaState(conv=torch.cat([s.conv for s in states]), ssm=torch.cat([s.ssm for s in states]))


def conv_gather_indices(segs: Segments, d_conv: int) -> tuple[Tensor, Tensor]:
    """Gather indices into ext = cat([x (T, C), state rows (S' * (d_conv - 1), C)]) for the causal conv over a
    segmented pack (a segment start continues its stream's conv state, as the scan continues its ssm state).

    Row s * (d_conv - 1) + c of the state part is column c (oldest first) of stream s's conv state.
    Returns (older (d_conv - 1, T): row i = the input d_conv - 1 - i steps before each token;
             new_state (S, d_conv - 1): the last d_conv - 1 inputs of each stream's segment, oldest first).
    """
    w = d_conv - 1
    T = segs.total
    dev = segs.start.device
    t = torch.arange(T, device=dev)  # (T,)
    pos = t - segs.segment_start()  # (T,) position inside the segment
    lag = torch.arange(w, 0, -1, device=dev)[:, None]  # (w, 1)
    back = pos[None, :] - lag  # (w, T) < 0: runs off the segment's start, into the state columns
    older = torch.where(back >= 0, t[None, :] - lag, T + segs.seg[None, :] * w + w + back)  # (w, T)
    last = segs.last  # (S,)
    if T:
        lengths = torch.where(last >= 0, pos.index_select(0, last.clamp(min=0)) + 1, 0)  # (S,)
    else:  # no token: every stream keeps its state
        lengths = torch.zeros_like(last)
    col = torch.arange(w, device=dev)[None, :]  # (1, w)
    p = lengths[:, None] - w + col  # (S, w) position inside the segment
    s_idx = torch.arange(last.shape[0], device=dev)[:, None]  # (S, 1)
    new_state = torch.where(p >= 0, last[:, None] - (w - 1) + col, T + s_idx * w + col + lengths[:, None])
    return older, new_state


@dataclass(frozen=True)
class Packing:
    """A segmented pack and the causal conv's gather indices over it (`conv_gather_indices`).

    Build it once and hand it to every layer that runs over the same packing (the local Mamba layers of
    all PHiM blocks share two): the index arithmetic is a few dozen small ops, a kernel launch each on a GPU.
    `scan`, when set, overrides the layers' `MambaConfig.scan` (the fixed-shape step: an implementation with
    no host sync, `ScanImpl.AUTO`).
    """

    segments: Segments
    older: Tensor  # (d_conv - 1, T)
    new_state: Tensor  # (S, d_conv - 1)
    scan: ScanImpl | None = None

    @staticmethod
    def of(cu_seqlens: Tensor, total: int, d_conv: int) -> Packing:
        """Packed sequences: cu_seqlens (S + 1,) int64 over `total` tokens, sequence s continuing state s."""
        return Packing.of_segments(Segments.of_cu_seqlens(cu_seqlens, total), d_conv)

    @staticmethod
    def of_segments(segs: Segments, d_conv: int, scan: ScanImpl | None = None) -> Packing:
        return Packing(segs, *conv_gather_indices(segs, d_conv), scan)

    @property
    def num_seqs(self) -> int:
        return self.segments.num_streams

    @property
    def total(self) -> int:
        return self.older.shape[1]


class Mamba(nn.Module):
    """Mamba-1 layer on packed sequences: x (T, d_model), cu_seqlens (S + 1,) -> (T, d_model), state."""

    def __init__(self, d_model: int, cfg: MambaConfig):
        super().__init__()
        self.cfg = cfg
        self.d_model = d_model
        self.d_inner = cfg.expand * d_model
        self.dt_rank = cfg.dt_rank or math.ceil(d_model / 16)
        di, n = self.d_inner, cfg.d_state
        self.in_proj = nn.Linear(d_model, 2 * di, bias=False)
        self.conv1d = nn.Conv1d(di, di, cfg.d_conv, groups=di, bias=True)  # weights only; applied by gathers
        self.x_proj = nn.Linear(di, self.dt_rank + 2 * n, bias=False)
        self.dt_proj = nn.Linear(self.dt_rank, di, bias=True)
        self.out_proj = nn.Linear(di, d_model, bias=False)
        if cfg.shared_decay:  # one decay per channel, A in -[1, 16] as Mamba-2's per-head init
            a = torch.empty(di, 1).uniform_(1.0, 16.0)  # (di, 1)
        else:
            a = torch.arange(1, n + 1, dtype=torch.float32).repeat(di, 1)  # (di, n) S4D-real: A = -(1..n)
        self.A_log = nn.Parameter(torch.log(a))  # (di, n) or (di, 1)
        self.D = nn.Parameter(torch.ones(di))
        self.A_log._no_weight_decay = True
        self.D._no_weight_decay = True
        self._init_dt()

    def _init_dt(self) -> None:
        cfg = self.cfg
        std = self.dt_rank**-0.5
        with torch.no_grad():
            self.dt_proj.weight.uniform_(-std, std)
            log_lo, log_hi = math.log(cfg.dt_min), math.log(cfg.dt_max)
            dt = torch.exp(torch.rand(self.d_inner) * (log_hi - log_lo) + log_lo).clamp(min=cfg.dt_init_floor)
            self.dt_proj.bias.copy_(dt + torch.log(-torch.expm1(-dt)))  # inverse softplus

    def _conv(self, x: Tensor, packing: Packing, conv_state: Tensor) -> tuple[Tensor, Tensor]:
        """Packed causal depthwise conv: x (T, di), conv_state (S', di, d_conv - 1) -> (T, di), new state
        (S, di, d_conv - 1)."""
        di = x.shape[1]
        k = self.cfg.d_conv
        older, new_idx = packing.older, packing.new_state  # (k - 1, T), (S, k - 1)
        state_rows = conv_state.to(x.dtype).transpose(1, 2).reshape(-1, di)  # (S' * (k - 1), di)
        ext = torch.cat([x, state_rows])  # (T + S' * (k - 1), di)
        weight = self.conv1d.weight.view(di, k).t()  # (k, di), row k - 1 multiplies the current token
        out = torch.addcmul(self.conv1d.bias, x, weight[k - 1])  # (T, di)
        for i in range(k - 1):  # older inputs, one gather per lag
            out = out.addcmul_(ext.index_select(0, older[i]), weight[i])
        new_state = ext.index_select(0, new_idx.reshape(-1)).view(-1, k - 1, di)  # (S, k - 1, di)
        # the state keeps its dtype (float32 under bf16 autocast, where x is bf16: exact)
        return out, new_state.transpose(1, 2).to(conv_state.dtype).contiguous()  # (T, di), (S, di, k - 1)

    def packing(self, cu_seqlens: Tensor, total: int) -> Packing:
        return Packing.of(cu_seqlens, total, self.cfg.d_conv)

    def forward(
        self, x: Tensor, seqs: Tensor | Packing, state: MambaState | None = None
    ) -> tuple[Tensor, MambaState]:
        """x (T, d_model) packed; seqs: cu_seqlens (S + 1,) int64, or a Packing built for this layer's d_conv
        (shared between layers over the same pack); state with S rows or None (zeros). Returns (T, d_model)
        (padding rows of a segmented pack: finite, meaningless) and the new state (S rows)."""
        cfg = self.cfg
        packing = seqs if isinstance(seqs, Packing) else self.packing(seqs, x.shape[0])
        if packing.total != x.shape[0] or packing.older.shape[0] != cfg.d_conv - 1:
            raise ValueError(
                f"packing for {packing.total} tokens and d_conv {packing.older.shape[0] + 1}; "
                f"got {x.shape[0]} tokens, d_conv {cfg.d_conv}"
            )
        S = packing.num_seqs
        if state is None:  # zeros; at least one conv row (a frustum pack's segments continue none, seg 0)
            conv = x.new_zeros(max(S, 1), self.d_inner, cfg.d_conv - 1)  # (S', di, d_conv - 1)
            h0 = None
        else:
            if state.num_seqs != S:
                raise ValueError(f"state has {state.num_seqs} sequences, the packing describes {S}")
            conv, h0 = state.conv, state.ssm
        xz = self.in_proj(x)  # (T, 2 di)
        xi, z = xz.chunk(2, dim=-1)  # (T, di) each
        xc, conv_state = self._conv(xi, packing, conv)
        xc = F.silu(xc)  # (T, di)
        dt, B, C = self.x_proj(xc).split([self.dt_rank, cfg.d_state, cfg.d_state], dim=-1)
        delta = F.softplus(self.dt_proj(dt))  # (T, di)
        A = -torch.exp(self.A_log.to(torch.promote_types(self.A_log.dtype, torch.float32)))  # (di, n | 1)
        scan = cfg.scan if packing.scan is None else packing.scan
        y, ssm_state = selective_scan(xc, delta, A, B, C, packing.segments, h0, scan, cfg.chunk_size)
        y = (y + xc * self.D.to(y.dtype)) * F.silu(z)  # (T, di)
        return self.out_proj(y), MambaState(conv=conv_state, ssm=ssm_state)
