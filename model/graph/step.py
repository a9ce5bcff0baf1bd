"""One streaming step of fixed shape: padded sectors of B streams and their states -> top-k candidates, stats
and new states. Every shape is set by `Capacity` and the batch size; no op waits for the device.

The computation is the eager detector's (`model.stream.StreamingDetector.step`, the reference twin) with
fixed-capacity sites (`model.graph.sites`): rows [0, n) real, padding after, overflow counted, never hidden:

    voxelize (sort, first-occurrence compaction) -> per PHiM block: local Mamba over frustum segments,
    decomposed down convs over neighbour tables, global Mamba over one segment per stream continuing its
    state, up convs -> each stream's new sector gathered into its buffer row -> polar->BEV scatter-mean over
    the buffered sectors and the new one -> BEV backbone -> head -> top-k candidates.

The host reads one flat tensor (`HostLayout`): the candidates, per stream stats and the site counts. NMS
runs on the host from the candidates (`model.layers.head.select_detections`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from model.config import PHiMConfig, ScanImpl
from model.detector import PHiM
from model.geometry.rulebook import Plane
from model.geometry.sparse_tensor import BATCH, THETA
from model.geometry.sparse_tensor import R as R_AX
from model.graph.bev import dense_cell_table, polar_to_bev
from model.graph.bev_crop import crop_cells, crop_plan, merge_crop, wedge_bins, wedge_of
from model.graph.segments import frustum_segments, stream_segments
from model.graph.sites import Sites, scatter_sum
from model.graph.sparse_conv import inverse_table, strided_sites, subm_table
from model.graph.voxelize import voxelize_fixed
from model.layers.decomposed import DecomposedDown, DecomposedUp
from model.layers.head import HeadOutput, peak_candidates, rot_channels
from model.layers.mamba import MambaState, Packing
from model.layers.phim_block import LocalPackings, PHiMBlock
from model.ops.segments import Segments
from model.ops.table_conv import table_conv

# per stream columns of the host tensor; wedge: the sector's wedge (`model.graph.bev_crop.wedge_of`)
STATS = ("points_kept", "points_out_of_range", "voxels", "wedge")


@dataclass(frozen=True)
class Capacity:
    """Row capacities of one step (Python ints: a compiled step or CUDA graph is specialised on them)."""

    points: int  # per stream
    voxels: int  # all streams together
    coarse: tuple[tuple[int, int], ...]  # per strided (kernel, stride) of `coarse_keys`: sites after (a), (c)
    bev_crop: bool = False  # the dense part on each stream's crop (`model.graph.bev_crop`), else whole


def coarse_keys(cfg: PHiMConfig) -> tuple[tuple[int, int], ...]:
    """The distinct (kernel, stride) pairs of the blocks with stride > 1, in block order."""
    b = cfg.backbone
    pairs = [(k, s) for k, s in zip(b.down_kernels, b.down_strides, strict=True) if s > 1]
    return tuple(dict.fromkeys(pairs))


@dataclass(frozen=True)
class HostLayout:
    """Where each part lies in the flat float32 tensor the host copies once per step."""

    batch: int
    top_k: int
    counts: int  # site counts: voxels, (a) and (c) per coarse key

    @property
    def candidate_width(self) -> int:
        return 10  # box (7), score, label, heatmap score

    def split(self, host: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """-> candidates (B, K, 10), stats (B, len(STATS)), site counts (F,) int64."""
        b, k = self.batch, self.top_k
        n_cand = b * k * self.candidate_width
        cand = host[:n_cand].view(b, k, self.candidate_width)
        stats = host[n_cand : n_cand + b * len(STATS)].view(b, len(STATS))
        return cand, stats, host[n_cand + b * len(STATS) :].long()


@dataclass(frozen=True)
class _Down:
    """A (kernel, stride)'s tables, shared by its blocks (they depend on the sites only)."""

    rz: Tensor  # (M1, KK) rows of the block input
    sub: Tensor  # (M1, KK) rows of the sites after (a)
    tz: Tensor  # (M2, K * kz) rows of the sites after (a)
    inv_tz: Tensor  # (M1, K * kz) rows of the coarse sites
    inv_rz: Tensor  # (V, KK) rows of the sites after (a)
    coarse: Sites  # (M2,) the global Mamba's tokens
    counts: Tensor  # (2,) int64: the sites after (a) and after (c) there are (> capacity: overflow)
    packing: Packing  # the global Mamba's: one segment per stream over the coarse sites


