"""NMS of real candidates on the host, for one stream and a batch: the batch kernel, the numba NMS item by
item, and its torch twin (model/geometry/nms.py, model/ops/nms_numba.py).

Usage: PYTHONPATH=. python scripts/bench_nms.py [--rounds 2] [--streams 1,32]
Streams KITTI 000000 (or a synthetic turn) through the fixed-shape step of `tiny` (shipped weights) and
`paper` (untrained: 4,096 candidates a sector, the worst case), keeps each sector's candidates, stacks them
into batches of each size (a server's batch: one sector per stream), then times `select_detections` on them
with each implementation in turn, alternating, and prints a table.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

import model.geometry.nms as nms
from model.config import HeadConfig
from model.graph import engine
from model.graph.engine import GraphStreamingDetector
from model.layers.head import Candidates, select_detections, select_detections_plain
from model.sectors import split_turn
from model.tools.cli import load_model, load_turn


def candidates(config: str, checkpoint: str | None, steps: int) -> tuple[list[Candidates], HeadConfig]:
    """The candidates the fixed-shape step hands to NMS for `steps` streamed sectors."""
    model = load_model(config, checkpoint, "cpu")
    turn, _ = load_turn(None, fallback_kitti=True)
    det = GraphStreamingDetector(model)
    sectors = split_turn(turn, model.cfg.sectors_per_turn)
    seen: list[Candidates] = []

    def keep(c: Candidates, head: HeadConfig) -> list:
        seen.append(c)
        return select_detections(c, head)

    engine.select_detections = keep  # the step's NMS call, seen from here
    state = det.new_state()
    for k in range(steps):
        _, (state,) = det.step([sectors[k % len(sectors)]], [state])
    engine.select_detections = select_detections
    return seen, model.cfg.head


def batch_of(cands: list[Candidates], streams: int) -> Candidates:
    """`streams` streams' candidates in one batch, the recorded sectors' in turn."""
    picks = [cands[k % len(cands)] for k in range(streams)]
    fields = ("boxes", "scores", "labels", "heat")
    return Candidates(*(torch.cat([getattr(c, f) for c in picks]) for f in fields))


IMPLS = {  # name -> (the NMS of a batch, the greedy pass an item's `class_nms` uses)
    "torch twin": (select_detections_plain, nms._grouped_nms_torch),
    "numba item by item": (select_detections_plain, nms._grouped_nms),
    "batch kernel": (select_detections, nms._grouped_nms),
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--streams", default="1,32", help="batch sizes, comma-separated")
    a = ap.parse_args()
    torch.set_num_threads(2)
    rows = []
    for config, checkpoint in (("tiny", "default"), ("paper", None)):
        cands, head = candidates(config, checkpoint, 8 if config == "tiny" else 4)
        n = max(int(((c.heat > 0) & (c.heat >= head.score_threshold)).sum()) for c in cands)
        for streams in (int(x) for x in a.streams.split(",")):
            batch = batch_of(cands, streams)
            times: dict[str, list[float]] = {name: [] for name in IMPLS}
            for _ in range(a.rounds * max(1, 8 // streams)):
                for name, (select, greedy) in IMPLS.items():
                    nms._grouped_nms = greedy
                    t0 = time.perf_counter()
                    select(batch, head)
                    times[name].append((time.perf_counter() - t0) * 1e3)
            rows.append((config, streams, n, *(statistics.median(times[name]) for name in IMPLS)))
    nms._grouped_nms = IMPLS["batch kernel"][1]
    print("| config | streams | candidates (most) | torch twin | numba item by item | batch kernel |")
    print("|---|---|---|---|---|---|")
    for config, streams, n, twin, item, batch in rows:
        print(f"| {config} | {streams} | {n} | {twin:.2f} ms | {item:.2f} ms | {batch:.2f} ms |")


if __name__ == "__main__":
    main()
