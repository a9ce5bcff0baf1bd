"""The PHiM block (paper Algorithm 1) and the 3D backbone made of them.

One block, for a batch of sectors (one batch item = one sector; sectors never mix here except through the
global Mamba, which runs forward in time over the sectors of each stream):

    local:  voxels serialized by (azimuth, radius, height) inside each azimuth frustum;
            V_local = x + fwd_mamba(LN(x)) + reverse(bwd_mamba(reverse(LN(x))))
    down:   decomposed sparse convs on the (r, z) then (theta, z) planes -> sector-level features
    global: forward Mamba over each stream's sector-level features in time order, continuing from the
            stream's carried state; then LayerNorm (the paper's "normalize")
    up:     decomposed inverse convs back to the local sites; residual with V_local
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from model.config import BackboneConfig
from model.geometry.sparse_tensor import BATCH, THETA, SparseTensor
from model.layers.decomposed import DecomposedDown, DecomposedUp, DownContext
from model.layers.mamba import Mamba, MambaState, Packing


@dataclass(frozen=True)
class StreamLayout:
    """Which stream each batch item (sector) belongs to.

    `stream_index` (B,) int64 is non-decreasing and the items of one stream are in time order, so a
    stream's sectors are contiguous: its global-Mamba sequence is their tokens concatenated.
    """

    stream_index: Tensor  # (B,) int64
    num_streams: int

    @staticmethod
    def one_per_item(batch_size: int, device: torch.device) -> StreamLayout:
        return StreamLayout(torch.arange(batch_size, device=device), batch_size)

    @staticmethod
    def single_stream(batch_size: int, device: torch.device) -> StreamLayout:
        return StreamLayout(torch.zeros(batch_size, dtype=torch.int64, device=device), 1)


def cu_seqlens_from_keys(keys: Tensor, num_groups: int) -> Tensor:
    """Sorted group ids (T,) in [0, num_groups) -> cu_seqlens (num_groups + 1,), empty groups allowed."""
    counts = torch.bincount(keys, minlength=num_groups)  # (G,)
    return torch.cat([counts.new_zeros(1), counts.cumsum(0)])


def frustum_cu_seqlens(x: SparseTensor, frustum_theta_bins: int) -> Tensor:
    """Packed frustum sequences of x (rows sorted by (batch, theta, r, z)) -> cu_seqlens (F' + 1,).

    Only non-empty frustums become sequences; their rows are contiguous because theta is the major key.
    """
    n_frustums = -(-x.spatial_shape[1] // frustum_theta_bins)
    key = x.coords[:, BATCH] * n_frustums + x.coords[:, THETA] // frustum_theta_bins  # (N,)
    if key.numel() == 0:
        return key.new_zeros(1)
    _, counts = torch.unique_consecutive(key, return_counts=True)
    return torch.cat([counts.new_zeros(1), counts.cumsum(0)])


def reversed_cu_seqlens(cu_seqlens: Tensor) -> Tensor:
    """cu_seqlens of the pack flipped along dim 0: flipping reverses each sequence and their order."""
    lengths = cu_seqlens.diff().flip(0)
    return torch.cat([cu_seqlens.new_zeros(1), lengths.cumsum(0)])


@dataclass(frozen=True)
class LocalPackings:
    """The local Mamba's frustum sequences, forward and reversed. Every block of a backbone runs on the same
    sites (a block's output keeps its input's), so one is built per forward and shared by all blocks."""

    fwd: Packing
    bwd: Packing  # of the pack flipped: every frustum reversed, and their order

    @staticmethod
    def of(x: SparseTensor, frustum_theta_bins: int, d_conv: int) -> LocalPackings:
        cu = frustum_cu_seqlens(x, frustum_theta_bins)
        n = x.num_sites
        return LocalPackings(Packing.of(cu, n, d_conv), Packing.of(reversed_cu_seqlens(cu), n, d_conv))


@dataclass(frozen=True)
class Coarsening:
    """A block's down-sampling rule books and its global Mamba's packing of the coarse sites: the same for
    every block with that kernel and stride in one forward (they depend on the sites and the layout only)."""

    down: DownContext
    global_seqs: Packing


class PHiMBlock(nn.Module):
    def __init__(self, cfg: BackboneConfig, kernel: int, stride: int):
        super().__init__()
        d = cfg.d_model
        self.kernel, self.stride = kernel, stride  # of the decomposed down/up-sampling
        self.frustum_theta_bins = cfg.frustum_theta_bins
        self.norm_local = nn.LayerNorm(d)
        self.fwd_mamba = Mamba(d, cfg.mamba)
        self.bwd_mamba = Mamba(d, cfg.mamba)
        self.down = DecomposedDown(d, kernel, stride, cfg.tz_kernel_z)
        self.global_mamba = Mamba(d, cfg.mamba)
        self.norm_global = nn.LayerNorm(d)
        self.up = DecomposedUp(d, kernel, stride, cfg.tz_kernel_z)

    def local_packings(self, x: SparseTensor) -> LocalPackings:
        return LocalPackings.of(x, self.frustum_theta_bins, self.fwd_mamba.cfg.d_conv)

    def local(self, x: SparseTensor | Tensor, seqs: LocalPackings) -> Tensor:
        """Bidirectional Mamba inside each frustum -> V_local features (N, C). x: the sites, or their
        features (N, C) (the fixed-shape step's padded rows, with segmented packings)."""
        feats = x.features if isinstance(x, SparseTensor) else x  # (N, C)
        h = self.norm_local(feats)  # (N, C)
        fwd, _ = self.fwd_mamba(h, seqs.fwd)
        bwd, _ = self.bwd_mamba(h.flip(0), seqs.bwd)  # flipping the pack reverses every frustum
        return feats + fwd + bwd.flip(0)

    def forward(
        self,
        x: SparseTensor,
        layout: StreamLayout,
        state: MambaState,
        local_seqs: LocalPackings | None = None,
        coarsening: Coarsening | None = None,
    ) -> tuple[SparseTensor, MambaState, Coarsening]:
        """x: sectors (rows sorted by (batch, theta, r, z)); state: global Mamba state, one row per stream.

        `local_seqs` and `coarsening`, when given, must have been built for x's sites (and this block's kernel
        and stride, and `layout`): the backbone shares them between blocks. Returns the block's Coarsening.
        """
        v_local = self.local(x, self.local_packings(x) if local_seqs is None else local_seqs)  # (N, C)
        coarse, ctx = self.down(x.replace(v_local), None if coarsening is None else coarsening.down)
        if coarsening is None:
            stream_of_row = layout.stream_index.index_select(0, coarse.coords[:, BATCH])  # (M,)
            cu = cu_seqlens_from_keys(stream_of_row, layout.num_streams)
            coarsening = Coarsening(ctx, self.global_mamba.packing(cu, coarse.num_sites))
        g, new_state = self.global_mamba(coarse.features, coarsening.global_seqs, state)  # (M, C)
        up = self.up(coarse.replace(self.norm_global(g)), ctx)
        return x.replace(up.features + v_local), new_state, coarsening


class PHiMBackbone(nn.Module):
    """A stack of PHiM blocks, one per (down_stride, down_kernel) pair of the config."""

    def __init__(self, cfg: BackboneConfig):
        super().__init__()
        self.cfg = cfg
        self.blocks = nn.ModuleList(
            PHiMBlock(cfg, k, s) for s, k in zip(cfg.down_strides, cfg.down_kernels, strict=True)
        )

    def init_states(self, num_streams: int, device: torch.device) -> list[MambaState]:
        """Zero global-Mamba states, one MambaState (num_streams rows) per block."""
        m = self.cfg.mamba
        d_inner = m.expand * self.cfg.d_model
        return [MambaState.zeros(num_streams, d_inner, m.d_conv, m.d_state, device) for _ in self.blocks]

    def forward(
        self, x: SparseTensor, layout: StreamLayout, states: list[MambaState]
    ) -> tuple[SparseTensor, list[MambaState]]:
        """Blocks with the same kernel and stride share their rule books and packings (same sites)."""
        local_seqs = LocalPackings.of(x, self.cfg.frustum_theta_bins, self.cfg.mamba.d_conv)
        coarsenings: dict[tuple[int, int], Coarsening] = {}
        new_states = []
        for block, state in zip(self.blocks, states, strict=True):
            key = (block.kernel, block.stride)
            x, s, coarsenings[key] = block(x, layout, state, local_seqs, coarsenings.get(key))
            new_states.append(s)
        return x, new_states
