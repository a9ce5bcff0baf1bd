"""Where a streaming step's time goes: wall time per step against device kernel time, and the top kernels.

Usage: PYTHONPATH=. python scripts/profile_step.py --config paper --engine graph --device cuda --batch 1
       [--precision bf16] [--sector-points 32768] [--steps 8] [--rows 25] [--json FILE]
Streams KITTI 000000 (or a synthetic turn) like `phim bench model`, then records `--steps` steps with
torch.profiler and prints the kernels (CUDA) or ops (CPU) by total self time, and the share of the wall time
the device was busy. The numbers are for one machine and one hour: give both with them.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from collections import defaultdict

import torch
from torch.profiler import ProfilerActivity, profile

from model.config import Engine, Precision
from model.engine import EngineSettings, engine_for
from model.graph.engine import GraphStreamingDetector
from model.sectors import split_turn
from model.tools.cli import load_model, load_turn


def _args() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="paper")
    ap.add_argument("--checkpoint", default=None)
    ap.add_argument("--engine", default="graph", choices=[e.value for e in Engine])
    ap.add_argument("--precision", default="fp32", choices=[p.value for p in Precision])
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--batch", type=int, default=1)
    ap.add_argument("--sector-points", type=int, default=0, help="pad every sector to this (one bucket)")
    ap.add_argument("--steps", type=int, default=8)
    ap.add_argument("--rows", type=int, default=25)
    ap.add_argument("--json", default=None, help="write the table as JSON here")
    return ap.parse_args()


def main() -> None:
    a = _args()
    model = load_model(a.config, a.checkpoint, a.device)
    turn, source = load_turn(None, fallback_kitti=True)
    dev = model.device
    cuda = dev.type == "cuda"
    settings = EngineSettings(
        engine=Engine(a.engine), precision=Precision(a.precision), sector_points=a.sector_points
    )
    det = engine_for(model, settings)
    sectors = [s.to(dev) for s in split_turn(turn, model.cfg.sectors_per_turn)]
    t0 = time.perf_counter()
    if isinstance(det, GraphStreamingDetector):
        det.calibrate(sectors)
    states = [det.new_state() for _ in range(a.batch)]

    def step(k: int) -> float:
        nonlocal states
        sync()
        s = time.perf_counter()
        _, states = det.step([sectors[k % len(sectors)]] * a.batch, states)
        sync()
        return (time.perf_counter() - s) * 1e3

    def sync() -> None:
        if cuda:
            torch.cuda.synchronize(dev)

    for k in range(2 * len(sectors)):  # warm-up: compiles and captures every sector's bucket
        step(k)
    warm_s = time.perf_counter() - t0
    wall = [step(k) for k in range(4 * len(sectors))]
    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
    with profile(activities=acts) as prof:
        for k in range(a.steps):
            step(k)
    rows = _kernels(prof, cuda)
    busy_ms = sum(r["total_ms"] for r in rows) / a.steps
    p50 = statistics.median(wall)
    report = {
        "config": a.config,
        "engine": a.engine,
        "precision": a.precision,
        "batch": a.batch,
        "device": torch.cuda.get_device_name(dev) if cuda else "cpu",
        "input": source,
        "warmup_s": round(warm_s, 1),
        "p50_ms": round(p50, 2),
        "kernel_ms_per_step": round(busy_ms, 2),
        "kernels_per_step": round(sum(r["calls"] for r in rows) / a.steps, 1),
        "top": [dict(r, total_ms=round(r["total_ms"] / a.steps, 3)) for r in rows[: a.rows]],
    }
    _print(report, a.steps)
    if a.json:
        with open(a.json, "w") as f:
            json.dump(report, f, indent=1)


def _print(r: dict, steps: int) -> None:
    print(
        f"{r['config']} {r['engine']} {r['precision']} batch {r['batch']} on {r['device']}: "
        f"p50 {r['p50_ms']:.2f} ms, device busy {r['kernel_ms_per_step']:.2f} ms/step "
        f"({r['kernels_per_step']} kernels), warm-up {r['warmup_s']:.0f} s"
    )
    print("| ms/step | calls/step | kernel |")
    print("|---|---|---|")
    for k in r["top"]:
        print(f"| {k['total_ms']:.3f} | {k['calls'] / steps:.1f} | {k['name'][:110]} |")


def _kernels(prof, cuda: bool) -> list[dict]:
    """Device kernels (CUDA) or top-level ops' self time (CPU), summed by name, largest first."""
    total: dict[str, float] = defaultdict(float)
    calls: dict[str, int] = defaultdict(int)
    for e in prof.events():
        on_device = e.device_type == torch.autograd.DeviceType.CUDA
        if cuda != on_device:
            continue
        us = e.self_device_time_total if cuda else e.self_cpu_time_total
        total[e.name] += us / 1e3
        calls[e.name] += 1
    rows = [{"name": n, "total_ms": t, "calls": calls[n]} for n, t in total.items()]
    return sorted(rows, key=lambda r: -r["total_ms"])


if __name__ == "__main__":
    main()
