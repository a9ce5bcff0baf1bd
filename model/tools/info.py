"""Parameter count and a measured FLOP count for a config (`phim model info`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import TypeVar

import torch
from torch import Tensor, nn
from torch.utils.flop_counter import FlopCounterMode

from model.config import PHiMConfig
from model.detector import PHiM
from model.layers.phim_block import StreamLayout
from model.sectors import split_turn

T = TypeVar("T")


@dataclass(frozen=True)
class ModelInfo:
    config: str
    params: int
    params_mb: float  # float32 weights
    params_by_part: dict[str, int]
    gflops: float  # one full turn in one pass: 3D part over all sectors + one BEV/head pass
    gflops_per_sector_step: float  # streaming: one sector through the 3D part + one BEV/head pass
    input_points: int
    voxels: int

    def to_dict(self) -> dict:
        return asdict(self)


def count_params(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


def _counted(fn: Callable[[], T]) -> tuple[T, int]:
    """fn's result and the FLOPs it ran."""
    counter = FlopCounterMode(display=False)
    with counter:
        out = fn()
    return out, counter.get_total_flops()


def _silent(what: str) -> None:
    """No progress reports."""


@torch.inference_mode()
def model_info(cfg: PHiMConfig, turn: Tensor, progress: Callable[[str], None] = _silent) -> ModelInfo:
    """Counts matmul/conv FLOPs (multiply-add = 2 FLOPs) of real forwards over `turn` (N, C) points;
    `progress` hears of each forward as it starts.

    FLOPs of a sparse model depend on occupancy, so the input scan is part of the answer. The BEV backbone
    and head run on the whole map however many sectors feed it, so their pass is counted once and added to
    the 3D part of the whole turn and to that of one sector.
    """
    progress(f"building the {cfg.name} config")
    model = PHiM(cfg).eval()
    sectors = split_turn(turn, cfg.sectors_per_turn)
    turn_layout = StreamLayout.single_stream(len(sectors), model.device)
    progress(
        f"counting the FLOPs of the whole turn in one pass ({turn.shape[0]} points, {len(sectors)} sectors): "
        "the 3D part"
    )
    enc, turn_3d = _counted(lambda: model.encode(sectors, turn_layout, model.init_states(1)))
    progress("counting the FLOPs of the BEV backbone and head (the slowest part: one counted forward)")
    _, dense = _counted(lambda: model.detect([enc.sectors]))
    progress("counting the FLOPs of one streaming step (one sector through the 3D part)")
    one = StreamLayout.one_per_item(1, model.device)
    _, sector_3d = _counted(lambda: model.encode(sectors[:1], one, model.init_states(1)))
    full, step = (turn_3d + dense) / 1e9, (sector_3d + dense) / 1e9
    parts = {
        "voxelizer": model.voxelizer,
        "backbone3d": model.backbone,
        "bev_backbone": model.bev_backbone,
        "head": model.head,
    }
    params = count_params(model)
    return ModelInfo(
        config=cfg.name,
        params=params,
        params_mb=round(params * 4 / 2**20, 2),
        params_by_part={k: count_params(v) for k, v in parts.items()},
        gflops=round(full, 2),
        gflops_per_sector_step=round(step, 2),
        input_points=int(turn.shape[0]),
        voxels=sum(s.num_voxels for s in enc.sectors),
    )
