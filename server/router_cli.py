"""`phim router`: a zenoh router (eclipse-zenoh in router mode, what zenohd runs without its plugins) where
workers (`phim serve --zenoh-mode client --zenoh-connect EP`) and vehicles meet. No REST plugin, no
storage: it only routes. Runs until SIGTERM or SIGINT."""

from __future__ import annotations

import json
import logging
import signal
import threading
from pathlib import Path

import click
import zenoh

from contract import DEFAULT_ZENOH_ENDPOINT
from server.settings import endpoint_is_loopback
from server.zenoh_transport import ZenohConfig, open_session

log = logging.getLogger("phim.router")
DICTIONARY_KEY = "transport/auth/usrpwd/dictionary_file"
PLACEHOLDER_PASSWORD = "change-me"  # the samples' passwords (deploy/zenoh/), never a real one


@click.command("router")
@click.option(
    "--listen",
    default=DEFAULT_ZENOH_ENDPOINT,
    show_default=True,
    help="Comma-separated endpoints to listen on (tcp/HOST:PORT, tls/HOST:PORT).",
)
@click.option(
    "--config-file",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    help="A zenoh JSON5 file (TLS, user/password, ACL: deploy/zenoh/); --listen overrides its endpoints.",
)
@click.option(
    "--insecure",
    is_flag=True,
    envvar="PHIM_INSECURE",
    help="Listen beyond loopback without a guarding --config-file (anyone who reaches it may route).",
)
def router_cmd(listen: str, config_file: Path | None, insecure: bool) -> None:
    """Route zenoh between workers and vehicles until SIGTERM/SIGINT. Like `phim serve`, a listener beyond
    loopback needs a --config-file with an ACL, mTLS or user/password (deploy/zenoh/), or --insecure; a
    user/password dictionary still holding a sample's placeholder password (change-me...) is refused."""
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    endpoints = tuple(e.strip() for e in listen.split(",") if e.strip())
    wide = [e for e in endpoints if not endpoint_is_loopback(e)]
    if wide and not insecure and config_file is None:
        raise click.UsageError(
            f"--listen {','.join(wide)}: beyond loopback, and a router without an ACL routes anyone's sectors"
            " into every stream; give --config-file FILE with an ACL, mTLS or user/password (deploy/zenoh/), "
            "or --insecure (PHIM_INSECURE=1) to accept that"
        )
    cfg = ZenohConfig(
        mode="router",
        listen=endpoints,
        config_file=None if config_file is None else str(config_file),
        guard_required=bool(wide) and not insecure,
    )
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    if config_file is not None and (placeholders := placeholder_users(config_file)):
        raise click.UsageError(
            f"--config-file {config_file}: the users {', '.join(placeholders)} still have the sample's "
            "placeholder password (change-me...) in its dictionary file: give each a secret of its own"
        )
    try:
        session = open_session(cfg)
    except ValueError as e:  # the config file guards nothing
        raise click.UsageError(str(e)) from e
    except zenoh.ZError as e:
        raise click.ClickException(f"zenoh router on {','.join(endpoints)}: {e}") from e
    log.info("zenoh router %s listening on %s", session.zid(), ",".join(endpoints))
    stop.wait()
    session.close()
    log.info("zenoh router stopped")


def placeholder_users(config_file: Path) -> list[str]:
    """The users of the config's user/password dictionary file (`user:password` lines) whose password is
    still a sample's placeholder (deploy/zenoh/router-users.txt: `change-me...`); [] without a dictionary.
    A dictionary zenoh cannot read fails where zenoh reads it, at the session's start."""
    try:
        dictionary = json.loads(zenoh.Config.from_file(str(config_file)).get_json(DICTIONARY_KEY))
    except zenoh.ZError:
        return []  # a config zenoh cannot read: its error comes with the session's start
    if not dictionary:
        return []
    try:
        lines = Path(dictionary).read_text().splitlines()
    except (OSError, UnicodeDecodeError):
        return []
    users = [line.partition(":") for line in lines]
    return [user for user, _, password in users if password.startswith(PLACEHOLDER_PASSWORD)]
