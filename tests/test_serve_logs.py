"""`phim serve`'s logs, from a real `python -m phim serve` process: JSON lines on stderr (--log-format json),
uvicorn's access log off by default and on with PHIM_ACCESS_LOG; and the JSON formatter on an exception."""

from __future__ import annotations

import io
import json
import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import httpx
from conftest import REPO
from server_helpers import START_TIMEOUT_S, free_port, post_first_sector

from server.logs import JsonFormatter

FIELDS = {"time", "level", "logger", "message"}


def serve_one_sector(tmp_path: Path, *flags: str, **env: str) -> tuple[str, str]:
    """Start `python -m phim serve` (CPU, no zenoh, our PHIM_ variables dropped), send it one sector
    over HTTP, stop it with SIGTERM -> (stdout, stderr); it must exit 0."""
    port = free_port()
    clean = {k: v for k, v in os.environ.items() if not k.startswith("PHIM_")}
    cmd = [sys.executable, "-m", "phim", "serve", "--port", str(port), "--device", "cpu", "--no-zenoh",
           "--warmup-sectors", "1", "--threads", "2", *flags]  # fmt: skip
    out, err = tmp_path / "stdout", tmp_path / "stderr"
    with out.open("wb") as o, err.open("wb") as e:
        proc = subprocess.Popen(cmd, env={**clean, **env}, stdout=o, stderr=e, cwd=REPO)
        try:
            url = f"http://127.0.0.1:{port}"
            wait_ready(url, proc, err)
            r = post_first_sector(url)
            assert r.status_code == 200, r.content[:300]
            proc.send_signal(signal.SIGTERM)
            rc = proc.wait(60)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    assert rc == 0, err.read_text()[-3000:]
    return out.read_text(), err.read_text()


def wait_ready(url: str, proc: subprocess.Popen, err: Path, timeout_s: float = START_TIMEOUT_S) -> None:
    deadline = time.monotonic() + timeout_s
    while True:
        assert proc.poll() is None, f"phim serve exited early: {err.read_text()[-3000:]}"
        try:
            if httpx.get(f"{url}/health/ready", timeout=5).status_code == 200:
                return
        except httpx.TransportError:
            pass  # not listening yet
        assert time.monotonic() < deadline, f"never ready: {err.read_text()[-3000:]}"
        time.sleep(0.2)


def json_lines(text: str) -> list[dict[str, Any]]:
    """Every line a JSON object with at least time, level, logger and message."""
    entries = [json.loads(line) for line in text.splitlines()]
    for entry in entries:
        assert set(entry) >= FIELDS, entry
    return entries


def test_json_logs_and_no_access_log_by_default(tmp_path: Path):
    stdout, stderr = serve_one_sector(tmp_path, "--log-format", "json")
    assert stdout == ""
    entries = json_lines(stderr)
    loggers = {e["logger"] for e in entries}
    assert {"phim.serve", "uvicorn.error", "server.worker", "server.warmup"} <= loggers, loggers
    assert "uvicorn.access" not in loggers and "/v1/streams" not in stderr  # no line for the request
    assert all(e["level"] in ("INFO", "WARNING") and e["time"].endswith("+00:00") for e in entries)
    messages = [e["message"] for e in entries]
    assert any(m.startswith("Uvicorn running on http://127.0.0.1:") for m in messages)
    assert messages[-1] == "stopped by signal 15 after a graceful shutdown"


def test_access_log_when_asked_for(tmp_path: Path):
    _, stderr = serve_one_sector(tmp_path, PHIM_ACCESS_LOG="true", PHIM_LOG_FORMAT="json")
    access = [e["message"] for e in json_lines(stderr) if e["logger"] == "uvicorn.access"]
    assert access[-1].endswith('"POST /v1/streams/car-1/sectors HTTP/1.1" 200'), access
    assert access[-2].endswith('"GET /health/ready HTTP/1.1" 200'), access  # the one that found it ready
    assert all('"GET /health/ready HTTP/1.1" ' in m for m in access[:-1]), access  # 503s while warming up


def test_json_formatter_keeps_an_exception_on_its_line():
    stream = io.StringIO()
    handler = logging.StreamHandler(stream)
    handler.setFormatter(JsonFormatter())
    logger = logging.getLogger("phim.test_json")
    logger.addHandler(handler)
    try:
        try:
            raise KeyError("missing")
        except KeyError:
            logger.error("lookup of %s failed: ünïcode", "missing", exc_info=True)
    finally:
        logger.removeHandler(handler)
    (line,) = stream.getvalue().splitlines()
    entry = json.loads(line)
    assert entry["level"] == "ERROR" and entry["logger"] == "phim.test_json"
    assert entry["message"] == "lookup of missing failed: ünïcode"
    assert entry["exception"].startswith("Traceback") and "KeyError: 'missing'" in entry["exception"]
