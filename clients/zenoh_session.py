"""The clients' zenoh sessions (the server opens its own, server/zenoh_transport.py): a config file if given,
then the mode and endpoints; multicast scouting off, so a session goes only where it is told."""

from __future__ import annotations

import json
from collections.abc import Sequence

import zenoh

from contract import MSGPACK

MSGPACK_ENCODING = zenoh.Encoding(MSGPACK)


def open_session(
    connect: Sequence[str], mode: str = "client", listen: Sequence[str] = (), config_file: str | None = None
) -> zenoh.Session:
    """A zenoh session in `mode` ("client": through the endpoints in `connect`; "peer": may also `listen`)."""
    if mode not in ("client", "peer"):
        raise ValueError(f"zenoh mode: {mode!r}; expected 'client' or 'peer'")
    conf = zenoh.Config.from_file(config_file) if config_file else zenoh.Config()
    settings = {
        "mode": mode,
        "connect/endpoints": list(connect),
        "listen/endpoints": list(listen),
        "scouting/multicast/enabled": False,
    }
    for key, value in settings.items():
        conf.insert_json5(key, json.dumps(value))
    return zenoh.open(conf)
