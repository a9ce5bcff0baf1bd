"""Run a load test end to end: connect, read the model's sectors per turn, load the sectors, run every step
in one event loop (one client for all vehicles), summarize, write the files."""

from __future__ import annotations

import asyncio
import logging
from pathlib import Path

from clients.base import ClientError, DetectorClient
from clients.connect import make_client
from clients.loadtest.config import LoadTestConfig, Mode, OutputConfig
from clients.loadtest.plots import write_plots
from clients.loadtest.progress import LiveProgress
from clients.loadtest.report import LoadTestReport, write_csv, write_json
from clients.loadtest.runner import StepRunner
from clients.loadtest.source import load_source
from clients.loadtest.stats import StepResult, summarize

log = logging.getLogger(__name__)
DEFAULT_SECTORS = 4


def sectors_per_turn(client: DetectorClient, cfg: LoadTestConfig) -> int:
    if cfg.sectors_per_turn is not None:
        return cfg.sectors_per_turn
    try:
        return int(client.model_info()["sectors_per_turn"])
    except ClientError as e:
        log.warning("model info unavailable (%s); assuming %d sectors per turn", e, DEFAULT_SECTORS)
        return DEFAULT_SECTORS


def run_loadtest(cfg: LoadTestConfig, out: OutputConfig | None = None) -> LoadTestReport:
    out = out or OutputConfig()
    client = make_client(cfg.connect, max_connections=None)  # a send never waits for a free connection
    try:
        spt = sectors_per_turn(client, cfg)
        source = load_source(cfg.source, spt)
        steps = asyncio.run(_run_steps(client, source, cfg, spt, out.progress))
    finally:
        client.close()
    report = LoadTestReport(
        client.transport, cfg.mode.value, source.description, spt, cfg, steps, retried=client.retries
    )
    write_outputs(report, out)
    return report


async def _run_steps(
    client: DetectorClient, source, cfg: LoadTestConfig, spt: int, progress: bool
) -> list[StepResult]:
    runner = StepRunner(client, source, cfg, spt)
    results: list[StepResult] = []
    try:
        with LiveProgress(progress) as live:
            for i, vehicles in enumerate(cfg.vehicles):
                if i:
                    await asyncio.sleep(cfg.settle_s)
                live.start_step(vehicles, cfg.warmup_s + cfg.measure_s)
                step = await runner.run(vehicles, live.tick)
                results.append(summarize(step, cfg, client.transport))
                if cfg.sweep and cfg.mode is Mode.OPEN and cfg.stop_after_failure and not results[-1].held:
                    break
    finally:
        await client.aclose()
    return results


def write_outputs(report: LoadTestReport, out: OutputConfig) -> list[Path]:
    written: list[Path] = []
    if out.json_path is not None:
        write_json(report, out.json_path)
        written.append(out.json_path)
    if out.csv_path is not None:
        write_csv(report, out.csv_path)
        written.append(out.csv_path)
    if out.plots_dir is not None:
        written += write_plots(report, out.plots_dir)
    return written
