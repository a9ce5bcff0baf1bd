"""The server on the fixed-shape step: a real uvicorn server around GraphStreamingDetector answers KITTI
sectors of concurrent streams as the eager detector does directly."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import httpx
import pytest
from pydantic import ValidationError
from server_helpers import (
    assert_same_boxes,
    comparable_detector,
    kitti_sectors,
    run_direct,
    sector_msg,
    serve,
)

from contract import MSGPACK, DetectionsReply, decode_response, encode_sector
from model.graph.engine import GraphStreamingDetector
from server.settings import Settings


def post(url: str, stream: str, seq: int, points) -> DetectionsReply:
    body = encode_sector(sector_msg(stream, seq, points))
    r = httpx.post(
        f"{url}/v1/streams/{stream}/sectors", content=body, headers={"Content-Type": MSGPACK}, timeout=120
    )
    assert r.status_code == 200, r.content[:300]
    out = decode_response(r.content)
    assert isinstance(out, DetectionsReply)
    return out


@pytest.mark.samples
def test_concurrent_streams_on_the_fixed_step_equal_the_eager_model():
    eager = comparable_detector()
    scans = {"car-a": kitti_sectors(0, every=2), "car-b": kitti_sectors(1, every=2)}
    refs = {k: run_direct(eager, v) for k, v in scans.items()}
    det = GraphStreamingDetector(eager.model)
    with serve(det, max_batch=4, max_wait_ms=20.0) as s, ThreadPoolExecutor(2) as pool:
        info = httpx.get(f"{s.url}/v1/model", timeout=10).json()
        assert (info["engine"], info["sector_voxels"]) == ("fixed", det.sector_voxels)
        for seq in range(4):
            futures = {k: pool.submit(post, s.url, k, seq, v[seq]) for k, v in scans.items()}
            for k, f in futures.items():
                r = f.result()
                assert_same_boxes(r.boxes, r.scores, r.labels, refs[k][seq])
                assert r.context_sectors == seq + 1


def test_a_graph_engine_batches_at_most_the_largest_bucket():
    with pytest.raises(ValidationError, match="max_batch 64"):
        Settings(engine="graph", max_batch=64)
    assert Settings(engine="eager", max_batch=64).max_batch == 64
