"""`phim loadtest --transport zenoh --workers auto` with no worker alive (a real router, nobody behind it):
the event loop never blocks, every sector gets its transport error after one bounded wait, the run ends with
its duration, the report counts every sector, and the exit code is 1."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from server_helpers import free_endpoint

from server.zenoh_transport import ZenohConfig, open_session

VEHICLES, TURNS_PER_S, SPT, DURATION_S = 3, 5, 4, 3


def test_no_live_worker_ends_the_run_on_time_with_every_sector_counted(tmp_path: Path) -> None:
    endpoint, out = free_endpoint(), tmp_path / "lt.json"
    args = ["loadtest", "--transport", "zenoh", "--zenoh-connect", endpoint, "--workers", "auto"]
    args += ["--synthetic", "--every", "16", "--vehicles", str(VEHICLES), "--turns-per-s", str(TURNS_PER_S)]
    args += ["--sectors-per-turn", str(SPT), "--duration", str(DURATION_S), "--timeout", "2"]
    args += ["--no-progress", "--out", str(out)]
    with open_session(ZenohConfig(mode="router", listen=(endpoint,))):
        # bounded: before, each scheduled sector blocked the loop up to 2 s (180 sectors: 6 minutes)
        r = subprocess.run([sys.executable, "-m", "phim", *args], capture_output=True, text=True, timeout=120)
    assert r.returncode == 1, r.stderr[-3000:]
    doc = json.loads(out.read_text())
    scheduled = VEHICLES * DURATION_S * TURNS_PER_S * SPT
    assert abs(doc["sent"] - scheduled) <= VEHICLES, doc["sent"]  # every sector due was sent and counted
    assert doc["lost"] == doc["sent"] and doc["lost_by_reason"] == {"transport": doc["sent"]}  # no drain
    assert doc["answered"] == 0
