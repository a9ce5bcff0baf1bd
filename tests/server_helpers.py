"""Shared pieces of the server tests: the real default model, KITTI sectors, a gate on the forward pass, and
a real uvicorn server on a loopback port in a thread."""

from __future__ import annotations

import contextlib
import dataclasses
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import httpx
import numpy as np
import pytest
import torch
import uvicorn
from conftest import kitti_scan

from clients.bench.server import free_port
from contract import MSGPACK, DetectionsReply, SectorMessage, decode_response, encode_sector
from model.checkpoint import DEFAULT_SEED, load_default_model
from model.config import tiny
from model.detector import PHiM
from model.engine import StreamEngine
from model.sectors import split_turn
from model.stream import StreamingDetector
from server.app import create_app
from server.cli import uvicorn_config
from server.settings import Settings

FIELDS = ("x", "y", "z", "intensity")
START_TIMEOUT_S = 600.0  # a server's start and warm-up, bounded: a busy 2-core machine took over 60 s
LATE_S = 30.0  # slack past a configured timeout before a bounded wait fails: a busy machine is late


def default_detector() -> StreamingDetector:
    """The model `phim serve` runs by default (tiny config, fixed-seed weights)."""
    return StreamingDetector(load_default_model("cpu")[0])


def comparable_detector() -> StreamingDetector:
    """The default model's config and weights, but with clear heatmap peaks and a heatmap score threshold
    of 0.3: none to a few dozen boxes per KITTI sector instead of 200 near-ties, so the float noise between a
    batched and a single forward never changes which boxes pass a top-k cut (as in test_streaming)."""
    cfg = tiny()
    cfg = dataclasses.replace(cfg, head=dataclasses.replace(cfg.head, score_threshold=0.3))
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(DEFAULT_SEED)
        model = PHiM(cfg)
    with torch.no_grad():
        model.head.heatmap[-1].weight.mul_(40.0)
    return StreamingDetector(model.eval())


def kitti_sectors(index: int = 0, every: int = 1) -> list[np.ndarray]:
    """A real KITTI scan split into the tiny config's 4 azimuth sectors, (N_k, 4) float32 each; `every` > 1
    keeps every n-th point (faster forwards)."""
    return [s[::every].contiguous().numpy() for s in split_turn(kitti_scan(index), 4)]


def sector_msg(
    stream_id: str, seq: int, points: np.ndarray, index: int | None = None, **kw: Any
) -> SectorMessage:
    return SectorMessage(
        stream_id, seq, seq % 4 if index is None else index, 1000 * seq, points, FIELDS, **kw
    )


def post_first_sector(url: str, stream_id: str = "car-1") -> httpx.Response:
    """POST the first sector of KITTI 000000 (every 4th point) to a server at `url` as msgpack."""
    body = encode_sector(sector_msg(stream_id, 0, kitti_sectors(0, every=4)[0]))
    headers = {"Content-Type": MSGPACK}
    return httpx.post(f"{url}/v1/streams/{stream_id}/sectors", content=body, headers=headers, timeout=60)


def run_direct(det: StreamingDetector, sectors: list[np.ndarray]) -> list[Any]:
    """The reference: the same sectors through StreamingDetector.step, one stream, no server."""
    state, out = det.new_state(), []
    for s in sectors:
        (r,), (state,) = det.step([torch.from_numpy(s.copy())], [state])
        out.append(r.detections)
    return out


SCORE_NOISE = 1e-5  # batched and alone forwards differ by float noise; detections come sorted by score


def assert_same_boxes(boxes: np.ndarray, scores: np.ndarray, labels: np.ndarray, ref: Any) -> None:
    """A reply's arrays equal a reference Detections: the same count, the same scores in order, and each box
    and label equal to the reference's of the same score (up to float noise). Boxes whose scores differ by
    less than the noise may come in either order, and where the list is cut (top-k) either may be kept."""
    want_boxes, want_scores, want_labels = ref.boxes.numpy(), ref.scores.numpy(), ref.labels.numpy()
    assert boxes.shape == (len(ref), 7), (boxes.shape, len(ref))
    np.testing.assert_allclose(scores, want_scores, atol=SCORE_NOISE, rtol=0)
    taken = np.zeros(len(ref), bool)
    for i in range(len(boxes)):
        same = ~taken & (np.abs(want_scores - scores[i]) <= SCORE_NOISE) & (want_labels == labels[i])
        same &= np.all(np.abs(want_boxes - boxes[i]) <= 1e-4, axis=1)
        if same.any():
            taken[np.argmax(same)] = True
        else:  # only a box tied with the last one may differ: the cut fell the other way
            assert scores[i] - want_scores[-1] <= SCORE_NOISE, (i, boxes[i], scores[i], labels[i])


