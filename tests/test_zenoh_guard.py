"""zenoh's safe defaults, with the real CLI and settings: a listener beyond loopback needs a config file that
guards it (an ACL, mTLS or user/password) or --insecure; with --auth-tokens zenoh is never left open; a zenoh
client listens nowhere unless asked, so two workers on one host join one router (`phim router`)."""

from __future__ import annotations

import contextlib
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import IO

import pytest
from conftest import REPO
from pydantic import ValidationError
from server_helpers import free_endpoint, free_port

from clients.bench.fleet import spawned_router
from clients.bench.server import spawned
from contract import KeySpace
from server.auth import add_token
from server.settings import Settings
from server.zenoh_transport import ZenohConfig, build_config, open_session

SAMPLES = REPO / "deploy" / "zenoh"
PHIM = [sys.executable, "-m", "phim"]


def serve_cli(*args: str, timeout_s: float = 120) -> subprocess.CompletedProcess[str]:
    port = str(free_port())
    cmd = [*PHIM, "serve", "--port", port, "--warmup-sectors", "1", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s, cwd=REPO)


def test_a_zenoh_listener_beyond_loopback_needs_a_guard_or_insecure():
    r = serve_cli("--zenoh-listen", "tcp/0.0.0.0:7447")
    assert r.returncode == 2, r.stderr[-2000:]
    assert "zenoh_listen tcp/0.0.0.0:7447: beyond loopback zenoh without an ACL" in r.stderr
    assert "--zenoh-config-file" in r.stderr and "PHIM_INSECURE=1" in r.stderr
    for endpoint in ("tcp/127.0.0.1:7447", "tcp/[::1]:7447", "tcp/localhost:7447"):
        assert Settings(zenoh_listen=endpoint).zenoh_exposed() is None
    for endpoint in ("tcp/0.0.0.0:7447", "tcp/[::]:7447", "tls/10.0.0.1:7447", "udp/192.168.1.2:7447"):
        with pytest.raises(ValidationError, match="beyond loopback"):
            Settings(zenoh_listen=endpoint)
        assert Settings(zenoh_listen=endpoint, insecure=True).zenoh_config().guard_required is False
        guarded = Settings(zenoh_listen=endpoint, zenoh_config_file=SAMPLES / "worker-mtls-acl.json5")
        assert guarded.zenoh_config().guard_required is True
    # the ROS 2 bridge opens the same session when zenoh itself is off
    with pytest.raises(ValidationError, match="beyond loopback"):
        Settings(zenoh_enabled=False, zenoh_listen="tcp/0.0.0.0:7447", ros2_points="/car1/lidar/points")


def test_with_auth_tokens_zenoh_is_never_left_open(tmp_path: Path):
    tokens = tmp_path / "tokens.jsonl"
    add_token(tokens, "car-")
    r = serve_cli("--auth-tokens", str(tokens))  # zenoh on its default loopback endpoint, unguarded
    assert r.returncode == 2, r.stderr[-2000:]
    assert "--auth-tokens: HTTP needs a token, but zenoh without an ACL" in r.stderr
    with pytest.raises(ValidationError, match="HTTP needs a token"):
        Settings(auth_tokens=tokens, zenoh_mode="client", zenoh_connect="tcp/router:7447")
    with pytest.raises(ValidationError, match="HTTP needs a token"):
        Settings(auth_tokens=tokens, zenoh_listen="", zenoh_multicast_scouting=True)
    # reachable by none, off, guarded by a config file, or accepted: it starts
    assert Settings(auth_tokens=tokens, zenoh_listen="").zenoh_exposed() is None
    assert Settings(auth_tokens=tokens, zenoh_enabled=False).zenoh_exposed() is None
    sample = SAMPLES / "worker-usrpwd-acl.json5"
    assert Settings(auth_tokens=tokens, zenoh_config_file=sample).zenoh_config().guard_required
    assert Settings(auth_tokens=tokens, insecure=True).zenoh_exposed() is not None


