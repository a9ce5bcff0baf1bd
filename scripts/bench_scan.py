"""The selective-scan implementations on the CPU, in one process: a training step and an eager streaming step.

Usage: PYTHONPATH=. python scripts/bench_scan.py [--impls chunked,numba] [--rounds 4] [--turns 16]
Training: three batches of 4 simulated training scans (the training pipeline, ground-truth sampling
included) through `TrainStep` (`tiny`, shipped weights), forward and backward, with each implementation in
turn, the order alternating every round; the first round's losses agree when the implementations do.
Streaming: the eager engine over KITTI 000000's 1/4 sectors (or a synthetic turn), one detector per
implementation (each on its own copy of the model), a turn of each in turn. Prints one table.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from model.config import ScanImpl
from model.detector import PHiM
from model.engine import engine_for
from model.sectors import split_turn
from model.tools.bench import _Streams
from model.tools.cli import load_model, load_turn
from model.train.distributed import Dist
from model.train.loop import TrainConfig, _loader
from model.train.step import TrainStep
from phim.process import tune_malloc


def _alternate(runs: dict[ScanImpl, object], rounds: int, once) -> dict[ScanImpl, list[float]]:
    """`once(impl, run)` -> times (s or ms) for every round, the order of impls reversed every other one."""
    impls = list(runs)
    times: dict[ScanImpl, list[float]] = {i: [] for i in impls}
    for r in range(rounds):
        for impl in impls if r % 2 == 0 else impls[::-1]:
            times[impl] += once(impl, runs[impl])
    return times


def train_steps(impls: list[ScanImpl], rounds: int) -> tuple[dict[ScanImpl, list[float]], dict]:
    model: PHiM = load_model("tiny", "default", "cpu").train()
    cfg = TrainConfig("tiny", data="sim", steps=100, batch_size=4, workers=0)
    step = TrainStep(model, cfg.loss)
    batches = [b for _, b in zip(range(3), _loader(cfg, model, Dist.from_env("cpu"), 0), strict=False)]
    losses: dict[ScanImpl, list[float]] = {i: [] for i in impls}

    def once(impl: ScanImpl, _) -> list[float]:
        model.set_scan(impl)  # the training step reads the layers' config at every call
        out = []
        for b in batches:
            model.zero_grad(set_to_none=True)
            t = time.perf_counter()
            loss = step(b).total
            loss.backward()
            out.append(time.perf_counter() - t)
            if len(losses[impl]) < len(batches):
                losses[impl].append(round(loss.item(), 5))
        return out

    return _alternate(dict.fromkeys(impls), rounds, once), losses


def stream_steps(impls: list[ScanImpl], turns: int) -> dict[ScanImpl, list[float]]:
    turn, _ = load_turn(None, fallback_kitti=True)
    runs = {}
    for impl in impls:  # the detector works on its own (BN-folded) copy: set the scan before building it
        model = load_model("tiny", "default", "cpu")
        model.set_scan(impl)
        runs[impl] = _Streams(engine_for(model), split_turn(turn, 4))
    _alternate(runs, 2, lambda _, run: run.turn())  # warm-up
    return _alternate(runs, turns, lambda _, run: run.turn())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--impls", default="chunked,numba")
    ap.add_argument("--rounds", type=int, default=4, help="training rounds (3 steps of each per round)")
    ap.add_argument("--turns", type=int, default=16, help="streaming turns of each (4 sectors each)")
    args = ap.parse_args()
    tune_malloc()
    impls = [ScanImpl(name) for name in args.impls.split(",")]
    train, losses = train_steps(impls, args.rounds)
    stream = stream_steps(impls, args.turns)
    print(f"\ntiny, {torch.get_num_threads()} threads; ratios to {impls[0].value}")
    print("| scan | training step p50 (4 scans) | ratio | eager sector p50 | ratio | first losses |")
    print("|---|---|---|---|---|---|")
    t0, s0 = statistics.median(train[impls[0]]), statistics.median(stream[impls[0]])
    for i in impls:
        t, s = statistics.median(train[i]), statistics.median(stream[i])
        print(f"| {i.value} | {t:.3f} s | {t / t0:.3f} | {s:.1f} ms | {s / s0:.3f} | {losses[i]} |")


if __name__ == "__main__":
    main()
