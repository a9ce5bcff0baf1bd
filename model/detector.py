"""The whole PHiM detector: voxelizer -> PHiM backbone -> sector buffer -> polar->BEV -> BEV backbone -> head.

The detector is split in two calls so that streaming, whole-turn and training runs share every line:
`encode` runs the 3D part over a batch of sectors (carrying global-Mamba states per stream), and
`predict` combines any set of encoded sectors per prediction (the new one plus the buffered ones) into a
Cartesian BEV map and runs the 2D part.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from model.config import EgoFootprint, PHiMConfig, ScanImpl
from model.ego import drop_ego_boxes, drop_ego_points
from model.geometry.boxes import Detections
from model.geometry.sparse_tensor import BATCH, SparseTensor
from model.layers.bev_backbone import BEVBackbone
from model.layers.head import CenterHead, HeadOutput, decode
from model.layers.mamba import Mamba, MambaState
from model.layers.phim_block import PHiMBackbone, StreamLayout
from model.layers.polar_bev import PolarToBEV
from model.layers.refine import BoxRefiner, refine
from model.layers.voxelize import PolarVoxelizer, VoxelStats


@dataclass(frozen=True)
class SectorFeatures:
    """One sector's 3D backbone output, as kept in a stream's sector buffer."""

    features: Tensor  # (M, C)
    coords: Tensor  # (M, 3) int64: r, theta, z

    @property
    def num_voxels(self) -> int:
        return int(self.coords.shape[0])


@dataclass(frozen=True)
class Encoded:
    sectors: list[SectorFeatures]  # one per input sector
    states: list[MambaState]  # per PHiM block, one row per stream
    stats: VoxelStats


class PHiM(nn.Module):
    def __init__(self, cfg: PHiMConfig):
        super().__init__()
        self.cfg = cfg
        d = cfg.backbone.d_model
        self.voxelizer = PolarVoxelizer(cfg.grid, cfg.vfe, d)
        self.backbone = PHiMBackbone(cfg.backbone)
        self.to_bev = PolarToBEV(cfg.grid, cfg.bev)
        self.bev_backbone = BEVBackbone(d, cfg.bev)
        self.head = CenterHead(self.bev_backbone.out_channels, cfg.head)
        self.refiner = BoxRefiner(len(cfg.head.class_names), cfg.refine) if cfg.refine else None

    @property
    def device(self) -> torch.device:
        return next(self.parameters()).device

    def drop_refiner(self) -> None:
        """The detector alone from here on, without its box refiner (a server's `--no-refiner`)."""
        self.refiner = None
        self.cfg = dataclasses.replace(self.cfg, refine=None)

    def set_ego(self, ego: EgoFootprint | None) -> None:
        """The ego vehicle's footprint from here on (None: every point read, every box kept): a deployment's
        car, not the weights' (a server's `--ego-footprint`)."""
        self.cfg = dataclasses.replace(self.cfg, ego=ego)

    def init_states(self, num_streams: int) -> list[MambaState]:
        return self.backbone.init_states(num_streams, self.device)

    def set_scan(self, impl: ScanImpl) -> None:
        """Run every Mamba layer's selective scan with `impl` (how, not what: the weights still fit)."""
        mamba = dataclasses.replace(self.cfg.backbone.mamba, scan=impl)
        self.cfg = dataclasses.replace(self.cfg, backbone=dataclasses.replace(self.cfg.backbone, mamba=mamba))
        for m in self.modules():
            if isinstance(m, Mamba):
                m.cfg = mamba

    def encode(self, points: list[Tensor], layout: StreamLayout, states: list[MambaState]) -> Encoded:
        """points[i]: (N_i, C) sector i; layout maps sectors to streams; states: per block, per stream."""
        voxels, stats = self.voxelizer(points)
        out, new_states = self.backbone(voxels, layout, states)
        return Encoded(split_sectors(out), new_states, stats)

    def bev_input(self, scenes: list[list[SectorFeatures]]) -> SparseTensor:
        """Concatenate each prediction's sectors (buffered ones first) into one batch item."""
        feats, coords = [], []
        for b, sectors in enumerate(scenes):
            for s in sectors:
                feats.append(s.features)
                coords.append(nn.functional.pad(s.coords, (1, 0), value=b))
        g = self.cfg.grid
        if not feats:
            feats = [torch.zeros(0, self.cfg.backbone.d_model, device=self.device)]
            coords = [torch.zeros(0, 4, dtype=torch.int64, device=self.device)]
        return SparseTensor(
            torch.cat(feats), torch.cat(coords), (g.r_bins, g.theta_bins, g.z_bins), len(scenes)
        )

    def predict(self, scenes: list[list[SectorFeatures]]) -> HeadOutput:
        bev = self.to_bev(self.bev_input(scenes))  # (B, C, ny, nx)
        return self.head(self.bev_backbone(bev))

    def detect(self, scenes: list[list[SectorFeatures]]) -> list[Detections]:
        return decode(self.predict(scenes), self.cfg.head, self.cfg.bev, self.cfg.every_cell)

    def forward_turn(self, sectors: list[Tensor]) -> tuple[list[Detections], Encoded]:
        """The whole turn in one pass: all sectors of one stream, global Mamba over their concatenation (and
        the box refiner, where the model has one, over all their points); without the ego vehicle's points
        and boxes (`cfg.ego`), as the streaming step."""
        sectors = drop_ego_points(sectors, self.cfg.ego)
        layout = StreamLayout.single_stream(len(sectors), self.device)
        enc = self.encode(sectors, layout, self.init_states(1))
        (det,) = self.detect([enc.sectors])
        if self.refiner is not None:
            det = refine(self.refiner, det, torch.cat(sectors))
        return [drop_ego_boxes(det, self.cfg.ego)], enc


def split_sectors(x: SparseTensor) -> list[SectorFeatures]:
    """Backbone output (rows sorted by batch) -> one SectorFeatures per batch item."""
    counts = torch.bincount(x.coords[:, BATCH], minlength=x.batch_size).tolist()
    feats = x.features.split(counts)
    coords = x.coords[:, 1:].split(counts)
    return [SectorFeatures(f, c) for f, c in zip(feats, coords, strict=True)]
