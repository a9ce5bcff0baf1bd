"""The soak script's CI version: a real `phim serve` at twice its measured ceiling for 60 s over HTTP and
zenoh at once: every sector answered exactly once, no gross RSS growth, no live streams after the idle
timeout (scripts/soak.sh runs it for ten minutes). The offered rate derives from the ceiling measured in the
run, so a busy machine gets twice its own ceiling, not a fixed sensor rate (two vehicles at 40 sectors/s were
8-90 times the ceiling of a busy 2-core machine)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def test_sixty_seconds_at_twice_the_ceiling(tmp_path: Path) -> None:
    out = tmp_path / "soak.json"
    cmd = [sys.executable, str(REPO / "scripts" / "soak.py"), "--duration", "60", "--out", str(out)]
    # a minute is too short to judge a slope (the allocator's arenas still grow and the heap in use swings
    # with the queue: at 2x a ceiling of 24-31 sectors/s on the 2-core machine its second half rose 190-356
    # MB/min): only a gross leak fails here; the ten-minute run (scripts/soak.sh) holds the RSS to 20 MB/min
    # and the heap in use to 5
    cmd += ["--max-rss-slope", "600", "--max-heap-slope", "600"]
    # idle eviction after 2 s, not 5: the check after the load waits less (a vehicle's sectors come less than
    # 2 s apart at any ceiling over 0.5 sectors/s; one evicted between two of them is answered all the same)
    cmd += ["--idle-timeout", "2"]
    env = {**os.environ, "PHIM_WARMUP_SECTORS": "1"}  # the server's warm-up: one forward, not five
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=2400, env=env)  # a busy machine is slow
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    result = json.loads(out.read_text())
    assert all(result["checks"].values()), result
    assert 10 < result["heap_mb_start"] < result["rss_mb_start"]  # the heap gauge was read
    offered, ceiling = result["offered_sectors_per_s"], result["capacity_sectors_per_s"]
    slowest = 0.01 * 4 * sum(result["vehicles"].values())  # vehicles at 0.01 turns/s: a load test's slowest
    assert offered == pytest.approx(max(2 * ceiling, slowest), rel=0.01, abs=0.01), result  # twice its own
    sent = sum(report["sent"] for report in result["reports"].values())
    assert sent <= 1.05 * offered * 60 + 8, result  # on schedule (open loop): never more than offered
    for report in result["reports"].values():
        assert report["sent"] > 0 and report["lost"] == 0 and report["errors"] > 0  # overload was reached
