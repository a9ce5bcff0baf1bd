"""deploy/nginx/phim.conf with Debian's real nginx on loopback, in front of 3 real workers: a stream's sectors
all reach one worker, removing a worker moves only its own streams, and the workers' error replies pass
through. The config under test is the shipped one with only its server lines, listen port and file paths
replaced (render_conf)."""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import time
from collections.abc import Iterator
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path

import httpx
import msgpack
import numpy as np
import pytest
from conftest import REPO
from server_helpers import RunningServer, default_detector, sector_msg, serve

from clients.bench.server import free_port
from clients.http_client import HttpClient
from contract import MSGPACK, DetectionsReply, ErrorReply, decode_response

SHIPPED = REPO / "deploy" / "nginx" / "phim.conf"
SHIPPED_SERVERS = [f"server phim-worker-{i}:8080;" for i in range(3)]
SHIPPED_LISTEN = "listen 8080;"
# CI sets this (.ci/run): without nginx these tests fail instead of skipping (scripts/test_services.sh
# installs it)
REQUIRE_NGINX = os.environ.get("PHIM_REQUIRE_NGINX") == "1"
WORKERS = ("w0", "w1", "w2")
POINTS = np.random.default_rng(0).uniform(-20, 20, (300, 4)).astype(np.float32)  # a small valid sector


# Debian's nginx is in /usr/sbin, which a normal user's PATH lacks
NGINX = shutil.which("nginx") or shutil.which("nginx", path="/usr/sbin:/sbin")
NO_NGINX = "needs nginx (not on PATH nor in /usr/sbin): scripts/test_services.sh installs Debian's"
if NGINX is None and not REQUIRE_NGINX:
    pytest.skip(NO_NGINX, allow_module_level=True)


def replace_line(lines: list[str], old: str, new: list[str]) -> list[str]:
    """`lines` with the one line whose text is `old` replaced by `new` (kept at its indentation)."""
    at = [i for i, line in enumerate(lines) if line.strip() == old]
    assert len(at) == 1, f"{SHIPPED}: expected one line {old!r}, found {len(at)}"
    indent = lines[at[0]][: len(lines[at[0]]) - len(lines[at[0]].lstrip())]
    return lines[: at[0]] + [indent + n for n in new] + lines[at[0] + 1 :]


def render_conf(shipped: str, servers: list[str], port: int, prefix: Path) -> str:
    """The shipped config with its upstream servers, listen port and files (pid, temp folders) replaced, and
    nothing else: the map and the hash directives are the ones shipped."""
    lines = shipped.splitlines()
    lines = replace_line(lines, SHIPPED_SERVERS[0], [f"server {s};" for s in servers])
    for old in SHIPPED_SERVERS[1:]:
        lines = replace_line(lines, old, [])
    lines = replace_line(lines, SHIPPED_LISTEN, [f"listen 127.0.0.1:{port};"])
    temps = ("client_body", "proxy", "fastcgi", "uwsgi", "scgi")  # Debian's defaults are in /var/lib/nginx
    lines = replace_line(lines, "http {", ["http {", *(f"    {t}_temp_path {prefix}/{t};" for t in temps)])
    # as root the nginx workers would run as nobody, who cannot enter pytest's private tmp folders
    head = [f"pid {prefix}/nginx.pid;"] + (["user root;"] if os.geteuid() == 0 else [])
    return "\n".join(head + lines) + "\n"


def nginx_args(binary: str, prefix: Path, *extra: str) -> list[str]:
    return [binary, "-p", str(prefix), "-c", str(prefix / "phim.conf"), "-e", "stderr", *extra]


@dataclass
class Nginx:
    binary: str
    prefix: Path
    port: int
    proc: subprocess.Popen[bytes]

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    @property
    def conf(self) -> Path:
        return self.prefix / "phim.conf"

    def args(self, *extra: str) -> list[str]:
        return nginx_args(self.binary, self.prefix, *extra)

    def workers(self) -> set[int]:
        """The pids of the master's worker processes (Linux: /proc/PID/task/PID/children)."""
        children = Path(f"/proc/{self.proc.pid}/task/{self.proc.pid}/children").read_text()
        return {int(p) for p in children.split()}

    def reload(self, servers: list[str]) -> None:
        """Rewrite the upstream and reload; return once the old worker processes (old config) have exited,
        so that every new connection meets the new config."""
        old = self.workers()
        self.conf.write_text(render_conf(SHIPPED.read_text(), servers, self.port, self.prefix))
        subprocess.run(self.args("-t", "-q"), check=True, timeout=30)
        subprocess.run(self.args("-s", "reload"), check=True, timeout=30)
        deadline = time.monotonic() + 30
        while old & self.workers():
            assert time.monotonic() < deadline, f"nginx's old workers {old & self.workers()} did not exit"
            time.sleep(0.05)

    def stop(self) -> None:
        """A graceful quit (`nginx -s quit`), then a fast one (SIGTERM: the master stops its workers too)."""
        self.proc.send_signal(signal.SIGQUIT)
        try:
            self.proc.wait(20)
        except subprocess.TimeoutExpired:
            self.proc.terminate()
            self.proc.wait(20)


