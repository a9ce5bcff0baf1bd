"""The worker's engine before it serves (warm-up, then the heap frozen), and the model description served on
GET /v1/model."""

from __future__ import annotations

import gc
import json
import logging
from importlib.metadata import PackageNotFoundError, version
from typing import Any

from contract import POINT_FIELDS, REQUIRED_FIELDS
from model.engine import StreamEngine

log = logging.getLogger(__name__)


def warm_up(engine: StreamEngine, sectors: int, max_batch: int = 1) -> float:
    """The engine's own warm-up (`StreamEngine.warm_up`: `sectors` forwards, batches up to `max_batch`), then
    the heap frozen (`freeze_heap`) -> the mean seconds of one forward."""
    mean_s = engine.warm_up(sectors, max_batch)
    log.info("%d objects frozen out of the collector's reach", freeze_heap())
    return mean_s


def freeze_heap() -> int:
    """After the warm-up: collect, then move every object alive (modules, the model's Python objects,
    compiled graphs and their caches; they live as long as the process) to the collector's permanent
    generation, so that the full collections while serving walk only what serving allocates. Returns the
    number of objects frozen."""
    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()


def package_version() -> str:
    try:
        return version("phim")
    except PackageNotFoundError:
        return "0+unknown"


def model_info(engine: StreamEngine, source: str, worker_id: str) -> dict[str, Any]:
    cfg, info = engine.cfg, engine.describe()
    return {
        "name": "PHiM",
        "version": package_version(),
        "config": cfg.name,
        "weights": source,
        "device": info.device,
        "scan": info.scan.value,  # as configured (auto: the best available)
        "scan_impl": info.scan_impl.value,  # what runs on this device
        "engine": info.engine.value,
        "precision": info.precision.value,
        "sector_voxels": info.sector_voxels,
        "sector_points": info.sector_points,
        "bev_crop": info.bev_crop,
        "refiner": info.refiner,  # the box refiner runs (docs/model.md)
        # a fixed-shape engine's device-resident stream-state slots (None for eager: per-stream states)
        "state_slots": info.state_slots,
        "slot_bytes": info.slot_bytes,
        "slot_memory_mb": info.slot_memory_mb,
        "classes": list(cfg.head.class_names),
        "sectors_per_turn": cfg.sectors_per_turn,
        "buffer_sectors": cfg.buffer_sectors,
        # the columns a sector carries (at least the wire's four), and those the model reads (3: no intensity)
        "point_fields": list(POINT_FIELDS[: max(cfg.vfe.point_features, len(REQUIRED_FIELDS))]),
        "fields_read": list(POINT_FIELDS[: cfg.vfe.point_features]),
        "worker_id": worker_id,
        "config_detail": json.loads(json.dumps(cfg.to_dict())),
    }
