"""HTTPS: `phim serve --tls-cert --tls-key` with certificates from scripts/make_test_certs.py; clients check
the server against a given CA (`--ca-cert`) and refuse it without; the image's health check speaks HTTPS."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import httpx
import numpy as np
import pytest
from pydantic import ValidationError
from server_helpers import default_detector, sector_msg, serve

from clients.base import TransportError
from clients.connect import ConnectConfig, make_client
from server.healthcheck import check
from server.settings import Settings

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def certs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("certs")
    subprocess.run([sys.executable, str(REPO / "scripts" / "make_test_certs.py"), str(folder)], check=True)
    return folder


def test_https_with_a_ca_and_refused_without(certs: Path):
    points = np.zeros((50, 4), np.float32)
    with serve(default_detector(), tls_cert=certs / "server.pem", tls_key=certs / "server-key.pem") as s:
        assert s.url.startswith("https://")
        with make_client(ConnectConfig(url=s.url, ca_cert=str(certs / "ca.pem"))) as client:
            assert client.send(sector_msg("car", 0, points)).context_sectors == 1
            assert client.model_info()["config"] == "tiny"
        with (
            make_client(ConnectConfig(url=s.url)) as client,
            pytest.raises(TransportError, match="CERTIFICATE"),
        ):
            client.model_info()  # the system's CAs do not know the test CA
        with pytest.raises(httpx.HTTPError):
            httpx.get(s.url.replace("https://", "http://") + "/health/live", timeout=5)  # no plain HTTP
        port = int(s.url.rsplit(":", 1)[1])
        assert check(port, tls=True)[0] and not check(port, tls=False)[0]


def test_a_certificate_needs_its_key(certs: Path, tmp_path: Path):
    with pytest.raises(ValidationError, match="give both"):
        Settings(tls_cert=certs / "server.pem")
    with pytest.raises(ValidationError, match="no such file"):
        Settings(tls_cert=tmp_path / "missing.pem", tls_key=certs / "server-key.pem")
