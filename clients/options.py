"""The options of the client commands (loadtest, replay, bench server), each defined once with its PHIM_
environment variable, and the connection they describe."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import click

from clients.connect import ConnectConfig, Transport
from contract import DEFAULT_URL, DEFAULT_ZENOH_ENDPOINT
from phim.options import EnumValue

Decorator = Callable[[Callable[..., Any]], Callable[..., Any]]

zenoh_connect_option = click.option(
    "--zenoh-connect",
    envvar="PHIM_ZENOH_CONNECT",
    default=DEFAULT_ZENOH_ENDPOINT,
    show_default=True,
    show_envvar=True,
    help="Zenoh endpoints to connect to, comma-separated.",
)
every_option = click.option(
    "--every", type=click.IntRange(1), default=1, show_default=True, help="Keep every n-th point of a scan."
)
CONNECTION: list[Decorator] = [
    click.option(
        "--transport",
        envvar="PHIM_TRANSPORT",
        type=EnumValue(Transport),
        default=Transport.HTTP.value,
        show_default=True,
        show_envvar=True,
        help="How sectors travel.",
    ),
    click.option(
        "--url",
        envvar="PHIM_URL",
        default=DEFAULT_URL,
        show_default=True,
        show_envvar=True,
        help="The server's HTTP address (over zenoh too: model info, ending streams).",
    ),
    zenoh_connect_option,
    click.option(
        "--zenoh-mode",
        envvar="PHIM_ZENOH_MODE",
        type=click.Choice(["client", "peer"]),
        default="client",
        show_default=True,
        show_envvar=True,
        help="Zenoh session mode.",
    ),
    click.option(
        "--zenoh-config",
        envvar="PHIM_ZENOH_CONFIG_FILE",
        type=click.Path(exists=True, dir_okay=False, path_type=Path),
        show_envvar=True,
        help="A zenoh JSON5 config file (TLS, ...).",
    ),
    click.option(
        "--workers",
        envvar="PHIM_WORKERS",
        type=click.Choice(["shared", "auto"]),
        default="shared",
        show_default=True,
        show_envvar=True,
        help="zenoh: 'shared' sends to the shared keys (one worker); 'auto' sends each stream to its owner "
        "among the live workers (a fleet; a sector whose worker died is sent once more to the new owner).",
    ),
    click.option(
        "--token",
        envvar="PHIM_TOKEN",
        show_envvar=True,
        help="A bearer token for a server run with --auth-tokens (phim auth add-token).",
    ),
    click.option(
        "--ca-cert",
        envvar="PHIM_CA_CERT",
        type=click.Path(exists=True, dir_okay=False, path_type=Path),
        show_envvar=True,
        help="An https --url: check the server's certificate against this CA (PEM) instead of the system's.",
    ),
    click.option(
        "--timeout",
        envvar="PHIM_TIMEOUT_S",
        type=click.FloatRange(0.001),
        default=10.0,
        show_default=True,
        show_envvar=True,
        help="Per-request timeout (s).",
    ),
]


def connection_options(command: Callable[..., Any]) -> Callable[..., Any]:
    """--transport, --url, --zenoh-connect, --zenoh-mode, --zenoh-config, --workers, --token, --ca-cert,
    --timeout: see `connect_config`."""
    for option in reversed(CONNECTION):
        command = option(command)
    return command


def connect_config(
    transport: Transport,
    url: str,
    zenoh_connect: str,
    zenoh_mode: str,
    zenoh_config: Path | None,
    workers: str,
    token: str | None,
    ca_cert: Path | None,
    timeout: float,
) -> ConnectConfig:
    """The connection options -> a ConnectConfig."""
    return ConnectConfig(
        transport=transport,
        url=url,
        zenoh_connect=tuple(e.strip() for e in zenoh_connect.split(",") if e.strip()),
        zenoh_mode=zenoh_mode,
        zenoh_config_file=None if zenoh_config is None else str(zenoh_config),
        auto_workers=workers == "auto",
        timeout_s=timeout,
        token=token or None,
        ca_cert=None if ca_cert is None else str(ca_cert),
    )
