"""The Docker image's commands, run directly (no Docker engine here): the weights step, the CMD as a real
`phim serve` process with the image's environment, the HEALTHCHECK, one sector, SIGTERM and a clean exit.
Also the Dockerfile and compose essentials."""

from __future__ import annotations

import importlib.util
import json
import os
import re
import shlex
import signal
import socket
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import httpx
import pytest
import torch
import yaml
from conftest import REPO
from pydantic import ValidationError
from server_helpers import START_TIMEOUT_S, free_port, post_first_sector

from contract import DetectionsReply, decode_response
from server.settings import Settings

DOCKERFILE = REPO / "Dockerfile"
COMPOSE = REPO / "deploy" / "docker-compose.yml"
BIN = Path(sys.executable).parent


def instructions() -> list[tuple[str, str]]:
    """Dockerfile -> [(INSTRUCTION, arguments)], continuation lines joined, comments dropped, ${ARG}s replaced
    by their defaults."""
    text = re.sub(r"\\\n", " ", DOCKERFILE.read_text())
    out, args = [], {}
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            word, _, rest = line.partition(" ")
            rest = re.sub(r"\$\{(\w+)\}", lambda m: args[m[1]], rest.strip())
            if word.upper() == "ARG":
                name, _, default = rest.partition("=")
                args[name] = default
            out.append((word.upper(), rest))
    return out


def image_env() -> dict[str, str]:
    env = {}
    for word, rest in instructions():
        if word == "ENV":
            env.update(dict(kv.split("=", 1) for kv in shlex.split(rest)))
    return env


def test_dockerfile_essentials():
    ins = instructions()
    words = [w for w, _ in ins]
    base = dict(ins)["FROM"]
    assert base.startswith("pytorch/pytorch:") and "cuda" in base
    users = [rest for w, rest in ins if w == "USER"]
    assert users and users[-1] not in ("root", "0")
    assert words.index("USER") < words.index("CMD")
    runs = " ".join(rest for w, rest in ins if w == "RUN")
    # never reinstalls the base image's torch
    assert '".[server,ros2]"' in runs and "torch-constraint" in runs
    assert "-c constraints.txt" in runs  # the pinned versions CI runs with
    copied = {rest.split()[0] for w, rest in ins if w == "COPY"}
    packages = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]["find"]
    assert {p.rstrip("*") for p in packages["include"]} <= copied  # every package of the project is copied
    assert "constraints.txt" in " ".join(rest for w, rest in ins if w == "COPY")
    assert "python -m server.default_model --out" in runs  # weights inside
    assert re.search(r"apt-get install .*\bgcc\b", runs)  # Triton builds its kernel launchers with it
    health = dict(ins)["HEALTHCHECK"]
    assert json.loads(health.split("CMD", 1)[1]) == ["python", "-m", "server.healthcheck"]
    cmd = json.loads(dict(ins)["CMD"])  # exec form (a JSON array), so SIGTERM reaches phim directly
    assert cmd == ["phim", "serve", "--host", "0.0.0.0"]
    assert image_env()["PHIM_CHECKPOINT"].startswith("/opt/phim/weights/")
    assert "PHIM_INSECURE" not in image_env() and "PHIM_AUTH_TOKENS" not in image_env()  # the operator says


def test_the_image_command_refuses_to_serve_all_interfaces_without_tokens():
    cmd = json.loads(dict(instructions())["CMD"])
    env = {**os.environ, **image_env()}
    env.pop("PHIM_INSECURE", None)
    r = subprocess.run([str(BIN / cmd[0]), *cmd[1:]], env=env, capture_output=True, text=True, timeout=60)
    assert r.returncode == 2, r.stderr[-2000:]
    assert "host 0.0.0.0: beyond loopback without --auth-tokens" in r.stderr and "PHIM_INSECURE=1" in r.stderr


