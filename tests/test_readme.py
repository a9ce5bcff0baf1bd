"""Every python snippet of README.md runs as written, in the order the README gives them, from the repository
root (as in a fresh clone), against a real uvicorn server serving the default model: with the real samples,
and without them (PHIM_SAMPLES_DIR pointing at an empty folder: a clone without ../shared). Only the
server's address is put in for the README's 127.0.0.1:8080 (the test's server has a free port)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from conftest import require_samples
from server_helpers import RunningServer, default_detector, serve

REPO = Path(__file__).resolve().parents[1]
README_URL = "http://127.0.0.1:8080"
BOXES = re.compile(r"^\(\d+, 7\) ")  # a snippet's line for a DetectionsReply: its boxes' shape first


def python_snippets() -> list[str]:
    return re.findall(r"^```python\n(.*?)^```", (REPO / "README.md").read_text(), flags=re.S | re.M)


@pytest.fixture(scope="module")
def server() -> Iterator[RunningServer]:
    with serve(default_detector()) as s:
        yield s


def run_snippets(url: str, env: dict[str, str]) -> None:
    snippets = python_snippets()
    assert len(snippets) >= 3 and sum(README_URL in s for s in snippets) >= 2, "the README's snippets moved"
    for code in snippets:
        r = subprocess.run(
            [sys.executable, "-c", code.replace(README_URL, url)],
            cwd=REPO, env=env, capture_output=True, text=True, timeout=600,
        )  # fmt: skip
        assert r.returncode == 0, f"{code}\n{r.stdout[-2000:]}\n{r.stderr[-3000:]}"
        lines = r.stdout.splitlines()
        assert lines, code
        if README_URL in code:  # every sector sent got its detections (no 409 stale, no other error)
            assert all(BOXES.match(line) for line in lines), f"{code}\n{r.stdout}"


def end_streams(url: str) -> None:
    """The README's streams ended (as its DELETE says), so that a second run starts them afresh."""
    for stream in ("car-1", "car-2"):
        assert httpx.delete(f"{url}/v1/streams/{stream}", timeout=30).status_code in (200, 404)


def test_the_readme_snippets_run_with_the_samples(server: RunningServer) -> None:
    require_samples()
    end_streams(server.url)
    run_snippets(server.url, dict(os.environ))


def test_the_readme_snippets_run_in_a_clone_without_the_samples(
    server: RunningServer, tmp_path: Path
) -> None:
    end_streams(server.url)
    (tmp_path / "no-samples").mkdir()
    run_snippets(server.url, {**os.environ, "PHIM_SAMPLES_DIR": str(tmp_path / "no-samples")})