def test_a_config_file_that_guards_nothing_refuses_to_start(tmp_path: Path):
    bare = tmp_path / "bare.json5"
    bare.write_text("{ scouting: { multicast: { enabled: false } } }\n")
    r = serve_cli("--zenoh-listen", f"tcp/0.0.0.0:{free_port()}", "--zenoh-config-file", str(bare))
    assert r.returncode == 2, r.stderr[-2000:]
    assert f"zenoh config file {bare}: no ACL" in r.stderr.replace("\n", "")
    for name in ("worker-mtls-acl.json5", "worker-usrpwd-acl.json5", "router-mtls-acl.json5"):
        build_config(ZenohConfig(config_file=str(SAMPLES / name), guard_required=True))  # accepted
    with pytest.raises(ValueError, match="no ACL"):
        build_config(ZenohConfig(config_file=str(bare), guard_required=True))
    build_config(ZenohConfig(config_file=str(bare)))  # on loopback without tokens: nothing required


def test_a_zenoh_client_listens_nowhere_unless_asked(monkeypatch: pytest.MonkeyPatch):
    assert Settings(zenoh_mode="client", zenoh_connect="tcp/r:7447").zenoh_config().listen == ()
    assert Settings(zenoh_mode="peer").zenoh_config().listen == ("tcp/127.0.0.1:7447",)
    asked = Settings(zenoh_mode="client", zenoh_listen="tcp/127.0.0.1:7999").zenoh_config()
    assert asked.listen == ("tcp/127.0.0.1:7999",)
    monkeypatch.setenv("PHIM_ZENOH_MODE", "client")
    assert Settings().zenoh_listen == ()
    monkeypatch.setenv("PHIM_ZENOH_LISTEN", "tcp/127.0.0.1:7998")
    assert Settings().zenoh_listen == ("tcp/127.0.0.1:7998",)


def test_two_client_workers_on_one_host_join_one_router(tmp_path: Path):
    """docs/deployment.md's fleet command, twice on one host: both start and both are seen at the router."""
    router = free_endpoint()
    with (
        open(tmp_path / "fleet.log", "w") as log,
        spawned_router(router, log),
        contextlib.ExitStack() as workers,
        ThreadPoolExecutor(2) as pool,  # both start at once
    ):
        starting = [
            pool.submit(workers.enter_context, spawned_worker(w, router, log)) for w in ("w-a", "w-b")
        ]
        a, b = (f.result() for f in starting)
        watch = workers.enter_context(open_session(ZenohConfig(mode="client", listen=(), connect=(router,))))
        assert a.poll() is None and b.poll() is None
        keys = KeySpace()
        deadline = time.monotonic() + 30
        seen: set[str] = set()
        while seen != {"w-a", "w-b"} and time.monotonic() < deadline:
            replies = watch.liveliness().get(keys.worker("*", "*"), timeout=5)
            seen = {keys.worker_of(str(r.ok.key_expr))[0] for r in replies if r.ok is not None}
        assert seen == {"w-a", "w-b"}, (tmp_path / "fleet.log").read_text()[-3000:]


def spawned_worker(
    worker_id: str, router: str, log: IO[str]
) -> contextlib.AbstractContextManager[subprocess.Popen[bytes]]:
    port = free_port()
    env = {
        "PHIM_WORKER_ID": worker_id,
        "PHIM_PORT": str(port),
        "PHIM_THREADS": "1",
        "PHIM_WARMUP_SECTORS": "1",
        "PHIM_ZENOH_SHARED_KEYS": "0",
    }
    cmd = [*PHIM, "serve", "--zenoh-mode", "client", "--zenoh-connect", router]  # no --zenoh-listen
    return spawned(cmd, f"http://127.0.0.1:{port}/health/ready", env=env, log=log)


def test_a_router_beyond_loopback_needs_a_guard_or_insecure(tmp_path: Path):
    """`phim router` applies serve's rule: beyond loopback, a guarding config file or --insecure."""
    r = subprocess.run(
        [*PHIM, "router", "--listen", "tcp/0.0.0.0:7447"],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=REPO,
    )
    assert r.returncode == 2, r.stderr[-2000:]
    assert "tcp/0.0.0.0:7447: beyond loopback" in r.stderr and "--insecure" in r.stderr
    unguarded = tmp_path / "open.json5"
    unguarded.write_text("{}\n")
    r = subprocess.run(
        [*PHIM, "router", "--listen", "tcp/0.0.0.0:7447", "--config-file", str(unguarded)],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=REPO,
    )
    assert r.returncode == 2, r.stderr[-2000:]
    assert "no ACL" in r.stderr