def test_a_start_up_that_fails_exits_with_code_1():
    """The documented exit code when the server cannot start: here its zenoh endpoint is taken."""
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        endpoint = f"tcp/127.0.0.1:{taken.getsockname()[1]}"
        cmd = [str(BIN / "phim"), "serve", "--port", str(free_port()), "--zenoh-listen", endpoint]
        r = subprocess.run([*cmd, "--warmup-sectors", "1"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 1 and "Address already in use" in r.stderr, (r.returncode, r.stderr[-800:])


def test_compose_essentials():
    compose = yaml.safe_load(COMPOSE.read_text())
    router, server = compose["services"]["zenoh-router"], compose["services"]["phim-worker-0"]
    assert router["image"].startswith("eclipse/zenoh:")
    env = server["environment"]
    assert env["PHIM_ZENOH_MODE"] == "client" and env["PHIM_ZENOH_CONNECT"] == "tcp/zenoh-router:7447"
    devices = server["deploy"]["resources"]["reservations"]["devices"]
    assert devices[0]["driver"] == "nvidia" and "gpu" in devices[0]["capabilities"]
    assert server["build"]["dockerfile"] == "Dockerfile" and "zenoh-router" in server["depends_on"]
    published = [p for service in compose["services"].values() for p in service.get("ports", [])]
    assert published and all(p.startswith("127.0.0.1:") for p in published)  # nothing on all interfaces
    assert env["PHIM_INSECURE"] == "1" and not any(p.endswith(":8000") for p in published)


def test_image_commands_serve_a_sector_and_stop_cleanly(tmp_path: Path):
    env = {**os.environ, **image_env()}
    weights = tmp_path / "phim-default.pt"
    subprocess.run(
        [sys.executable, "-m", "server.default_model", "--out", str(weights)], check=True, cwd=REPO
    )
    port = free_port()
    env.update(PHIM_CHECKPOINT=str(weights), PHIM_PORT=str(port), PHIM_THREADS="2", PHIM_WARMUP_SECTORS="2")
    env["PHIM_MIN_SCORE"] = "0"  # every box: a reply with boxes shows the model ran on the sector
    if importlib.util.find_spec("server.zenoh_transport") is not None:
        env["PHIM_ZENOH_LISTEN"] = f"tcp/127.0.0.1:{free_port()}"
    else:  # the zenoh transport is not in this checkout yet
        env["PHIM_ZENOH_ENABLED"] = "false"
    cmd = json.loads(dict(instructions())["CMD"])
    cmd = [str(BIN / cmd[0]), *("127.0.0.1" if a == "0.0.0.0" else a for a in cmd[1:])]
    log = tmp_path / "serve.log"
    with log.open("wb") as out:
        proc = subprocess.Popen(cmd, env=env, stdout=out, stderr=subprocess.STDOUT, cwd=tmp_path)
        try:
            wait_healthy(env, proc, log)
            r = post_first_sector(f"http://127.0.0.1:{port}")
            reply = decode_response(r.content)
            assert r.status_code == 200 and isinstance(reply, DetectionsReply) and len(reply.scores) > 0
            model = httpx.get(f"http://127.0.0.1:{port}/v1/model", timeout=10).json()
            assert model["weights"] == f"checkpoint {weights}"
            proc.send_signal(signal.SIGTERM)
            rc = proc.wait(60)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    text = log.read_text()
    assert rc == 0, text[-3000:]
    assert f"device={'cuda' if torch.cuda.is_available() else 'cpu'}" in text and "warm-up" in text
    assert "stopped by signal 15 after a graceful shutdown" in text and "Traceback" not in text


def wait_healthy(
    env: dict[str, str], proc: subprocess.Popen, log: Path, timeout_s: float = START_TIMEOUT_S
) -> None:
    """Run the image's HEALTHCHECK command until it passes."""
    deadline = time.monotonic() + timeout_s
    while True:
        assert proc.poll() is None, f"phim serve exited early: {log.read_text()[-3000:]}"
        check = subprocess.run(
            [sys.executable, "-m", "server.healthcheck"], env=env, capture_output=True, cwd=REPO
        )
        if check.returncode == 0:
            return
        assert time.monotonic() < deadline, f"never ready: {check.stdout!r} {log.read_text()[-3000:]}"
        time.sleep(0.3)


def test_settings_defaults_env_and_flags(monkeypatch: pytest.MonkeyPatch):
    for key in [k for k in os.environ if k.startswith("PHIM_")]:
        monkeypatch.delenv(key)
    s = Settings()
    assert (s.host, s.port, s.device, s.checkpoint, s.idle_timeout_s) == (
        "127.0.0.1",
        8080,
        "auto",
        None,
        10.0,
    )
    z = s.zenoh_config()
    assert (z.mode, z.listen, z.connect, z.multicast_scouting) == ("peer", ("tcp/127.0.0.1:7447",), (), False)
    monkeypatch.setenv("PHIM_ZENOH_MODE", "client")
    monkeypatch.setenv("PHIM_ZENOH_CONNECT", "tcp/router:7447, tcp/backup:7447")
    monkeypatch.setenv("PHIM_ZENOH_LISTEN", "")
    monkeypatch.setenv("PHIM_MAX_BATCH", "4")
    s = Settings(max_batch=2)  # what `phim serve --max-batch 2` does: flags win over the environment
    assert s.max_batch == 2 and s.zenoh_listen == () and s.zenoh_mode == "client"
    assert s.zenoh_config().connect == ("tcp/router:7447", "tcp/backup:7447")
    with pytest.raises(ValidationError, match="device"):
        Settings(device="gpu")
    with pytest.raises(ValidationError, match="max_batch"):
        Settings(max_batch=0)
