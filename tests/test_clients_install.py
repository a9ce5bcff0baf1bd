"""A clients-only install, as a user makes it: `pip install ".[clients]"` in a fresh virtual environment gets
no torch, and its `phim loadtest`, `phim replay`, Python clients and sectorizer work against a real server."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from client_helpers import serve_both
from conftest import REPO
from server_helpers import default_detector

from contract import REQUIRED_FIELDS
from lidar.readers import write_native_scan
from lidar.synthetic import synthetic_turn

SOURCES = (
    "pyproject.toml",
    "README.md",
    "LICENSE",
    "contract",
    "lidar",
    "ros",
    "phim",
    "model",
    "server",
    "clients",
)
CLIENT_CODE = """
from clients.http_client import HttpClient
from lidar.sectorizer import split_scan
from lidar.synthetic import synthetic_turn
turn = synthetic_turn(seed=1)[::8]
with HttpClient("{url}") as client:
    for seq, sector in enumerate(split_scan(turn, ("x", "y", "z", "intensity"), sectors=4)):
        reply = client.send_points("py-client", seq, sector.index, sector.points)
print(reply.context_sectors, reply.boxes.shape[1])
"""


def run(*cmd: str | Path, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    done = subprocess.run([str(c) for c in cmd], capture_output=True, text=True, timeout=timeout, cwd="/")
    assert done.returncode == 0, f"{cmd}: {done.stderr[-3000:]}"
    return done


@pytest.fixture(scope="module")
def venv(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A fresh virtual environment with the package's `clients` extra, installed from a copy of this checkout
    (pip builds in the source tree: the copy keeps build/ out of the repository)."""
    root, source = tmp_path_factory.mktemp("clients-venv"), tmp_path_factory.mktemp("source")
    for name in SOURCES:
        if (REPO / name).is_dir():
            shutil.copytree(REPO / name, source / name, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy(REPO / name, source / name)
    run(sys.executable, "-m", "venv", root)
    pip = [root / "bin" / "python", "-m", "pip", "install", "-q", "--disable-pip-version-check"]
    run(*pip, "-c", REPO / "constraints.txt", f"{source}[clients]", timeout=900)
    return root


@pytest.mark.slow
def test_a_clients_only_install_has_no_torch_and_its_clients_work(venv: Path, tmp_path: Path) -> None:
    python, phim = venv / "bin" / "python", venv / "bin" / "phim"
    no_torch = subprocess.run([python, "-c", "import torch"], capture_output=True, text=True)
    assert no_torch.returncode != 0 and "No module named 'torch'" in no_torch.stderr
    assert run(phim, "--version").stdout.startswith("phim, version ")
    drive = tmp_path / "drive"
    drive.mkdir()
    write_native_scan(drive / "000000.npz", synthetic_turn(seed=2)[::8], REQUIRED_FIELDS)
    with serve_both(default_detector(), deadline_ms=60_000) as served:
        for transport in ("http", "zenoh"):
            args = ["--transport", transport, "--url", served.url, "--zenoh-connect", served.zenoh_endpoint]
            args += ["--synthetic", "--every", "8", "--duration", "1", "--turns-per-s", "2", "--no-progress"]
            doc = json.loads(run(phim, "loadtest", *args, "--json").stdout)
            assert doc["sent"] == doc["answered"] == doc["ok"] > 0, doc
        predictions = tmp_path / "predictions.jsonl"
        args = ["--url", served.url, "--rate", "0", "--out", predictions, "--json"]
        summary = json.loads(run(phim, "replay", drive, *args).stdout)
        assert summary["scans"] == 1 and summary["ok"] == 4 and summary["errors"] == 0
        assert len(predictions.read_text().splitlines()) == 1 + 4  # a header, then one record per sector
        context, columns = run(python, "-c", CLIENT_CODE.format(url=served.url)).stdout.split()
    assert (int(context), int(columns)) == (4, 7)
