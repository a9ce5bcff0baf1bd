"""The Kubernetes zenoh router checks who joins. deploy/k8s/router-deployment.yaml's own container command
runs as a real `phim router` on loopback with the config the manifest mounts: the Secret phim-zenoh-router
made as the manifest's header says, from deploy/zenoh/ (router-usrpwd-acl.json5 and a copy of
router-users.txt). A worker joins as the StatefulSet runs one (its PHIM_* variables, the Secret phim-zenoh
from worker-usrpwd.json5) and serves; a vehicle with its user name and password gets its answers; no, wrong
or unknown credentials get no session; a vehicle reaches neither another vehicle's stream nor, posing as a
worker, anyone's sectors. With the samples' placeholder passwords the router refuses to start."""

from __future__ import annotations

import contextlib
import json
import os
import re
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
import zenoh
from server_helpers import START_TIMEOUT_S, default_detector, free_port, sector_msg

from clients.base import TransportError
from clients.zenoh_client import ZenohClient, ZenohClientConfig
from contract import DetectionsReply, KeySpace, Limits
from server.settings import Settings
from server.worker import Worker, WorkerConfig
from server.zenoh_transport import ZenohConfig, ZenohTransport, open_session

REPO = Path(__file__).resolve().parents[1]
K8S = REPO / "deploy" / "k8s"
SAMPLES = REPO / "deploy" / "zenoh"
ROUTER = K8S / "router-deployment.yaml"
WORKERS = K8S / "worker-statefulset.yaml"
KEYS = KeySpace()
POINTS = np.zeros((50, 4), np.float32)
WORKER_ID = "phim-worker-0"  # the StatefulSet's first pod name: its PHIM_WORKER_ID


def header_secret(manifest: Path, name: str) -> dict[str, str]:
    """The files of the Secret `name` as the manifest's header comment creates it: key -> file named by
    `kubectl create secret generic NAME --from-file=KEY=FILE ...` (the command may go on over `\\` lines)."""
    comment = " ".join(line.lstrip("# ").rstrip("\\ ") for line in manifest.read_text().splitlines()[:40])
    command = re.search(rf"create secret generic {name}((?: --from-file=\S+)+)", comment)
    assert command, (
        f"{manifest.name}: no `kubectl create secret generic {name} --from-file=...` in its header"
    )
    return dict(item.split("=", 1) for item in re.findall(r"--from-file=(\S+)", command[1]))


def secret_dir(manifest: Path, name: str, folder: Path) -> Path:
    """The Secret as its mounted directory: each file a repository path, else (an operator's copy, named
    after it) the deploy/zenoh/ sample it copies."""
    folder.mkdir(parents=True)
    for key, source in header_secret(manifest, name).items():
        path = REPO / source if (REPO / source).is_file() else SAMPLES / Path(source).name
        assert path.is_file(), f"{manifest.name}: secret {name}'s {key} comes from {source}, not in deploy/"
        (folder / key).write_text(path.read_text())
    return folder


def mounted_secret(pod: dict[str, Any], container: dict[str, Any], path: str) -> str:
    """The Secret whose mount holds `path` (a directory mount: an updated Secret reaches the file)."""
    (mount,) = [m for m in container["volumeMounts"] if Path(path).parent == Path(m["mountPath"])]
    assert mount.get("readOnly") is True and "subPath" not in mount, mount
    (volume,) = [v for v in pod["volumes"] if v["name"] == mount["name"]]
    assert "secret" in volume, volume
    return volume["secret"]["secretName"]


def option(args: list[str], name: str) -> str:
    assert args.count(name) == 1, (name, args)
    return args[args.index(name) + 1]


def replaced(args: list[str], name: str, value: str) -> list[str]:
    out = list(args)
    out[out.index(name) + 1] = value
    return out


