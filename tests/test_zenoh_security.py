"""zenoh locked down with the sample configs of deploy/zenoh/: mTLS (certificates from scripts/
make_test_certs.py) and an ACL per vehicle, on real sessions around a real worker. A vehicle's own stream
works; another's gets no answer; a vehicle cannot act as a worker (no queryable that would receive sectors
and forge boxes, no worker liveliness token); sessions without our CA's certificate are refused."""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import zenoh
from server_helpers import START_TIMEOUT_S, default_detector, free_port, sector_msg

from clients.base import TransportError
from clients.zenoh_client import ZenohClient, ZenohClientConfig
from contract import DetectionsReply, KeySpace, Limits, encode_reply
from server.worker import Worker, WorkerConfig
from server.zenoh_transport import MSGPACK_ENCODING, ZenohConfig, ZenohTransport, open_session

REPO = Path(__file__).resolve().parents[1]
SAMPLES = REPO / "deploy" / "zenoh"
KEYS = KeySpace()
POINTS = np.zeros((50, 4), np.float32)


def make_certs(folder: Path, clients: str) -> Path:
    script = REPO / "scripts" / "make_test_certs.py"
    subprocess.run([sys.executable, str(script), str(folder), "--clients", clients], check=True)
    return folder


def sample(name: str, certs: Path, out: Path, identity: str = "car-1", password: str = "change-me") -> str:
    """A sample config with its paths pointing at `certs` (and the vehicle's certificate or user name and
    password at `identity`)."""
    text = (SAMPLES / name).read_text().replace("/etc/phim/tls/", f"{certs}/")
    text = text.replace("/etc/phim/zenoh-users.txt", str(certs / "users.txt"))
    text = text.replace("car-1.pem", f"{identity}.pem").replace("car-1-key.pem", f"{identity}-key.pem")
    text = text.replace('user: "car-1"', f'user: "{identity}"').replace("change-me", password)
    path = out / f"{name}.{identity}.{password}.json5"
    path.write_text(text)
    return str(path)


@pytest.fixture(scope="module")
def worker() -> Iterator[Worker]:
    worker = Worker(lambda: (default_detector(), "test"), WorkerConfig(worker_id="w-tls", warmup_sectors=1))
    worker.start()
    assert worker.wait_ready(START_TIMEOUT_S), worker.status
    yield worker
    worker.close(10)


@contextlib.contextmanager
def listening(worker: Worker, endpoint: str, config_file: str | None = None) -> Iterator[None]:
    """The worker's zenoh transport, a peer listening on `endpoint` with the given config file."""
    cfg = ZenohConfig(mode="peer", listen=(endpoint,), config_file=config_file)
    transport = ZenohTransport(worker.submit, cfg, worker.worker_id, Limits())
    transport.start()
    try:
        yield
    finally:
        transport.close(10)


@pytest.fixture(scope="module")
def hub(worker: Worker, tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, Path, Path]]:
    """The worker behind worker-mtls-acl.json5 -> (its endpoint, our certs, a folder for configs)."""
    tmp = tmp_path_factory.mktemp("zenoh-tls")
    certs = make_certs(tmp / "certs", "car-1,car-2")
    endpoint = f"tls/localhost:{free_port()}"
    with listening(worker, endpoint, sample("worker-mtls-acl.json5", certs, tmp)):
        yield endpoint, certs, tmp


def vehicle(hub: tuple[str, Path, Path], identity: str, certs: Path | None = None) -> ZenohClient:
    endpoint, ours, tmp = hub
    config = sample("vehicle-mtls.json5", certs or ours, tmp, identity)
    return ZenohClient(ZenohClientConfig(connect=(endpoint,), config_file=config, timeout_s=3.0))


def test_each_vehicle_reaches_its_own_stream_only(hub):
    with vehicle(hub, "car-1") as car1, vehicle(hub, "car-2") as car2:
        assert isinstance(car1.send(sector_msg("car-1", 0, POINTS)), DetectionsReply)
        assert isinstance(car2.send(sector_msg("car-2", 0, POINTS)), DetectionsReply)
        with pytest.raises(TransportError, match="no worker answered"):
            car1.send(sector_msg("car-2", 1, POINTS))  # denied: the query never reaches the worker
        assert car2.send(sector_msg("car-2", 1, POINTS)).context_sectors == 2  # car-2's stream untouched
        assert car1.workers() == ["w-tls"] == car2.workers()


