"""The BEV backbone and head over the part of the map a step changed: a crop, merged into the last maps.

A stream's BEV map holds its last `buffer_sectors + 1` sectors. When a sector's wedge of the polar grid
(theta bins [w * P, (w + 1) * P), P = theta_bins / sectors_per_turn) replaces the sector of the same wedge a
turn before, the BEV input changes only in the cells that wedge's columns feed (`wedge_boxes`), and the head's
maps only within `bev_halo` cells of them: the dense part's receptive field. The step then runs the backbone
and head on a fixed-size crop around the wedge (its cells +- 2 halos, aligned to the backbone's total stride
so that strided grids coincide, inside the map: zero padding only at the map's own edges) and keeps the crop's
output within one halo of the wedge, where it equals the whole map's; elsewhere the stream's maps of its last
step stay. `tiny` crops 108 x 108 of 128 x 128 cells, `paper` 320 x 320 of 468 x 468 (47 % of the cells and
of the 680 dense GFLOPs). The whole-map step is the reference twin; the engine (`model.graph.engine`) decides
per batch and verifies the wedge the step reports.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from model.config import PHiMConfig

SPANS, EMPTY = -1, -2  # a sector's wedge when its voxels span several wedges / it has none


def wedge_bins(cfg: PHiMConfig) -> int:
    """P: the theta bins of one wedge (a sector's share of a turn)."""
    return cfg.grid.theta_bins // cfg.sectors_per_turn


def _conv(lo: np.ndarray, hi: np.ndarray, k: int, s: int) -> tuple[np.ndarray, np.ndarray]:
    """The input interval each output of a k-wide, stride-s, padding k // 2 conv reads (1D)."""
    n_out = (len(lo) + 2 * (k // 2) - k) // s + 1
    start = np.arange(n_out) * s - k // 2
    return lo[np.clip(start, 0, len(lo) - 1)], hi[np.clip(start + k - 1, 0, len(hi) - 1)]


def bev_halo(cfg: PHiMConfig) -> int:
    """Cells from an input cell to the farthest head output it reaches (the BEV backbone's and head's
    receptive radius, from their layer structure: `model.layers.bev_backbone`, `model.layers.head`)."""
    b, n = cfg.bev, max(cfg.bev.nx, cfg.bev.ny)
    x = (np.arange(n), np.arange(n))  # each output's [lo, hi] input cells
    ups = []
    for layers, stride, up in zip(b.layer_nums, b.layer_strides, b.upsample_strides, strict=True):
        x = _conv(*_conv(*x, 3, stride), 3, 1)  # the stage's projecting block (its 1x1 shortcut reads less)
        for _ in range(2 * layers):
            x = _conv(*x, 3, 1)
        src = np.minimum(np.arange(n) // up, len(x[0]) - 1)  # deblock: kernel = stride
        ups.append((x[0][src], x[1][src]))
    lo, hi = np.minimum.reduce([u[0] for u in ups]), np.maximum.reduce([u[1] for u in ups])
    for _ in range(1 + cfg.head.head_convs):  # shared conv, then each branch's
        lo, hi = _conv(lo, hi, 3, 1)
    cells = np.arange(n)
    return int(max((cells - lo).max(), (hi - cells).max()))


def wedge_boxes(cfg: PHiMConfig, cell_table: Tensor) -> list[tuple[int, int, int, int]]:
    """Per wedge, the cells its polar columns feed: (y0, y1, x0, x1), half-open; cell_table (R * THETA, D)
    from `model.graph.bev.dense_cell_table`."""
    g, nx, per = cfg.grid, cfg.bev.nx, wedge_bins(cfg)
    table = cell_table.view(g.r_bins, g.theta_bins, -1)
    boxes = []
    for w in range(cfg.sectors_per_turn):
        cells = table[:, w * per : (w + 1) * per].reshape(-1)
        cells = cells[cells >= 0]
        y, x = cells // nx, cells % nx
        boxes.append((int(y.min()), int(y.max()) + 1, int(x.min()), int(x.max()) + 1))
    return boxes


@dataclass(frozen=True)
class CropPlan:
    """Where each wedge's crop lies: `size` (h, w) cells; bounds[w] = (crop y0, x0, kept y0, y1, x0, x1)."""

    size: tuple[int, int]
    bounds: Tensor  # (wedges, 6) int64, on the host


def _span(lo: int, hi: int, halo: int, align: int, length: int) -> tuple[int, int, int, int]:
    """One axis of a wedge's cells [lo, hi): the crop (start, end) and the kept part (start, end)."""
    start, end = max(0, lo - 2 * halo) // align * align, min(length, -(-(hi + 2 * halo) // align) * align)
    return start, end, max(0, lo - halo), min(length, hi + halo)


def crop_plan(cfg: PHiMConfig, cell_table: Tensor) -> CropPlan | None:
    """The crops of `cfg`'s wedges, or None where a crop would not be smaller than the map or the map is
    not a multiple of the backbone's total stride (a crop could not sit aligned at its far edge)."""
    b = cfg.bev
    align = int(np.prod(b.layer_strides))
    if b.nx % align or b.ny % align:
        return None
    halo = bev_halo(cfg)
    spans = [
        (_span(y0, y1, halo, align, b.ny), _span(x0, x1, halo, align, b.nx))
        for y0, y1, x0, x1 in wedge_boxes(cfg, cell_table)
    ]
    h = max(sy[1] - sy[0] for sy, _ in spans)
    w = max(sx[1] - sx[0] for _, sx in spans)
    if h * w >= b.ny * b.nx:
        return None
    rows = [  # the fixed-size crop slid inwards where the map's edge cuts it; it still holds the kept part
        (min(sy[0], b.ny - h), min(sx[0], b.nx - w), sy[2], sy[3], sx[2], sx[3]) for sy, sx in spans
    ]
    return CropPlan((h, w), torch.tensor(rows, dtype=torch.int64))


def _crop_index(origin: Tensor, size: tuple[int, int]) -> tuple[Tensor, Tensor, Tensor]:
    """origin (B, 2) int64 (y0, x0) -> the crops' (batch (B, 1, 1), rows (B, h, 1), columns (B, 1, w)) into a
    (B, H, W, ...) map."""
    ys = origin[:, :1] + torch.arange(size[0], device=origin.device)  # (B, h)
    xs = origin[:, 1:2] + torch.arange(size[1], device=origin.device)  # (B, w)
    batch = torch.arange(origin.shape[0], device=origin.device)[:, None, None]
    return batch, ys[:, :, None], xs[:, None, :]


def crop_cells(bev: Tensor, origin: Tensor, size: tuple[int, int]) -> Tensor:
    """bev (B, C, H, W), origin (B, 2) int64 (y0, x0) -> (B, C, h, w): each stream's crop."""
    return bev.permute(0, 2, 3, 1)[_crop_index(origin, size)].permute(0, 3, 1, 2)


def merge_crop(maps: Tensor, part: Tensor, bounds: Tensor) -> Tensor:
    """maps (B, H, W, M) the last step's, part (B, M, h, w) the crop's head maps, bounds (B, 6) -> (B, H, W,
    M): part inside each stream's kept box, maps elsewhere."""
    index = _crop_index(bounds[:, :2], (part.shape[2], part.shape[3]))
    _, ys, xs = index  # (B, h, 1), (B, 1, w)
    keep_y = (ys >= bounds[:, 2, None, None]) & (ys < bounds[:, 3, None, None])  # (B, h, 1)
    keep_x = (xs >= bounds[:, 4, None, None]) & (xs < bounds[:, 5, None, None])  # (B, 1, w)
    keep = (keep_y & keep_x)[..., None]  # (B, h, w, 1)
    values = torch.where(keep, part.permute(0, 2, 3, 1).to(maps.dtype), maps[index])  # (B, h, w, M)
    return maps.index_put(index, values)


def wedge_of(sites_theta: Tensor, batch: Tensor, valid: Tensor, streams: int, per_wedge: int) -> Tensor:
    """Each stream's wedge from its voxels' theta bins (V,), stream index (V,) and validity (V,), with
    `per_wedge` = `wedge_bins(cfg)` -> (B,) int64: the wedge, SPANS or EMPTY."""
    big = torch.iinfo(torch.int64).max
    row = torch.where(valid, batch, streams)  # padding rows to a dump stream
    lo = torch.full((streams + 1,), big, dtype=torch.int64, device=batch.device)
    hi = torch.full((streams + 1,), -1, dtype=torch.int64, device=batch.device)
    lo = lo.scatter_reduce(0, row, sites_theta, "amin")[:streams]
    hi = hi.scatter_reduce(0, row, sites_theta, "amax")[:streams]
    w_lo = torch.div(lo, per_wedge, rounding_mode="floor")
    w_hi = torch.div(hi, per_wedge, rounding_mode="floor")
    return torch.where(hi < 0, EMPTY, torch.where(w_lo == w_hi, w_lo, SPANS))


def crop_wedges(wedges: list[tuple[int, ...]], keep: int, sectors_per_turn: int) -> list[int] | None:
    """Each stream's wedge for a batch whose dense part can run on crops, else None; wedges[i]: the wedges
    of the last keep + 1 sectors stream i's slot ran, oldest first. A stream qualifies once those are keep + 1
    sectors, each in one wedge, and its next sector, predicted from its last two (the sweep goes on in the
    same direction), falls in the wedge of the sector leaving its BEV map (the only change to the map is then
    in that wedge)."""
    for w in wedges:
        if len(w) <= keep or min(w) < 0 or (2 * w[-1] - w[-2]) % sectors_per_turn != w[0]:
            return None
    return [w[0] for w in wedges]
