"""Where a worker is found: its default addresses and the zenoh key space, the key expressions under one
prefix (docs/protocol.md, "Zenoh"). Import them from `contract`."""

from __future__ import annotations

from dataclasses import dataclass

DEFAULT_KEY_PREFIX = "phim/v1"
# a worker started without options: HTTP on this port of 127.0.0.1, zenoh (a peer) listening on this endpoint
DEFAULT_HTTP_PORT = 8080
DEFAULT_URL = f"http://127.0.0.1:{DEFAULT_HTTP_PORT}"
DEFAULT_ZENOH_ENDPOINT = "tcp/127.0.0.1:7447"
PROBE_CHUNK = "~probe"  # the stream chunk of a worker probe: `~` is in no stream ID, so no stream is probed


@dataclass(frozen=True)
class KeySpace:
    """The key expressions under one prefix."""

    prefix: str = DEFAULT_KEY_PREFIX

    @property
    def sector_queryable(self) -> str:  # request/reply: get with a sector as payload
        return f"{self.prefix}/streams/*/sector"

    @property
    def sector_subscriber(self) -> str:  # pub/sub: put a sector
        return f"{self.prefix}/streams/*/sectors"

    def sector(self, stream_id: str, worker_id: str | None = None) -> str:
        """Where a get sends a stream's sector: any worker serving the shared keys, or (`worker_id`) that
        worker only, under its own keys (a fleet: `contract.stream_owner` says which)."""
        return f"{self.prefix}/streams/{stream_id}{_at(worker_id)}/sector"

    def sectors(self, stream_id: str, worker_id: str | None = None) -> str:
        return f"{self.prefix}/streams/{stream_id}{_at(worker_id)}/sectors"

    def probe(self, worker_id: str) -> str:
        """Where a client checks that a worker's token is real: a get on the worker's own sector key with the
        stream chunk PROBE_CHUNK (never a stream ID) and no payload, answered by the worker with an error
        (whose replier is the worker's zenoh session) and counted nowhere (clients/zenoh_workers.py)."""
        return self.sector(PROBE_CHUNK, worker_id)

    def worker_sector_queryable(self, worker_id: str) -> str:  # the same, under one worker's keys
        return self.sector("*", worker_id)

    def worker_sector_subscriber(self, worker_id: str) -> str:
        return self.sectors("*", worker_id)

    def detections(self, stream_id: str) -> str:
        return f"{self.prefix}/streams/{stream_id}/detections"

    def errors(self, stream_id: str) -> str:
        return f"{self.prefix}/streams/{stream_id}/errors"

    def worker(self, worker_id: str, zid: str = "*") -> str:
        """A worker's liveliness token: its ID, then the ID of its zenoh session (the `replier_id` of its
        answers, which is how a client knows an answer came from a worker and from which)."""
        return f"{self.prefix}/workers/{worker_id}/{zid}"

    def worker_of(self, key: str) -> tuple[str, str] | None:
        """(worker ID, zenoh session ID) of a worker's token key; None for a key of another shape."""
        head = f"{self.prefix}/workers/"
        parts = key[len(head) :].split("/") if key.startswith(head) else []
        return (parts[0], parts[1]) if len(parts) == 2 else None

    def stream_id_of(self, key: str) -> str:
        """The stream-ID chunk of `{prefix}/streams/{id}/...` ('' if the key has another shape)."""
        head = f"{self.prefix}/streams/"
        return key[len(head) :].split("/", 1)[0] if key.startswith(head) else ""


def _at(worker_id: str | None) -> str:
    return "" if worker_id is None else f"/workers/{worker_id}"