@contextlib.contextmanager
def running(cmd: list[str], endpoint: str, log: Path) -> Iterator[subprocess.Popen[bytes]]:
    """The router process, once its endpoint accepts connections; killed at the end."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("PHIM_")}  # no PHIM_INSECURE
    with log.open("wb") as out:
        router = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, env=env, cwd=REPO)
    try:
        host, port = endpoint.removeprefix("tcp/").rsplit(":", 1)
        deadline = time.monotonic() + START_TIMEOUT_S
        while True:
            assert router.poll() is None, log.read_text()[-3000:]
            with contextlib.suppress(OSError), socket.create_connection((host, int(port)), timeout=1):
                break
            assert time.monotonic() < deadline, "the router did not start"
            time.sleep(0.1)
        yield router
    finally:
        router.kill()
        router.wait(30)


@pytest.fixture(scope="module")
def worker() -> Iterator[Worker]:
    worker = Worker(lambda: (default_detector(), "test"), WorkerConfig(worker_id=WORKER_ID, warmup_sectors=1))
    worker.start()
    assert worker.wait_ready(START_TIMEOUT_S), worker.status
    yield worker
    worker.close(10)


def worker_settings(endpoint: str, config_file: Path, tmp: Path, monkeypatch: pytest.MonkeyPatch) -> Settings:
    """`phim serve`'s settings from the StatefulSet's variables (the router's endpoint on loopback, the
    mounted files at `config_file` and an empty token file)."""
    (container,) = yaml.safe_load(WORKERS.read_text())["spec"]["template"]["spec"]["containers"]
    env = {e["name"]: e.get("value") for e in container["env"] if e["name"].startswith("PHIM_")}
    assert env["PHIM_ZENOH_CONNECT"] == "tcp/zenoh-router:7447" and "PHIM_INSECURE" not in env
    tokens = tmp / "tokens"
    tokens.write_text("")
    overrides = {
        "PHIM_WORKER_ID": WORKER_ID,
        "PHIM_ZENOH_CONNECT": endpoint,
        "PHIM_ZENOH_CONFIG_FILE": str(config_file),
        "PHIM_AUTH_TOKENS": str(tokens),
        "PHIM_DEVICE": "cpu",
    }
    for key in [k for k in os.environ if k.startswith("PHIM_")]:
        monkeypatch.delenv(key)
    for key, value in (env | overrides).items():
        monkeypatch.setenv(key, str(value))
    return Settings()


def credentials(tmp: Path, user: str | None, password: str = "") -> str:
    path = tmp / f"vehicle-{user}-{password}.json5"
    auth = f"auth: {{usrpwd: {json.dumps({'user': user, 'password': password})}}}" if user else ""
    path.write_text(f"{{transport: {{{auth}}}}}")
    return str(path)


@dataclass(frozen=True)
class K8sRouter:
    cmd: list[str]  # the container's command on a loopback endpoint, its mounted files under tmp
    endpoint: str
    users: Path  # the dictionary file: the sample's copy, placeholder passwords and all


def k8s_router(tmp: Path) -> K8sRouter:
    """The router's container from its manifest: `phim router` (not zenohd) with a config file from a
    mounted Secret whose dictionary file lies in the same mount, made as the manifest's header says."""
    pod = yaml.safe_load(ROUTER.read_text())["spec"]["template"]["spec"]
    (container,) = pod["containers"]
    args = container.get("command", []) + container.get("args", [])
    assert args[:2] == ["phim", "router"] and not container["image"].startswith("eclipse/zenoh"), args
    assert "PHIM_INSECURE" not in {e["name"] for e in container.get("env", [])}
    assert option(args, "--listen") == f"tcp/0.0.0.0:{container['ports'][0]['containerPort']}"
    config = option(args, "--config-file")
    secret = mounted_secret(pod, container, config)
    mount = str(Path(config).parent)
    files = secret_dir(ROUTER, secret, tmp / secret)
    router_json5 = files / Path(config).name
    dictionary = json.loads(
        zenoh.Config.from_file(str(router_json5)).get_json("transport/auth/usrpwd/dictionary_file")
    )
    assert dictionary and dictionary.startswith(f"{mount}/"), dictionary  # in the pod, beside its config
    router_json5.write_text(router_json5.read_text().replace(f"{mount}/", f"{files}/"))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    args = replaced(replaced(args, "--listen", endpoint), "--config-file", str(router_json5))
    return K8sRouter([sys.executable, "-m", *args], endpoint, files / Path(dictionary).name)