def wait_listening(n: Nginx, log: Path) -> None:
    deadline = time.monotonic() + 30
    while True:
        assert n.proc.poll() is None, f"nginx exited {n.proc.returncode}: {log.read_text()}"
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", n.port)) == 0:
                return
        assert time.monotonic() < deadline, f"nginx did not listen: {log.read_text()}"
        time.sleep(0.05)


@pytest.fixture(scope="module")
def workers() -> Iterator[dict[str, RunningServer]]:
    """Three real workers (the default model, zenoh off), each on its own free port."""
    with ExitStack() as stack:
        # idle streams stay 300 s: a slow run must not evict one between two sectors of a test
        yield {
            w: stack.enter_context(serve(default_detector(), worker_id=w, idle_timeout_s=300))
            for w in WORKERS
        }


def address(server: RunningServer) -> str:
    return server.url.removeprefix("http://")


def start_nginx(binary: str, prefix: Path, port: int) -> Nginx:
    """nginx in the foreground (daemon off: the Popen is the master), its stderr in prefix/nginx.stderr."""
    log = prefix / "nginx.stderr"
    with log.open("wb") as err:
        cmd = nginx_args(binary, prefix, "-g", "daemon off;")
        n = Nginx(binary, prefix, port, subprocess.Popen(cmd, stderr=err, stdin=subprocess.DEVNULL))
    try:
        wait_listening(n, log)
    except BaseException:
        n.stop()
        raise
    return n


@pytest.fixture
def nginx(workers: dict[str, RunningServer], tmp_path: Path) -> Iterator[Nginx]:
    """nginx with the rendered config, proxying to the 3 workers; stopped (and waited for) after the test."""
    if NGINX is None:
        pytest.fail(NO_NGINX)
    port = free_port()
    conf = render_conf(SHIPPED.read_text(), [address(s) for s in workers.values()], port, tmp_path)
    (tmp_path / "phim.conf").write_text(conf)
    n = start_nginx(NGINX, tmp_path, port)
    try:
        yield n
    finally:
        n.stop()


def send_round(url: str, streams: list[str], seq: int) -> dict[str, DetectionsReply]:
    """Sector `seq` of every stream, through a fresh client (new connections: any nginx worker process)."""
    with HttpClient(url) as client:
        return {s: client.send(sector_msg(s, seq, POINTS)) for s in streams}


def test_each_stream_stays_on_one_worker(nginx: Nginx) -> None:
    streams = [f"sticky-{i}" for i in range(24)]
    rounds = [send_round(nginx.url, streams, seq) for seq in range(3)]
    owner = {s: rounds[0][s].worker_id for s in streams}
    for seq, replies in enumerate(rounds):
        for s, r in replies.items():
            assert (r.stream_id, r.seq, r.worker_id) == (s, seq, owner[s])
            assert r.cold_start == (seq == 0), (s, seq)  # the same state all along: only the first is cold
    assert set(owner.values()) == set(WORKERS), owner


def test_removing_a_worker_moves_only_its_streams(nginx: Nginx, workers: dict[str, RunningServer]) -> None:
    streams = [f"ring-{i}" for i in range(24)]
    before = {s: r.worker_id for s, r in send_round(nginx.url, streams, 0).items()}
    assert set(before.values()) == set(WORKERS), before
    nginx.reload([address(workers[w]) for w in ("w0", "w1")])
    after = send_round(nginx.url, streams, 1)
    for s, r in after.items():
        if before[s] == "w2":  # moved: a fresh stream on one of the others
            assert r.worker_id in ("w0", "w1") and r.cold_start, (s, r.worker_id)
        else:  # stayed, with its state
            assert r.worker_id == before[s] and not r.cold_start, (s, before[s], r.worker_id)


def test_end_stream_and_model_reach_the_workers(nginx: Nginx) -> None:
    """DELETE hashes like the sectors (it ends the stream where it lives); /v1/model answers from any."""
    first = send_round(nginx.url, ["ended"], 0)["ended"]
    with HttpClient(nginx.url) as client:
        client.end_stream("ended")
        again = client.send(sector_msg("ended", 1, POINTS))
        assert client.model_info()["config"]
    assert again.worker_id == first.worker_id and again.cold_start


def test_worker_errors_pass_through(nginx: Nginx) -> None:
    """The worker's own 4xx replies come back through nginx, body and type unchanged."""
    url = f"{nginx.url}/v1/streams/bad-1/sectors"
    r = httpx.post(url, content=b"x", headers={"Content-Type": "text/plain", "Accept": "application/json"})
    assert (r.status_code, r.headers["content-type"]) == (400, "application/json"), r.text
    body = r.json()
    assert (body["kind"], body["code"], body["field"]) == ("error", "bad_request", "Content-Type"), body
    r = httpx.post(url, content=msgpack.packb({"stream_id": 7}), headers={"Content-Type": MSGPACK})
    assert 400 <= r.status_code < 500 and r.headers["content-type"] == MSGPACK, (r.status_code, r.content)
    out = decode_response(r.content)
    assert isinstance(out, ErrorReply) and out.stream_id == "bad-1", out