def test_a_vehicle_cannot_pose_as_a_worker(hub):
    with vehicle(hub, "car-1") as car1, vehicle(hub, "car-2") as car2:
        rogue = car1._session_or_fail()
        asked: list[str] = []

        def forge(q: zenoh.Query) -> None:  # a rogue worker: takes sectors, answers forged boxes
            asked.append(str(q.key_expr))
            q.reply(q.key_expr, b"forged boxes")

        forged = rogue.declare_queryable(KEYS.sector_queryable, forge)
        token = rogue.liveliness().declare_token(KEYS.worker("fake", str(rogue.zid())))
        time.sleep(0.5)
        for seq in range(3):  # only the real worker answers car-2 (a forged reply would not decode)
            assert car2.send(sector_msg("car-2", 10 + seq, POINTS)).stream_id == "car-2"
        assert not asked and car2.workers() == ["w-tls"]
        forged.undeclare()
        token.undeclare()


def test_behind_a_router_only_workers_serve(worker: Worker, tmp_path: Path):
    """router-mtls-acl.json5 on a router; the worker joins it with its own certificate (worker-1), the
    vehicles with theirs. Each vehicle reaches its own stream only, and a vehicle that declares the sector
    queryable and a worker token reaches nobody: the router's ACL lets only workers serve."""
    certs = make_certs(tmp_path / "certs", "car-1,car-2,worker-1")
    endpoint = f"tls/localhost:{free_port()}"
    router = ZenohConfig(
        mode="router", listen=(endpoint,), config_file=sample("router-mtls-acl.json5", certs, tmp_path)
    )
    joined = ZenohConfig(
        mode="client",
        listen=(),
        connect=(endpoint,),
        config_file=sample("vehicle-mtls.json5", certs, tmp_path, "worker-1"),
    )
    with open_session(router):
        transport = ZenohTransport(worker.submit, joined, worker.worker_id, Limits())
        transport.start()
        hub = (endpoint, certs, tmp_path)
        try:
            with vehicle(hub, "car-1") as car1, vehicle(hub, "car-2") as car2:
                assert car1.send(sector_msg("car-1", 2000, POINTS)).seq == 2000
                with pytest.raises(TransportError, match="no worker answered"):
                    car1.send(sector_msg("car-2", 2000, POINTS))
                rogue = car1._session_or_fail()
                asked: list[str] = []
                forged = rogue.declare_queryable(
                    KEYS.sector_queryable, lambda q: asked.append(str(q.key_expr))
                )
                token = rogue.liveliness().declare_token(KEYS.worker("fake", str(rogue.zid())))
                time.sleep(0.5)
                assert car2.send(sector_msg("car-2", 2000, POINTS)).seq == 2000
                assert not asked and car2.workers() == ["w-tls"]
                forged.undeclare()
                token.undeclare()
        finally:
            transport.close(10)