@dataclass(frozen=True)
class _Backbone:
    """The 3D backbone's part of a step."""

    sites: Sites  # (V,) the step's voxel sites
    x: Tensor  # (V, C) their features
    kept: Tensor  # (B,) points kept
    out_of_range: Tensor  # (B,) points outside the grid
    site_counts: list[Tensor]  # the voxels, then per coarse key the sites after (a) and (c): for the host
    conv: list[Tensor]  # per block the new global-Mamba conv state (B, di, d_conv - 1)
    ssm: list[Tensor]  # per block the new global-Mamba ssm state (B, di, N)


def _packing(segs: Segments, d_conv: int) -> Packing:
    """A segmented pack for the Mamba layers, scanned by an implementation with no host sync."""
    return Packing.of_segments(segs, d_conv, ScanImpl.AUTO)


def _down_tables(
    sites: Sites, kernel: int, stride: int, kz: int, caps: tuple[int, int] | None, d_conv: int
) -> _Down:
    k2, ktz = (kernel, kernel), (kernel, kz)
    if stride == 1:  # submanifold: the same sites throughout; an inverse table is the mirrored table
        mid = coarse = sites
        rz = sub = subm_table(sites, k2, Plane.RZ)
        tz = subm_table(sites, ktz, Plane.THETA_Z)
        inv_rz, inv_tz = rz.flip(1), tz.flip(1)
    else:
        assert caps is not None
        mid, rz = strided_sites(sites, k2, (stride, stride), Plane.RZ, caps[0])
        sub = subm_table(mid, k2, Plane.RZ)
        coarse, tz = strided_sites(mid, ktz, (stride, 1), Plane.THETA_Z, caps[1])
        inv_tz = inverse_table(mid, coarse, ktz, (stride, 1), Plane.THETA_Z)
        inv_rz = inverse_table(sites, mid, k2, (stride, stride), Plane.RZ)
    segs = stream_segments(coarse.coords[:, BATCH], coarse.valid, sites.batch_size)
    counts = torch.stack([mid.count, coarse.count])
    return _Down(rz, sub, tz, inv_tz, inv_rz, coarse, counts, _packing(segs, d_conv))


def _conv(conv: nn.Module, x: Tensor, table: Tensor) -> Tensor:
    """A folded sparse conv (weight (KK, C_in, C_out), bias (C_out,)) + ReLU over a neighbour table."""
    return torch.relu(table_conv(x, table, conv.weight, conv.bias))


def _block(block: PHiMBlock, x: Tensor, local: LocalPackings, t: _Down, state: MambaState):
    """x (V, C) at the step's voxel sites -> (V, C), the block's new global-Mamba state (B rows): the eager
    block's layers (`PHiMBlock.local`, its global Mamba) over the step's segmented packs."""
    v_local = block.local(x, local)  # (V, C)
    down: DecomposedDown = block.down
    h = _conv(down.conv_tz, _conv(down.conv_sub, _conv(down.conv_rz, v_local, t.rz), t.sub), t.tz)  # (M2, C)
    g, new_state = block.global_mamba(h, t.packing, state)
    up: DecomposedUp = block.up
    h = _conv(up.inv_rz, _conv(up.inv_tz, block.norm_global(g), t.inv_tz), t.inv_rz)  # (V, C)
    return h + v_local, new_state


def _check_folded(model: PHiM) -> None:
    for m in model.backbone.modules():
        if isinstance(m, DecomposedDown | DecomposedUp) and any(
            isinstance(bn, nn.BatchNorm1d) for bn in m.children()
        ):
            raise ValueError("the graph step runs a folded model: model.fold_bn.fold_batchnorms(model)")