def test_the_k8s_router_refuses_the_samples_placeholder_passwords(tmp_path: Path) -> None:
    router = k8s_router(tmp_path)
    r = subprocess.run(router.cmd, capture_output=True, text=True, timeout=120, cwd=REPO)
    assert r.returncode == 2 and "placeholder password" in r.stderr, r.stderr[-2000:]
    assert "phim-worker" in r.stderr


def worker_config(tmp: Path, password_of: Callable[[str], str]) -> Path:
    """The Secret phim-zenoh's worker.json5 as the StatefulSet's header makes it, with the password the
    router's dictionary gives its user."""
    worker_json5 = secret_dir(WORKERS, "phim-zenoh", tmp / "phim-zenoh") / "worker.json5"
    user = json.loads(zenoh.Config.from_file(str(worker_json5)).get_json("transport/auth/usrpwd/user"))
    text = re.sub(r'password: "[^"]*"', f'password: "{password_of(user)}"', worker_json5.read_text())
    worker_json5.write_text(text)
    return worker_json5


def test_the_k8s_router_lets_in_only_who_logs_in(
    worker: Worker, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    router = k8s_router(tmp_path)
    endpoint = router.endpoint
    users = [line.split(":", 1)[0] for line in router.users.read_text().splitlines()]
    assert {"phim-worker", "car-1", "car-2"} <= set(users), users
    router.users.write_text("".join(f"{user}:{user}-secret\n" for user in users))  # the operator's copy
    settings = worker_settings(
        endpoint, worker_config(tmp_path, lambda u: f"{u}-secret"), tmp_path, monkeypatch
    )

    def car(identity: str | None, password: str = "") -> ZenohClient:
        config = credentials(tmp_path, identity, password)
        return ZenohClient(
            ZenohClientConfig(connect=(endpoint,), config_file=config, timeout_s=3.0, auto_workers=True)
        )

    with running(router.cmd, endpoint, tmp_path / "router.log"):
        for identity, password in ((None, ""), ("car-1", "car-2-secret"), ("car-3", "car-3-secret")):
            with pytest.raises(TransportError, match="cannot open"):
                car(identity, password)
        transport = ZenohTransport(worker.submit, settings.zenoh_config(), settings.worker_id, Limits())
        transport.start()
        try:
            with car("car-1", "car-1-secret") as car1, car("car-2", "car-2-secret") as car2:
                assert isinstance(car1.send(sector_msg("car-1", 0, POINTS)), DetectionsReply)
                assert car1.workers() == [WORKER_ID] == car2.workers()
                with pytest.raises(TransportError, match="no worker answered"):
                    car1.send(sector_msg("car-2", 0, POINTS))  # denied: the query never reaches the worker
            # car-1's credentials in a session of its own, posing as a worker: a queryable on every key and
            # a worker's token; the router's ACL lets neither through
            rogue_config = credentials(tmp_path, "car-1", "car-1-secret")
            rogue_cfg = ZenohConfig(mode="client", listen=(), connect=(endpoint,), config_file=rogue_config)
            with open_session(rogue_cfg) as rogue, car("car-2", "car-2-secret") as car2:
                asked: list[str] = []
                forged = rogue.declare_queryable(f"{KEYS.prefix}/**", lambda q: asked.append(str(q.key_expr)))
                token = rogue.liveliness().declare_token(KEYS.worker("phim-worker-9", str(rogue.zid())))
                time.sleep(0.5)
                for seq in range(3):  # car-2's own stream, answered by the worker alone
                    assert car2.send(sector_msg("car-2", seq, POINTS)).context_sectors == seq + 1
                assert not asked and car2.workers() == [WORKER_ID]
                forged.undeclare()
                token.undeclare()
        finally:
            transport.close(10)
