"""`phim bench ops`: how many torch ops one streaming step runs, by model function.

On a GPU a step of the paper config is bound by launching small ops from Python, not by arithmetic
(docs/benchmarks.md: about 4,000 kernels for 28 ms of kernel time), so the op count is the number to bring
down, and it can be counted on any machine. One step = one 1/4 sector with the stream's buffer loaded, as
`phim bench model` times it. Counted with `torch.profiler`: the top-level aten ops (ops called by other
ops are not counted again), each credited to the innermost function of the `model` package it ran in.
"""

from __future__ import annotations

import re
from collections import Counter
from dataclasses import asdict, dataclass

import torch
from torch import Tensor
from torch.profiler import ProfilerActivity, profile

from model.config import Engine
from model.detector import PHiM
from model.graph.engine import GraphStreamingDetector
from model.ops.scan import resolve_scan
from model.sectors import split_turn
from model.stream import StreamingDetector

# ops that only make a new view of a tensor: no kernel on any device
_VIEWS = """slice select view unsqueeze squeeze transpose t reshape permute expand as_strided narrow split
split_with_sizes chunk unbind alias detach resolve_conj resolve_neg lift_fresh"""
# ops whose output size or value the host must wait for on CUDA (a host synchronisation)
_SYNCS = "nonzero unique_consecutive _unique2 unique_dim is_nonzero equal _local_scalar_dense"
VIEW_OPS = frozenset(f"aten::{n}" for n in _VIEWS.split())
SYNC_OPS = frozenset(f"aten::{n}" for n in _SYNCS.split())
# the scan: one fused path on CUDA
SCAN_FILES = ("model/ops/scan_torch.py", "model/ops/scan_triton.py", "model/ops/scan_numba.py")
_FRAME = re.compile(r"(model/[\w/]+\.py)\(\d+\): (\w+)")


@dataclass(frozen=True)
class OpRow:
    where: str  # "model/<file>.py: <function>", or "(outside model/)"
    ops: int  # ops that compute: a kernel launch each (or more) on a GPU
    views: int
    host_syncs: int


@dataclass(frozen=True)
class OpReport:
    config: str
    engine: str
    device: str
    scan: str
    ops: int
    views: int
    host_syncs: int
    ops_outside_scan: int
    cuda_kernels: int | None  # CUDA only: kernels the step launched
    rows: list[OpRow]  # by ops, descending

    def to_dict(self) -> dict:
        return asdict(self)


def _where(event: object) -> str:
    """The innermost `model/` Python frame above a profiler event."""
    parent = getattr(event, "cpu_parent", None)
    while parent is not None:
        m = _FRAME.search(parent.name)
        if m and "site-packages" not in parent.name:
            return f"{m.group(1)}: {m.group(2)}"
        parent = parent.cpu_parent
    return "(outside model/)"


def count_ops(model: PHiM, turn: Tensor, engine: Engine = Engine.EAGER) -> OpReport:
    """Stream one turn of `turn` (N, C) to load the buffer, then profile the step of its second sector.

    Engine.EAGER: the whole `StreamingDetector.step`. A graph engine: its fixed-shape step run op by op, from
    the inputs on the device to the flat tensor the host copies (the padding and NMS on the host are not
    counted); a compiled step runs the same ops, fused.
    """
    graph = engine is not Engine.EAGER
    det = GraphStreamingDetector(model) if graph else StreamingDetector(model)
    dev = det.device
    sectors = [s.to(dev) for s in split_turn(turn, model.cfg.sectors_per_turn)]
    state = det.new_state()
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if dev.type == "cuda" else [])
    with torch.inference_mode():
        for s in sectors:
            _, (state,) = det.step([s], [state])
        if isinstance(det, GraphStreamingDetector):
            inputs, cap = det.inputs([sectors[1]], [state]), det.planner.capacity(sectors[1].shape[0], 1)
            step = lambda: det.step_module(*inputs, cap)  # noqa: E731
        else:
            step = lambda: det.step([sectors[1]], [state])  # noqa: E731
        with profile(activities=activities, with_stack=True) as prof:
            step()
            if dev.type == "cuda":
                torch.cuda.synchronize(dev)
    events = prof.events()
    ops, views, syncs = Counter(), Counter(), Counter()
    for e in events:
        if not e.name.startswith("aten::"):
            continue
        where = _where(e)
        syncs[where] += e.name in SYNC_OPS  # at any depth: an op may wait inside another
        parent = e.cpu_parent
        if parent is not None and parent.name.startswith("aten::"):
            continue
        (views if e.name in VIEW_OPS else ops)[where] += 1
    rows = sorted(
        (OpRow(w, ops[w], views[w], syncs[w]) for w in ops.keys() | views.keys()),
        key=lambda r: (-r.ops, r.where),
    )
    kernels = sum(1 for e in events if e.device_type == torch.autograd.DeviceType.CUDA)
    return OpReport(
        config=model.cfg.name,
        engine=engine.value,
        device=str(dev),
        scan=resolve_scan(model.cfg.backbone.mamba.scan, dev).value,
        ops=sum(ops.values()),
        views=sum(views.values()),
        host_syncs=sum(syncs.values()),
        ops_outside_scan=sum(r.ops for r in rows if not r.where.startswith(SCAN_FILES)),
        cuda_kernels=kernels if dev.type == "cuda" else None,
        rows=rows,
    )