class GraphStep(nn.Module):
    """The fixed-shape step over a folded PHiM (`model.fold_bn.fold_batchnorms`), sharing its weights."""

    cell_table: Tensor

    def __init__(self, model: PHiM, sector_voxels: int):
        super().__init__()
        _check_folded(model)
        self.model = model
        self.cfg = model.cfg
        self.sector_voxels = sector_voxels  # S: voxel rows a stream keeps per buffered sector
        self.keys = coarse_keys(model.cfg)
        self.register_buffer("cell_table", dense_cell_table(model.to_bev), persistent=False)
        self.crop = crop_plan(model.cfg, self.cell_table)  # None: this config's dense part runs whole
        self.map_channels = sum(self._map_split())  # M: the head's map channels, HeadOutput's fields in order

    def host_layout(self, batch: int) -> HostLayout:
        top_k = min(
            self.cfg.head.pre_nms_top_k, len(self.cfg.head.class_names) * self.cfg.bev.nx * self.cfg.bev.ny
        )
        return HostLayout(batch, top_k, 1 + 2 * len(self.keys))

    def forward(
        self,
        points: Tensor,  # (B, Np, C) float32
        counts: Tensor,  # (B,) int64 real rows of each stream's points
        conv: list[Tensor],  # per block (B, di, d_conv - 1)
        ssm: list[Tensor],  # per block (B, di, N)
        buf_feats: Tensor,  # (B, keep, S, C)
        buf_cols: Tensor,  # (B, keep, S, 2) int64 polar column (r, theta) of each buffered row
        buf_valid: Tensor,  # (B, keep, S) bool
        maps: Tensor,  # (B, H, W, M) float32 the head's maps of each stream's last step
        crop: Tensor,  # (B, 6) int64 each stream's crop bounds (`CropPlan.bounds`), read if cap.bev_crop
        cap: Capacity,
    ) -> tuple[Tensor, list[Tensor], list[Tensor], Tensor, Tensor, Tensor, Tensor]:
        """-> (host (n,) float32 laid out by `host_layout(B)`, new conv, ssm, buffer feats, cols, valid,
        maps)."""
        cfg = self.cfg
        bb = self._backbone(points, counts, conv, ssm, cap)
        new_f, new_c, new_v, n_vox = self._sector_rows(bb.sites, bb.x)
        feats = torch.cat([buf_feats, new_f[:, None]], 1)  # (B, keep + 1, S, C)
        cols = torch.cat([buf_cols, new_c[:, None]], 1)
        valid = torch.cat([buf_valid, new_v[:, None]], 1)
        new_maps = self._dense(feats, cols, valid, maps, crop, cap)
        out = HeadOutput(*new_maps.permute(0, 3, 1, 2).split(self._map_split(), 1))
        cand = peak_candidates(out, cfg.head, cfg.bev, cfg.every_cell)
        packed = torch.cat(
            [
                cand.boxes,
                cand.scores[..., None],
                cand.labels[..., None].float(),
                cand.heat[..., None],
            ],
            -1,
        )
        b = points.shape[0]
        coords = bb.sites.coords
        wedge = wedge_of(coords[:, THETA], coords[:, BATCH], bb.sites.valid, b, wedge_bins(cfg))
        stats = torch.stack([bb.kept, bb.out_of_range, n_vox, wedge], 1).float()  # (B, len(STATS))
        host = torch.cat([packed.reshape(-1), stats.reshape(-1), torch.stack(bb.site_counts).float()])
        keep = cfg.buffer_sectors
        return (
            host,
            bb.conv,
            bb.ssm,
            feats[:, feats.shape[1] - keep :],
            cols[:, cols.shape[1] - keep :],
            valid[:, valid.shape[1] - keep :],
            new_maps,
        )

    def _backbone(
        self, points: Tensor, counts: Tensor, conv: list[Tensor], ssm: list[Tensor], cap: Capacity
    ) -> _Backbone:
        """`forward`'s points and global-Mamba states -> the voxelizer and 3D backbone's outputs."""
        m, cfg = self.model, self.cfg
        sites, x, kept, out_of_range = voxelize_fixed(m.voxelizer, points, counts, cap.voxels)
        d_conv = cfg.backbone.mamba.d_conv
        fwd, bwd = frustum_segments(
            sites.coords, sites.valid, cfg.grid.theta_bins, cfg.backbone.frustum_theta_bins
        )
        local = LocalPackings(_packing(fwd, d_conv), _packing(bwd, d_conv))
        tables: dict[tuple[int, int], _Down] = {}
        site_counts = [sites.count]
        for key in dict.fromkeys((b.kernel, b.stride) for b in m.backbone.blocks):
            caps = cap.coarse[self.keys.index(key)] if key[1] > 1 else None
            tables[key] = _down_tables(sites, key[0], key[1], cfg.backbone.tz_kernel_z, caps, d_conv)
        site_counts += [n for key in self.keys for n in tables[key].counts.unbind()]
        new_conv, new_ssm = [], []
        for block, c, s in zip(m.backbone.blocks, conv, ssm, strict=True):
            x, st = _block(block, x, local, tables[(block.kernel, block.stride)], MambaState(c, s))
            new_conv.append(st.conv)
            new_ssm.append(st.ssm)
        return _Backbone(sites, x, kept, out_of_range, site_counts, new_conv, new_ssm)

    def _dense(
        self, feats: Tensor, cols: Tensor, valid: Tensor, maps: Tensor, crop: Tensor, cap: Capacity
    ) -> Tensor:
        """The buffered sectors' rows (B, keep + 1, S, ...) -> the head's new maps (B, H, W, M): on a crop
        around the new sector merged into the last maps when cap.bev_crop, else the whole map."""
        b = feats.shape[0]
        bev = polar_to_bev(
            self.model.to_bev,
            self.cell_table,
            feats.view(b, -1, feats.shape[-1]),
            cols[..., 0].view(b, -1),
            cols[..., 1].view(b, -1),
            valid.view(b, -1),
        )
        if cap.bev_crop:
            assert self.crop is not None
            part = self._head_maps(crop_cells(bev, crop[:, :2], self.crop.size))  # (B, M, h, w)
            return merge_crop(maps, part, crop)  # (B, H, W, M)
        return self._head_maps(bev).permute(0, 2, 3, 1).contiguous()  # (B, H, W, M)

    def _head_maps(self, bev: Tensor) -> Tensor:
        """bev (B, C, H, W) -> the head's maps (B, M, H, W), HeadOutput's fields along M (float32)."""
        out = self.model.head(self.model.bev_backbone(bev))
        return torch.cat([out.heatmap, out.offset, out.z, out.log_dim, out.rot, out.iou], 1)

    def _map_split(self) -> list[int]:
        h = self.cfg.head
        return [len(h.class_names), 2, 1, 3, rot_channels(h.heading), 1]

    def _sector_rows(self, sites: Sites, x: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Each stream's rows of the backbone output -> feats (B, S, C), cols (B, S, 2), valid (B, S), and its
        voxel count (B,) (more than S: the buffer overflows; the host checks)."""
        b, s = sites.batch_size, self.sector_voxels
        batch = sites.coords[:, BATCH]  # (V,) padding rows: b
        n_vox = scatter_sum(
            torch.zeros(b + 1, dtype=torch.int64, device=x.device), batch, torch.ones_like(batch)
        )
        n_vox = n_vox[:b]  # (B,)
        start = torch.cumsum(n_vox, 0) - n_vox  # (B,) streams' rows are contiguous, in batch order
        j = torch.arange(s, device=x.device)  # (S,)
        valid = j[None, :] < n_vox[:, None]  # (B, S)
        rows = torch.where(valid, start[:, None] + j[None, :], 0).clamp_max(x.shape[0] - 1)  # (B, S)
        feats = torch.where(valid[..., None], x[rows], 0.0)  # (B, S, C)
        cols = sites.coords[rows][..., [R_AX, THETA]]  # (B, S, 2)
        return feats, cols, valid, n_vox
