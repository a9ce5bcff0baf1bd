"""bf16 against fp32 detections of the shipped model on the KITTI samples (docs/benchmarks.md, "bf16 against
fp32"): each scan streamed as one turn, the full-turn detections compared. A fp32 box is matched when a bf16
box of its class lies within 5 cm (centre).

Usage (from the repository root): PYTHONPATH=. python scripts/bf16_agreement.py [--device D] [--engine E]
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass, field

import torch

from lidar.samples import KITTI_VELODYNE
from model.checkpoint import load_default_model
from model.config import Engine, Precision
from model.engine import EngineSettings, StreamEngine, engine_for
from model.geometry.boxes import Detections
from model.graph.engine import GraphStreamingDetector
from model.sectors import load_kitti_bin, split_turn

MATCH_M = 0.05
SCANS = range(6)  # KITTI object 000000-000005


@dataclass
class Agreement:
    fp32_boxes: int = 0
    bf16_boxes: int = 0
    matched: int = 0
    dist: list[torch.Tensor] = field(default_factory=list)  # matched centre distances (metres), per scan
    score_diff: list[torch.Tensor] = field(default_factory=list)  # matched |fp32 - bf16 score|, per scan

    def add(self, fp32: Detections, bf16: Detections, min_score: float) -> None:
        keep = fp32.scores >= min_score
        boxes, labels, scores = fp32.boxes[keep], fp32.labels[keep], fp32.scores[keep]
        dist = torch.cdist(boxes[:, :3], bf16.boxes[:, :3])  # (n32, n16)
        dist[labels[:, None] != bf16.labels[None, :]] = float("inf")
        nearest, j = dist.min(1)  # (n32,)
        ok = nearest <= MATCH_M
        self.fp32_boxes += len(boxes)
        self.bf16_boxes += int((bf16.scores >= min_score).sum())
        self.matched += int(ok.sum())
        self.dist.append(nearest[ok])
        self.score_diff.append((scores[ok] - bf16.scores[j[ok]]).abs())

    def line(self) -> str:
        d, s = torch.cat(self.dist), torch.cat(self.score_diff)
        return (
            f"fp32 boxes {self.fp32_boxes}, bf16 boxes {self.bf16_boxes}, matched {self.matched} "
            f"({self.matched / self.fp32_boxes:.1%}); centre distance mean {d.mean() * 100:.2f} cm, max "
            f"{d.max() * 100:.2f} cm; |score difference| mean {s.mean():.4f}, max {s.max():.4f}"
        )


def full_turn(det: StreamEngine, sectors: list[torch.Tensor]) -> Detections:
    if isinstance(det, GraphStreamingDetector):
        det.calibrate(sectors)
    state = det.new_state()
    for s in sectors:
        (result,), (state,) = det.step([s], [state])
    return result.detections.to(torch.device("cpu"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--engine", type=Engine, default=Engine.EAGER)
    args = parser.parse_args()
    model = load_default_model(args.device)[0]
    fp32, bf16 = (engine_for(model, EngineSettings(engine=args.engine, precision=p)) for p in Precision)
    by_score = {0.3: Agreement(), 0.5: Agreement()}
    for i in SCANS:
        turn = load_kitti_bin(str(KITTI_VELODYNE / f"{i:06d}.bin"))
        sectors = [s.to(args.device) for s in split_turn(turn, model.cfg.sectors_per_turn)]
        a, b = full_turn(fp32, sectors), full_turn(bf16, sectors)
        for min_score, agreement in by_score.items():
            agreement.add(a, b, min_score)
    for min_score, agreement in by_score.items():
        print(f"{args.engine.value}, score >= {min_score}: {agreement.line()}")


if __name__ == "__main__":
    main()
