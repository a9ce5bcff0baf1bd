"""Bearer tokens bound to stream-ID prefixes, kept as hashes in a token file the server re-reads on change.

The file (`phim serve --auth-tokens F`, PHIM_AUTH_TOKENS) holds one JSON object per line:

    {"sha256": "<hex digest of the token>", "prefix": "fleet-a.", "admin": false, "note": "..."}

A token grants the streams whose ID starts with its prefix (send sectors, read, end); an admin token grants
every stream and lists them all. Only hashes are stored: tokens are 256 random bits, so one SHA-256 is as
good as a slow KDF and costs a microsecond per request. `add_token` (`phim auth add-token`) appends a line
and returns the new token, printed once. The server stats the file on every check and re-reads it when it
changed (rotation without restart: add the new token, move the clients, delete the old line). A file that
cannot be read or parsed (a half-written save, a line no JSON parser takes) keeps the last good table; a
file that is gone revokes every token (fail closed: deleting the file is how an operator shuts every client
out). Either is logged once, as an ERROR, not once per request.

A token's prefix also names a tenant (server/tenants.py): `tenant_of` gives a stream the longest stream
token prefix its ID starts with.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import secrets
import threading
from dataclasses import dataclass
from pathlib import Path

from server.tenants import tenant_of_id

log = logging.getLogger(__name__)

TOKEN_PREFIX = "phim_"  # new tokens start with it (easy to spot in a leaked log or config)


class TokenFileError(ValueError):
    """A token file that cannot be read or parsed; the message names the file and line."""


@dataclass(frozen=True)
class Grant:
    """What one token may do."""

    prefix: str  # stream IDs it may use start with this ("" with admin: all)
    admin: bool = False
    note: str = ""

    def allows(self, stream_id: str) -> bool:
        return self.admin or stream_id.startswith(self.prefix)


def token_hash(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


def parse_tokens(text: str, source: str) -> dict[str, Grant]:
    """The token file's text -> {sha256 hex: Grant}; TokenFileError naming the line at fault."""
    table: dict[str, Grant] = {}
    for n, line in enumerate(text.splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        try:
            entry = json.loads(line)
            digest, prefix, admin = entry["sha256"], entry.get("prefix", ""), entry.get("admin", False)
        except (ValueError, KeyError, TypeError, AttributeError, RecursionError) as e:
            # ValueError: bad JSON, or an integer of over 4,300 digits; RecursionError: JSON nested too deep
            raise TokenFileError(
                f"{source}:{n}: {e}; expected a JSON object with sha256, prefix, admin"
            ) from None
        if not (isinstance(digest, str) and re.fullmatch("[0-9a-f]{64}", digest)):
            raise TokenFileError(f"{source}:{n}: sha256 must be 64 lowercase hex digits")
        if not isinstance(prefix, str) or not isinstance(admin, bool) or not (prefix or admin):
            raise TokenFileError(f"{source}:{n}: a token needs a non-empty prefix (string) or admin: true")
        table[digest] = Grant(prefix, admin, str(entry.get("note", "")))
    return table


class TokenFile:
    """The token table of one file, re-read when the file changes. Thread-safe."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self._lock = threading.Lock()
        self._stamp: tuple[int, int, int] | None = self._stat()  # None: the file is gone
        self._table = parse_tokens(self._read(), str(self.path))  # a bad file at start-up: TokenFileError
        self._prefixes = _stream_prefixes(self._table)
        self._fault: str | None = None  # what is wrong with the file now (logged once)

    def grant(self, token: str) -> Grant | None:
        """The token's grant, or None for an unknown token (every token while the file is gone)."""
        self._reload_if_changed()
        return self._table.get(token_hash(token))

    def tenant_of(self, stream_id: str) -> str:
        """A stream's tenant: the longest stream-token prefix its ID starts with, else `tenant_of_id`."""
        self._reload_if_changed()
        return next((p for p in self._prefixes if stream_id.startswith(p)), None) or tenant_of_id(stream_id)

    def _stat(self) -> tuple[int, int, int] | None:
        try:
            st = os.stat(self.path)
        except FileNotFoundError:
            return None
        except OSError as e:
            raise TokenFileError(f"{self.path}: {e.strerror}") from None
        return st.st_ino, st.st_mtime_ns, st.st_size

    def _read(self) -> str:
        try:
            return self.path.read_text()
        except (OSError, UnicodeDecodeError) as e:
            raise TokenFileError(f"{self.path}: {e}") from None

    def _reload_if_changed(self) -> None:
        try:
            stamp = self._stat()
        except TokenFileError as e:  # not readable (permissions): keep the table
            self._log_fault(f"{e}; keeping the {len(self._table)} tokens read before")
            return
        if stamp == self._stamp:
            return
        with self._lock:
            if stamp == self._stamp:
                return
            if stamp is None:  # deleted: fail closed
                self._table, self._prefixes, self._stamp = {}, [], None
                self._log_fault(f"{self.path}: no such file; every token is refused until it is back")
                return
            try:
                table = parse_tokens(self._read(), str(self.path))
            except TokenFileError as e:  # not re-read until it changes again
                self._stamp = stamp
                self._log_fault(f"{e}; keeping the {len(self._table)} tokens read before")
                return
            self._table, self._prefixes, self._stamp = table, _stream_prefixes(table), stamp
            self._fault = None
            log.info("auth: %s re-read: %d tokens", self.path, len(table))

    def _log_fault(self, fault: str) -> None:
        if fault != self._fault:
            self._fault = fault
            log.error("auth: %s", fault)


def _stream_prefixes(table: dict[str, Grant]) -> list[str]:
    """The stream tokens' prefixes, longest first (the first one a stream ID starts with is its tenant)."""
    return sorted({g.prefix for g in table.values() if not g.admin and g.prefix}, key=len, reverse=True)


def add_token(path: str | Path, prefix: str, admin: bool = False, note: str = "") -> str:
    """Append a new token's hash to the file (created owner-only if missing) -> the token (shown once)."""
    if not (prefix or admin):
        raise ValueError("a token needs a prefix (the stream IDs it may use start with it) or admin")
    token = TOKEN_PREFIX + secrets.token_urlsafe(32)
    line = json.dumps({"sha256": token_hash(token), "prefix": prefix, "admin": admin, "note": note})
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o600)
    with os.fdopen(fd, "a") as f:
        f.write(line + "\n")
    return token
