"""The live view (`phim serve --foxglove-port P`): a Foxglove WebSocket server showing each stream's latest
answered sector, its points and its boxes, to Foxglove (the app or the desktop) watching a serving worker.

Serving never waits for it. The worker's device thread calls `observe`, which only puts (sector, reply) on a
bounded queue with `put_nowait`: a full queue drops the sector (counted in `phim_live_view_dropped_total`).
A thread of its own turns them into Foxglove messages (`ros.scene`) and logs them on the stream's channels,
made with the stream's first sector: `/phim/{stream_id}/points` (foxglove.PointCloud) and
`/phim/{stream_id}/boxes` (foxglove.SceneUpdate). A sector nobody subscribed to is not drawn at all; the
Foxglove server sends a client only what it subscribed to and drops the oldest for a slow client.

The Foxglove server has no authentication (server/settings.py keeps it on loopback without --insecure).
"""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from contract import DetectionsReply, SectorMessage
from ros.scene import SceneChannels

if TYPE_CHECKING:
    import foxglove

log = logging.getLogger(__name__)

Item = tuple[SectorMessage, DetectionsReply]


@dataclass(frozen=True)
class LiveViewConfig:
    host: str = "127.0.0.1"
    port: int = 8765  # 0: a free one (LiveView.port says which)
    queue_size: int = 8  # answered sectors waiting to be drawn; beyond: the newest is dropped (counted)
    idle_s: float = 60.0  # a stream's channels close (unadvertised) after this long without a sector
    name: str = "phim"  # the server name Foxglove shows


@dataclass
class _Channels:
    scene: SceneChannels  # its points and boxes, the scene `phim replay --mcap` writes too
    last_seen: float


def topics(stream_id: str) -> tuple[str, str]:
    """A stream's channels: its points and its boxes."""
    return f"/phim/{stream_id}/points", f"/phim/{stream_id}/boxes"


def frame(stream_id: str) -> str:
    """A stream's frame: its sensor's, one per stream (two vehicles' sensor frames have nothing in common)."""
    return f"phim/{stream_id}"


class LiveView:
    """`start` binds the port (raises if it cannot), `observe` is the worker's observer, `stop` ends both."""

    def __init__(self, cfg: LiveViewConfig, dropped: Callable[[], None]):
        self.cfg = cfg
        self._dropped = dropped  # counts a dropped sector (Metrics.live_view_dropped.inc)
        self._queue: queue.Queue[Item | None] = queue.Queue(cfg.queue_size)
        self._stopping = threading.Event()
        self._streams: dict[str, _Channels] = {}
        self._context: foxglove.Context | None = None
        self._server: Any = None  # foxglove.websocket.WebSocketServer
        self._thread: threading.Thread | None = None

    @property
    def port(self) -> int:
        if self._server is None:
            raise RuntimeError("the live view is not started")
        return int(self._server.port)

    def start(self) -> None:
        try:
            import foxglove
        except ImportError as e:
            raise RuntimeError(
                f"live view: {e}; install phim[ros2] (foxglove-sdk), or leave out --foxglove-port"
            ) from e
        # a context of its own: channels of several servers in one process (tests) never mix
        self._context = foxglove.Context()
        cfg = self.cfg
        try:
            self._server = foxglove.start_server(
                name=cfg.name, host=cfg.host, port=cfg.port, context=self._context
            )
        except RuntimeError as e:  # FoxgloveError: Failed to bind port: Address already in use
            raise RuntimeError(f"live view on {cfg.host}:{cfg.port} (--foxglove-port): {e}") from None
        self._thread = threading.Thread(target=self._run, name="phim-live-view", daemon=True)
        self._thread.start()
        log.info(
            "live view: Foxglove WebSocket server on ws://%s:%d (no authentication)", cfg.host, self.port
        )

    def observe(self, msg: SectorMessage, reply: DetectionsReply) -> None:
        """In the device thread: hand the answered sector over, or drop it when the queue is full."""
        if self._stopping.is_set():
            return
        try:
            self._queue.put_nowait((msg, reply))
        except queue.Full:
            self._dropped()

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop drawing (what is queued is dropped), close the channels and the Foxglove server."""
        self._stopping.set()
        with contextlib.suppress(queue.Full):  # a full queue wakes the thread as well
            self._queue.put_nowait(None)
        if self._thread is not None:
            self._thread.join(timeout_s)
            if self._thread.is_alive():
                log.warning("live view: still drawing %.1f s after stop; leaving it", timeout_s)
        if self._server is not None:
            self._server.stop()
            self._server = None
        log.info("live view stopped")

    # ------------------------------------------------------------------------------------ drawing thread

    def _run(self) -> None:
        while not self._stopping.is_set():
            try:
                item = self._queue.get(timeout=min(1.0, self.cfg.idle_s))
            except queue.Empty:
                item = None
            if item is not None and not self._stopping.is_set():
                try:
                    self._draw(*item)
                except Exception:  # one bad sector must not end the view
                    log.exception("live view: drawing %s seq %d failed", item[0].stream_id, item[0].seq)
            self._close_idle(time.monotonic())
        for stream_id in list(self._streams):
            self._close(stream_id)

    def _draw(self, msg: SectorMessage, reply: DetectionsReply) -> None:
        scene = self._channels(msg.stream_id).scene
        if scene.watched():  # nobody subscribed: drawing would be wasted
            scene.log(reply, msg.points, msg.timestamp_ns, frame(msg.stream_id), log_time_ns=time.time_ns())

    def _channels(self, stream_id: str) -> _Channels:
        """A stream's channels, made (advertised) with its first sector."""
        channels = self._streams.get(stream_id)
        if channels is None:
            points, boxes = topics(stream_id)
            channels = _Channels(SceneChannels(self._context, points, boxes), time.monotonic())
            self._streams[stream_id] = channels
            log.info("live view: stream %s on %s and %s", stream_id, points, boxes)
        channels.last_seen = time.monotonic()
        return channels

    def _close_idle(self, now: float) -> None:
        for stream_id, channels in list(self._streams.items()):
            if now - channels.last_seen > self.cfg.idle_s:
                self._close(stream_id)

    def _close(self, stream_id: str) -> None:
        self._streams.pop(stream_id).scene.close()