@dataclass
class StepGate:
    """Fault injection on the forward pass: hold `det.step` closed until `release()`, or make it raise."""

    det: StreamingDetector
    real: Callable[..., Any]
    opened: threading.Event = field(default_factory=threading.Event)
    entered: threading.Event = field(default_factory=threading.Event)
    batches: list[int] = field(default_factory=list)  # sectors per forward, in call order
    fail_at: set[int] = field(default_factory=set)  # forwards (0-based call numbers) that raise

    @staticmethod
    def install(det: StreamingDetector, monkeypatch: pytest.MonkeyPatch, closed: bool = True) -> StepGate:
        gate = StepGate(det, det.step)
        if not closed:
            gate.opened.set()
        monkeypatch.setattr(det, "step", gate.step)
        return gate

    def step(self, points: list[torch.Tensor], states: list[Any]) -> Any:
        call = len(self.batches)
        self.batches.append(len(points))
        self.entered.set()
        assert self.opened.wait(60), "gate never opened"
        if call in self.fail_at:
            raise RuntimeError("injected fault: device lost")
        return self.real(points, states)

    def release(self) -> None:
        self.opened.set()


@dataclass
class RunningServer:
    url: str
    server: uvicorn.Server
    thread: threading.Thread

    def stop(self) -> None:
        self.server.should_exit = True
        self.thread.join(60)
        assert not self.thread.is_alive(), "server did not stop"


def make_settings(**overrides: Any) -> Settings:
    """Test settings; replies keep every box (min_score 0), as `run_direct` gives them."""
    base: dict[str, Any] = dict(
        port=0, zenoh_enabled=False, warmup_sectors=1, worker_id="test-worker", min_score=0.0
    )
    return Settings(**{**base, **overrides})


@contextlib.contextmanager
def serve(det: StreamEngine | None, wait_ready: bool = True, **overrides: Any) -> Iterator[RunningServer]:
    """A real uvicorn server (thread, 127.0.0.1, free port) around create_app with the given detector (None:
    the one the settings build)."""
    settings = make_settings(**overrides)
    app = create_app(settings, detector=det)
    config = uvicorn_config(app, settings, log_level="warning")  # as `phim serve` runs it
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, name="uvicorn-test", daemon=True)
    thread.start()
    try:
        started = time.monotonic()  # bounded waits, long enough for a busy machine (they end when done)
        while time.monotonic() - started < START_TIMEOUT_S:
            if server.started or not thread.is_alive():
                break
            threading.Event().wait(0.05)
        assert server.started, "uvicorn did not start"
        port = server.servers[0].sockets[0].getsockname()[1]
        scheme = "https" if settings.tls_cert else "http"
        running = RunningServer(f"{scheme}://127.0.0.1:{port}", server, thread)
        if wait_ready:
            assert app.state.services.worker.wait_ready(START_TIMEOUT_S), app.state.services.worker.status
        yield running
    finally:
        server.should_exit = True
        thread.join(60)


def free_endpoint() -> str:
    """A zenoh TCP endpoint on a free loopback port."""
    return f"tcp/127.0.0.1:{free_port()}"


CONTROL = np.random.default_rng(0).uniform(-20, 20, (400, 4)).astype(np.float32)  # a sector with boxes


def control_reply(url: str, stream: str) -> DetectionsReply:
    """A fresh stream's first sector, always the same (CONTROL): fuzz tests compare its detections before
    and after to show that nothing they sent changed another stream."""
    r = httpx.post(
        f"{url}/v1/streams/{stream}/sectors",
        content=encode_sector(sector_msg(stream, 0, CONTROL)),
        headers={"Content-Type": MSGPACK},
        timeout=60,
    )
    out = decode_response(r.content)
    assert r.status_code == 200 and isinstance(out, DetectionsReply), out
    return out


def assert_same_reply(a: DetectionsReply, b: DetectionsReply) -> None:
    assert len(a.scores) > 0  # the control sector has boxes, so the comparison means something
    for x, y in ((a.boxes, b.boxes), (a.scores, b.scores), (a.labels, b.labels)):
        np.testing.assert_allclose(x, y, rtol=0, atol=1e-5)
