"""Build a client for a transport from plain options (the CLI commands share this)."""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import TYPE_CHECKING

from contract import DEFAULT_KEY_PREFIX, DEFAULT_URL, DEFAULT_ZENOH_ENDPOINT

if TYPE_CHECKING:
    from clients.base import DetectorClient


class Transport(enum.StrEnum):
    HTTP = "http"
    ZENOH = "zenoh"


@dataclass(frozen=True)
class ConnectConfig:
    transport: Transport = Transport.HTTP
    url: str = DEFAULT_URL  # HTTP address; over zenoh used for model info and ending streams
    zenoh_connect: tuple[str, ...] = (DEFAULT_ZENOH_ENDPOINT,)
    zenoh_mode: str = "client"
    zenoh_config_file: str | None = None
    key_prefix: str = DEFAULT_KEY_PREFIX
    auto_workers: bool = False  # zenoh: each stream to its owner among the live workers (--workers auto)
    timeout_s: float = 10.0
    use_http_control: bool = True  # over zenoh, reach model info / end stream at `url`
    token: str | None = None  # bearer token for HTTP (`phim serve --auth-tokens`)
    ca_cert: str | None = None  # https: the CA (PEM) the server's certificate is checked against


def make_client(cfg: ConnectConfig, max_connections: int | None = 256) -> DetectorClient:
    """The transport's client (imported here: `phim serve` needs neither httpx nor the client code)."""
    from clients.http_client import HttpClient, HttpConfig
    from clients.zenoh_client import ZenohClient, ZenohClientConfig

    if cfg.transport is Transport.HTTP:
        return HttpClient(
            config=HttpConfig(
                url=cfg.url,
                timeout_s=cfg.timeout_s,
                max_connections=max_connections,
                token=cfg.token,
                ca_cert=cfg.ca_cert,
            )
        )
    return ZenohClient(
        ZenohClientConfig(
            connect=cfg.zenoh_connect,
            mode=cfg.zenoh_mode,
            key_prefix=cfg.key_prefix,
            auto_workers=cfg.auto_workers,
            timeout_s=cfg.timeout_s,
            config_file=cfg.zenoh_config_file,
            http_url=cfg.url if cfg.use_http_control else None,
            token=cfg.token,
            ca_cert=cfg.ca_cert,
        )
    )
