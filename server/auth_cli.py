"""`phim auth add-token`: a new bearer token for a stream-ID prefix; only its hash goes to the token file."""

from __future__ import annotations

from pathlib import Path

import click

from server.auth import add_token


@click.command("add-token")
@click.option(
    "--file",
    "path",
    required=True,
    type=click.Path(dir_okay=False, path_type=Path),
    help="The token file (created owner-only if missing); `phim serve --auth-tokens` reads it.",
)
@click.option(
    "--prefix",
    default="",
    help="The token may use the streams whose ID starts with this; they are one tenant (shares: phim serve "
    "--tenant-max-streams, --tenant-queue-size).",
)
@click.option("--admin", is_flag=True, help="Every stream, and the list of all streams.")
@click.option("--note", default="", help="Who or what the token is for (kept beside the hash).")
def add_token_cmd(path: Path, prefix: str, admin: bool, note: str) -> None:
    """Print a new token (shown once: store it where the client reads it, e.g. PHIM_TOKEN) and append its
    SHA-256 with its prefix to FILE. A running server picks it up at its next request."""
    if not (prefix or admin):
        raise click.UsageError("give --prefix P (the stream IDs it may use start with P) or --admin")
    click.echo(add_token(path, prefix, admin, note))
