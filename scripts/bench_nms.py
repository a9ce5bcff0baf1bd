"""NMS of real candidates on the host: the numba kernel (model/geometry/nms_cpu.py) against its torch twin.

Usage: PYTHONPATH=. python scripts/bench_nms.py [--rounds 2]
Streams KITTI 000000 (or a synthetic turn) through the fixed-shape step of `tiny` (shipped weights) and
`paper` (untrained: 4,096 candidates a sector, the worst case), keeps each sector's candidates, then times
`select_detections` on them with each implementation in turn, alternating, and prints a table.
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
from model.layers.head import Candidates, select_detections
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
    state = det.init_state()
    for k in range(steps):
        _, (state,) = det.step([sectors[k % len(sectors)]], [state])
    engine.select_detections = select_detections
    return seen, model.cfg.head


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=2)
    a = ap.parse_args()
    torch.set_num_threads(2)
    fast, twin = nms._grouped_nms, nms._grouped_nms_torch
    rows = []
    for config, checkpoint in (("tiny", "default"), ("paper", None)):
        cands, head = candidates(config, checkpoint, 8 if config == "tiny" else 4)
        times: dict[str, list[float]] = {"numba": [], "torch twin": []}
        for _ in range(a.rounds):
            for name, impl in (("torch twin", twin), ("numba", fast)):
                nms._grouped_nms = impl
                for c in cands:
                    t0 = time.perf_counter()
                    kept = select_detections(c, head)
                    times[name].append((time.perf_counter() - t0) * 1e3)
        nms._grouped_nms = fast
        n = max(int(((c.heat > 0) & (c.heat >= head.score_threshold)).sum()) for c in cands)
        twin_ms, fast_ms = statistics.median(times["torch twin"]), statistics.median(times["numba"])
        rows.append((config, n, len(kept[0]), twin_ms, fast_ms))
    print("| config | candidates (most) | kept (last) | torch twin p50 | numba p50 | ratio |")
    print("|---|---|---|---|---|---|")
    for config, n, k, t, f in rows:
        print(f"| {config} | {n} | {k} | {t:.2f} ms | {f:.2f} ms | {f / t:.2f} |")


if __name__ == "__main__":
    main()