def test_user_and_password_with_the_acl(worker: Worker, tmp_path: Path):
    """worker-usrpwd-acl.json5: TLS with the worker's certificate only, a user name and password per vehicle
    (the dictionary file), the ACL by user name. The right password reaches its own stream only; a wrong
    password, no credentials, or another CA's worker certificate: no session."""
    certs = make_certs(tmp_path / "certs", "car-1")
    (certs / "users.txt").write_text("car-1:secret-1\ncar-2:secret-2\n")
    endpoint = f"tls/localhost:{free_port()}"

    def car(identity: str, password: str, ca: Path = certs) -> ZenohClient:
        config = sample("vehicle-usrpwd.json5", ca, tmp_path, identity, password)
        return ZenohClient(ZenohClientConfig(connect=(endpoint,), config_file=config, timeout_s=3.0))

    with listening(worker, endpoint, sample("worker-usrpwd-acl.json5", certs, tmp_path)):
        with car("car-1", "secret-1") as car1, car("car-2", "secret-2") as car2:
            assert isinstance(car1.send(sector_msg("car-1", 9000, POINTS)), DetectionsReply)
            with pytest.raises(TransportError, match="no worker answered"):
                car1.send(sector_msg("car-2", 9000, POINTS))
            assert car2.send(sector_msg("car-2", 9000, POINTS)).seq == 9000  # not taken by car-1's
        for identity, password in (("car-1", "secret-2"), ("car-3", "secret-1")):
            with pytest.raises(TransportError, match="cannot open"):
                car(identity, password)
        no_credentials = tmp_path / "no-credentials.json5"
        ca = f'root_ca_certificate: "{certs}/ca.pem"'
        no_credentials.write_text(f"{{transport: {{link: {{tls: {{{ca}}}}}}}}}")
        with pytest.raises(TransportError, match="cannot open"):
            ZenohClient(ZenohClientConfig(connect=(endpoint,), config_file=str(no_credentials), timeout_s=3))
        strangers = make_certs(tmp_path / "other-ca", "car-1")
        with pytest.raises(TransportError, match="cannot open"):
            car("car-1", "secret-1", ca=strangers)  # a worker our CA did not sign: not ours


def test_sessions_without_our_certificate_are_refused(hub, tmp_path: Path):
    endpoint = hub[0]
    strangers = make_certs(tmp_path / "other-ca", "car-1")  # the right name, another CA
    with pytest.raises(TransportError, match="cannot open"):
        vehicle(hub, "car-1", certs=strangers)
    plain = ZenohClientConfig(connect=(endpoint.replace("tls/", "tcp/"),), timeout_s=3.0)
    with pytest.raises(TransportError, match="cannot open"):
        ZenohClient(plain)


@pytest.mark.parametrize("rogue_first", [True, False])
def test_the_client_takes_answers_from_workers_only(worker: Worker, rogue_first: bool):
    """No ACL here, so a rogue session can declare the sector queryable and answer with a well-formed forged
    reply, before the worker or after it (zenoh's default consolidation would have kept the later one). The
    client takes the worker's answer (sync and async), since only the worker's session holds a worker
    token; pinned to another worker ID, it takes no answer at all."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with open_session(ZenohConfig(mode="router", listen=(endpoint,))):
        joined = ZenohConfig(mode="client", listen=(), connect=(endpoint,))

        def slow_submit(msg):  # the rogue surely answers first
            time.sleep(0.2 if rogue_first else 0.0)
            return worker.submit(msg)

        transport = ZenohTransport(slow_submit, joined, worker.worker_id, Limits())
        transport.start()
        try:
            with ZenohClient(connect=(endpoint,), timeout_s=5.0) as car, open_session(joined) as rogue:
                real = car.send(sector_msg(f"car-9-{rogue_first}", 0, POINTS))
                forged = dataclasses.replace(real, seq=999, context_sectors=999)
                asked: list[str] = []

                def forge(q: zenoh.Query) -> None:
                    asked.append(str(q.key_expr))
                    time.sleep(0.0 if rogue_first else 0.4)
                    q.reply(q.key_expr, encode_reply(forged), encoding=MSGPACK_ENCODING)

                queryable = rogue.declare_queryable(KEYS.sector_queryable, forge)
                time.sleep(0.5)
                got = [car.send(sector_msg(f"car-9-{rogue_first}", 1, POINTS))]
                got.append(asyncio.run(car.send_async(sector_msg(f"car-9-{rogue_first}", 2, POINTS))))
                assert len(asked) == 2 and car.workers() == ["w-tls"]
                assert [(r.seq, r.context_sectors) for r in got] == [(1, 2), (2, 3)]  # not the forged ones
                queryable.undeclare()
            with ZenohClient(connect=(endpoint,), timeout_s=2.0, worker="w-other") as pinned:
                with pytest.raises(TransportError, match="no worker answered"):
                    pinned.send(sector_msg(f"car-10-{rogue_first}", 0, POINTS))
                assert pinned.ignored_replies == 1  # w-tls's answer: not the pinned worker's
        finally:
            transport.close(10)
