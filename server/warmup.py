"""Warm-up forwards before a worker is ready, and the model description served on GET /v1/model."""

from __future__ import annotations

import gc
import json
import logging
import time
from importlib.metadata import PackageNotFoundError, version
from typing import Any

import torch

from contract import POINT_FIELDS, REQUIRED_FIELDS
from lidar.synthetic import synthetic_turn
from model.geometry.nms_cpu import compile_kernels as compile_nms_kernels
from model.graph.buckets import BATCH_BUCKETS, batch_bucket
from model.graph.engine import Detector, GraphStreamingDetector
from model.ops.scan import resolve_scan
from model.sectors import split_turn

log = logging.getLogger(__name__)


def warm_up(det: Detector, sectors: int, max_batch: int = 1, headroom: float = 1.0) -> float:
    """Run `sectors` single-stream forwards on a synthetic turn (filling the sector buffer), then (eager)
    one batch of two streams; returns the mean seconds of one forward (0.1 if no forward ran). A fixed-shape
    detector first learns its capacities from the turn, runs a batch of fresh streams for every bucket up to
    `max_batch`, on the whole map and on crops (a compiled one compiles them here, before the worker is
    ready), and gives back the one stream-state slot it used; its capacities are the turn's times
    `headroom` (real scans have more sites per point than the synthetic turn), and it is sealed: no
    compiling after the warm-up. Before any forward, the CPU NMS kernels are compiled (or loaded from
    numba's cache): whether a forward reaches NMS depends on the weights and the turn."""
    compile_nms_kernels()
    if sectors <= 0:
        return 0.1
    turn = split_turn(torch.from_numpy(synthetic_turn(seed=0)), det.cfg.sectors_per_turn)  # list of (N_k, 4)
    graph = isinstance(det, GraphStreamingDetector)
    if graph:
        det.calibrate(turn, headroom)
        crops = [False, True] if det.bev_crop else [False]
        for b in (b for b in BATCH_BUCKETS if b <= batch_bucket(max_batch)):
            for crop in crops:  # the whole map (a stream's first turn), and crops (every sector after it)
                det.run_fresh([turn[i % len(turn)] for i in range(b)], crop)
    pair = sectors >= 2 and not graph  # a fixed-shape detector ran its batch buckets above
    state = taken = det.init_state()
    t0 = time.monotonic()
    try:
        for i in range(sectors):
            _, (state,) = det.step([turn[i % len(turn)]], [state])
        if pair:
            det.step(turn[:2], [det.init_state(), state])
    finally:
        if isinstance(det, GraphStreamingDetector):
            det.release(taken)
            det.seal()  # a bucket not compiled by now runs op by op: no compile while serving
    forwards = sectors + int(pair)
    mean_s = (time.monotonic() - t0) / forwards
    log.info("warm-up: %d forwards, %.1f ms each on average", forwards, mean_s * 1e3)
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


def slot_info(det: Detector) -> dict[str, Any]:
    """The fixed-shape engines' device-resident stream-state slots (None for eager: per-stream states)."""
    if not isinstance(det, GraphStreamingDetector):
        return {"state_slots": None, "slot_bytes": None, "slot_memory_mb": None}
    slots = det.slots
    return {
        "state_slots": slots.count,
        "slot_bytes": slots.slot_bytes,
        "slot_memory_mb": round(slots.total_bytes / 2**20, 1),
    }


def model_info(det: Detector, source: str, worker_id: str) -> dict[str, Any]:
    cfg = det.cfg
    graph = isinstance(det, GraphStreamingDetector)
    return {
        "name": "PHiM",
        "version": package_version(),
        "config": cfg.name,
        "weights": source,
        "device": str(det.device),
        "scan": cfg.backbone.mamba.scan.value,  # as configured (auto: the best available)
        "scan_impl": resolve_scan(cfg.backbone.mamba.scan, det.device).value,  # what runs on this device
        "engine": det.engine.value,
        "precision": det.precision.value,
        "sector_voxels": det.sector_voxels if graph else None,
        "sector_points": det.sector_points if graph else None,
        "bev_crop": det.bev_crop if graph else None,
        "refiner": cfg.refine is not None,  # the box refiner runs (docs/model.md)
        **slot_info(det),
        "classes": list(cfg.head.class_names),
        "sectors_per_turn": cfg.sectors_per_turn,
        "buffer_sectors": cfg.buffer_sectors,
        # the columns a sector carries (at least the wire's four), and those the model reads (3: no intensity)
        "point_fields": list(POINT_FIELDS[: max(cfg.vfe.point_features, len(REQUIRED_FIELDS))]),
        "fields_read": list(POINT_FIELDS[: cfg.vfe.point_features]),
        "worker_id": worker_id,
        "config_detail": json.loads(json.dumps(cfg.to_dict())),
    }
