"""zenoh locked down with the sample configs of deploy/zenoh/: mTLS (certificates from scripts/
make_test_certs.py) and an ACL per vehicle, on real sessions around a real worker. A vehicle's own stream
works; another's gets no answer; a vehicle cannot act as a worker (no queryable that would receive sectors
and forge boxes, no worker liveliness token); sessions without our CA's certificate are refused."""

from __future__ import annotations

import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import zenoh
from server_helpers import default_detector, free_port, sector_msg

from clients.base import TransportError
from clients.zenoh_client import ZenohClient, ZenohClientConfig
from contract import DetectionsReply, KeySpace, Limits
from server.worker import Worker, WorkerConfig
from server.zenoh_transport import ZenohConfig, ZenohTransport

REPO = Path(__file__).resolve().parents[1]
SAMPLES = REPO / "deploy" / "zenoh"
KEYS = KeySpace()
POINTS = np.zeros((50, 4), np.float32)


def make_certs(folder: Path, clients: str) -> Path:
    script = REPO / "scripts" / "make_test_certs.py"
    subprocess.run([sys.executable, str(script), str(folder), "--clients", clients], check=True)
    return folder


def sample(name: str, certs: Path, out: Path, identity: str = "car-1") -> str:
    """A sample config with its certificate paths pointing at `certs` (and the vehicle's at `identity`)."""
    text = (SAMPLES / name).read_text().replace("/etc/phim/tls/", f"{certs}/")
    path = out / f"{name}.{identity}.json5"
    path.write_text(
        text.replace("car-1.pem", f"{identity}.pem").replace("car-1-key.pem", f"{identity}-key.pem")
    )
    return str(path)


@pytest.fixture(scope="module")
def hub(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, Path, Path]]:
    """A worker behind worker-mtls-acl.json5 -> (its endpoint, our certs, a folder for configs)."""
    tmp = tmp_path_factory.mktemp("zenoh-tls")
    certs = make_certs(tmp / "certs", "car-1,car-2")
    worker = Worker(lambda: (default_detector(), "test"), WorkerConfig(worker_id="w-tls", warmup_sectors=1))
    worker.start()
    assert worker.wait_ready(120), worker.status
    endpoint = f"tls/localhost:{free_port()}"
    cfg = ZenohConfig(
        mode="peer", listen=(endpoint,), config_file=sample("worker-mtls-acl.json5", certs, tmp)
    )
    transport = ZenohTransport(worker.submit, cfg, worker.worker_id, Limits())
    transport.start()
    try:
        yield endpoint, certs, tmp
    finally:
        transport.close(10)
        worker.close(10)


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
        token = rogue.liveliness().declare_token(KEYS.worker("fake"))
        time.sleep(0.5)
        for seq in range(3):  # only the real worker answers car-2 (a forged reply would not decode)
            assert car2.send(sector_msg("car-2", 10 + seq, POINTS)).stream_id == "car-2"
        assert not asked and car2.workers() == ["w-tls"]
        forged.undeclare()
        token.undeclare()


def test_sessions_without_our_certificate_are_refused(hub, tmp_path: Path):
    endpoint = hub[0]
    strangers = make_certs(tmp_path / "other-ca", "car-1")  # the right name, another CA
    with pytest.raises(TransportError, match="cannot open"):
        vehicle(hub, "car-1", certs=strangers)
    plain = ZenohClientConfig(connect=(endpoint.replace("tls/", "tcp/"),), timeout_s=3.0)
    with pytest.raises(TransportError, match="cannot open"):
        ZenohClient(plain)
