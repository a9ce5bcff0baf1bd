"""What serves beside HTTP, started by the app's lifespan: the zenoh transport, the ROS 2 bridge (on the
zenoh transport's session) and the live view. Each is imported only when it runs (zenoh, rosbags,
foxglove-sdk); what announces the worker to clients waits until it is warmed up."""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from functools import partial
from typing import TYPE_CHECKING

from server.metrics import Metrics
from server.settings import Settings
from server.worker import Worker

if TYPE_CHECKING:
    from ros.live_view import LiveView
    from server.ros2_bridge import Ros2Bridge
    from server.zenoh_transport import ZenohTransport

log = logging.getLogger(__name__)


def start_zenoh(settings: Settings, worker: Worker) -> ZenohTransport:
    try:
        from server.zenoh_transport import ZenohTransport
    except ImportError as e:
        raise RuntimeError(f"zenoh transport unavailable ({e}); serve with --no-zenoh") from e

    transport = ZenohTransport(
        partial(worker.submit, transport="zenoh"),
        settings.zenoh_config(),
        worker.worker_id,
        settings.limits(),
        on_reject=lambda code: worker.metrics.count("zenoh", code.value),
    )
    transport.start(announce=False)
    log.info(
        "zenoh: mode=%s listen=%s connect=%s",
        settings.zenoh_mode,
        settings.zenoh_listen,
        settings.zenoh_connect,
    )
    _when_ready(worker, transport.announce)
    return transport


def start_live_view(settings: Settings, metrics: Metrics) -> LiveView | None:
    """The live view when --foxglove-port is given (its port bound: a taken port fails the start-up)."""
    if settings.foxglove_port is None:
        return None
    from ros.live_view import LiveView  # foxglove-sdk is imported only when a live view runs

    view = LiveView(settings.live_view_config(), metrics.live_view_dropped.inc)
    view.start()
    return view


def start_ros2(settings: Settings, worker: Worker, zenoh: ZenohTransport | None) -> Ros2Bridge | None:
    """The ROS 2 bridge when --ros2-points is given (docs/ros2.md): on the zenoh transport's session (with
    --no-zenoh, its own from the same settings), in the ROS graph once the worker is warmed up."""
    if settings.ros2_points is None:
        return None
    from server.ros2_bridge import Ros2Bridge  # rosbags is imported only when a bridge runs

    bridge = Ros2Bridge(
        partial(worker.submit, transport="ros2"),
        settings.ros2_config(),
        settings.limits(),
        on_reject=lambda code: worker.metrics.count("ros2", code.value),
        zenoh_cfg=settings.zenoh_config(),
    )
    bridge.open(None if zenoh is None else zenoh.session)
    _when_ready(worker, lambda: bridge.announce(worker.det.cfg.sectors_per_turn))
    return bridge


def _when_ready(worker: Worker, then: Callable[[], None]) -> None:
    """Run `then` on a thread of its own once the worker is warmed up (never, if its start-up fails): what
    announces this worker to clients (a zenoh token, the ROS graph) waits until it can answer."""

    def wait() -> None:
        while worker.live:
            if worker.wait_ready(1.0):
                then()
                return

    threading.Thread(target=wait, daemon=True).start()
