"""A client nobody here wrote: openapi-python-client generates a Python client from the server's
GET /openapi.json alone, and a real scan's sectors go through it to a real uvicorn server, over JSON (the
generated operation) and msgpack (the generated models packed with a msgpack library, as a stranger does:
the generator has no msgpack serializer). The boxes come back, the same either way; a body whose stream_id
is not the path's gets a clear 422.

The scan is KITTI's first (the samples); where they are missing, a simulated one (in CI, where
PHIM_REQUIRE_SAMPLES=1, the KITTI one must be there)."""

from __future__ import annotations

import base64
import importlib
import io
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType
from typing import Any

import httpx
import msgpack
import numpy as np
import pytest
import torch
from conftest import REQUIRE_SAMPLES, kitti_scan
from server_helpers import RunningServer, default_detector, serve

from contract import JSON, MSGPACK
from lidar.samples import KITTI_000000
from lidar.sim.simulate import simulate
from model.sectors import split_turn

PACKAGE = "phim_generated_client"
FIELDS = ("x", "y", "z", "intensity")
CONFIG = "post_hooks: []\n"  # no formatter run over the generated code (it needs none to work)


def scan_sectors() -> list[np.ndarray]:
    """KITTI 000000 (every 2nd point) in the default model's 4 sectors, or a simulated turn without it."""
    if KITTI_000000.exists() or REQUIRE_SAMPLES:
        points = kitti_scan(0)[::2].contiguous()
    else:
        points = torch.from_numpy(simulate(3).points[:, :4].astype(np.float32))
    return [s.numpy() for s in split_turn(points, 4)]


@pytest.fixture(scope="module")
def server() -> Iterator[RunningServer]:
    with serve(default_detector()) as s:
        yield s


@pytest.fixture(scope="module")
def client_package(server: RunningServer, tmp_path_factory: pytest.TempPathFactory) -> Iterator[ModuleType]:
    """The package openapi-python-client generates from the running server's /openapi.json, imported."""
    root = tmp_path_factory.mktemp("generated")
    (root / "openapi.json").write_bytes(httpx.get(f"{server.url}/openapi.json", timeout=30).content)
    (root / "config.yaml").write_text(CONFIG)
    generator = Path(sys.executable).with_name("openapi-python-client")
    cmd = [str(generator), "generate", "--path", "openapi.json", "--meta", "none"]
    cmd += ["--output-path", PACKAGE, "--config", "config.yaml"]
    r = subprocess.run(cmd, cwd=root, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0 and (root / PACKAGE / "client.py").exists(), r.stdout + r.stderr
    assert "Unsupported" not in r.stdout.replace("Unsupported content type application/msgpack", ""), r.stdout
    sys.path.insert(0, str(root))
    try:
        yield importlib.import_module(PACKAGE)
    finally:
        sys.path.remove(str(root))
        for name in [n for n in sys.modules if n == PACKAGE or n.startswith(PACKAGE + ".")]:
            del sys.modules[name]


def generated(package: ModuleType, name: str) -> Any:
    return importlib.import_module(f"{package.__name__}.{name}")


def packable(value: Any) -> Any:
    """A generated model's to_dict() as msgpack values: a binary field (the generator's `File`, whose
    to_dict form is a (name, file, mime) tuple) as its bytes."""
    if isinstance(value, dict):
        return {k: packable(v) for k, v in value.items()}
    if isinstance(value, tuple) and len(value) == 3 and isinstance(value[1], io.BytesIO):
        return value[1].getvalue()
    if isinstance(value, list):
        return [packable(v) for v in value]
    return value


def test_a_generated_client_sends_a_scan_over_json_and_msgpack(server, client_package) -> None:
    models, types = generated(client_package, "models"), generated(client_package, "types")
    post_sector = generated(client_package, "api.default.post_sector")
    with generated(client_package, "client").Client(server.url, timeout=httpx.Timeout(120)) as client:
        boxes_json, boxes_msgpack = send_scan(client, models, types, post_sector)
    assert sum(len(b) for b in boxes_json) > 0, "no boxes came back"
    for a, b in zip(boxes_json, boxes_msgpack, strict=True):
        np.testing.assert_allclose(a, b, atol=1e-4)  # the same detections over either media type


def send_scan(client: Any, models: Any, types: Any, post_sector: Any) -> tuple[list, list]:
    """A turn's sectors through the generated client, over JSON and msgpack: the boxes (K, 7) of each."""
    fields = list(FIELDS)
    boxes_json, boxes_msgpack = [], []
    for seq, points in enumerate(scan_sectors()):
        raw = np.ascontiguousarray(points, "<f4").tobytes()
        b64 = base64.b64encode(raw).decode()
        # JSON: the generated operation, points.data a base64 string as JsonPoints says
        body = models.JsonSector(
            stream_id="gen-json", seq=seq, sector_index=seq, timestamp_ns=seq, fields=fields,
            points=models.JsonPoints(dtype="<f4", shape=list(points.shape), data=b64),
        )  # fmt: skip
        r = post_sector.sync_detailed("gen-json", client=client, body=body)
        assert r.status_code == 200 and isinstance(r.parsed, models.JsonDetections), r.content[:500]
        assert (r.parsed.stream_id, r.parsed.seq, r.parsed.context_sectors) == ("gen-json", seq, seq + 1)
        boxes_json.append(np.array(r.parsed.boxes, np.float32).reshape(-1, 7))
        # msgpack: the generated models (points.data a File: binary, as WirePoints says), packed as they are
        wire = models.WireSector(
            stream_id="gen-msgpack", seq=seq, sector_index=seq, timestamp_ns=seq, fields=fields,
            points=models.WirePoints(dtype="<f4", shape=list(points.shape), data=types.File(io.BytesIO(raw))),
        )  # fmt: skip
        headers = {"Content-Type": MSGPACK}
        packed = msgpack.packb(packable(wire.to_dict()), use_bin_type=True)
        reply = client.get_httpx_client().post(
            "/v1/streams/gen-msgpack/sectors", content=packed, headers=headers
        )
        assert reply.status_code == 200 and reply.headers["content-type"] == MSGPACK, reply.content[:500]
        detections = models.WireDetections.from_dict(msgpack.unpackb(reply.content))
        assert (detections.seq, detections.context_sectors) == (seq, seq + 1)
        assert isinstance(detections.boxes.data, types.File) and detections.boxes.dtype == "<f4"
        boxes = np.frombuffer(detections.boxes.data.payload.read(), "<f4").reshape(detections.boxes.shape)
        boxes_msgpack.append(boxes)
    return boxes_json, boxes_msgpack


def test_a_generated_client_is_told_clearly_what_it_got_wrong(server, client_package) -> None:
    models = generated(client_package, "models")
    post_sector = generated(client_package, "api.default.post_sector")
    points = np.zeros((8, 4), "<f4")

    def body(stream_id: str, fields: list[str]) -> Any:
        data = base64.b64encode(points.tobytes()).decode()
        return models.JsonSector(
            stream_id=stream_id, seq=0, sector_index=0, timestamp_ns=0, fields=fields,
            points=models.JsonPoints(dtype="<f4", shape=[8, 4], data=data),
        )  # fmt: skip

    with generated(client_package, "client").Client(server.url, timeout=httpx.Timeout(60)) as client:
        r = post_sector.sync_detailed("gen-path", client=client, body=body("gen-body", list(FIELDS)))
        assert r.status_code == 422 and isinstance(r.parsed, models.WireError), r.content
        assert r.parsed.field == "stream_id" and "'gen-body' in the body" in r.parsed.message, r.parsed
        fields = ["y", "x", "z", "intensity"]
        r = post_sector.sync_detailed("gen-path", client=client, body=body("gen-path", fields))
        assert r.status_code == 422 and r.parsed.field == "fields", r.content
    assert httpx.get(f"{server.url}/v1/streams/gen-path", timeout=30).status_code == 404  # nothing ran


def test_the_document_says_what_a_generator_needs(server) -> None:
    """The rules the generator cannot act on are written in the schema: per media type, fields, the path's
    stream_id, the azimuths of a sector."""
    doc = httpx.get(f"{server.url}/openapi.json", timeout=30).json()
    schemas = doc["components"]["schemas"]
    body = doc["paths"]["/v1/streams/{stream_id}/sectors"]["post"]["requestBody"]["content"]
    assert body[MSGPACK]["schema"]["$ref"].endswith("/WireSector")
    assert body[JSON]["schema"]["$ref"].endswith("/JsonSector")
    assert schemas["WirePoints"]["properties"]["data"]["format"] == "binary"
    assert schemas["WireArray"]["properties"]["data"]["format"] == "binary"  # the msgpack reply's arrays
    assert schemas["JsonPoints"]["properties"]["data"]["contentEncoding"] == "base64"
    fields = schemas["WireSector"]["properties"]["fields"]
    assert [p["const"] for p in fields["prefixItems"]] == ["x", "y", "z", "intensity"]
    assert (fields["minItems"], fields["maxItems"], fields["uniqueItems"]) == (4, 16, True)
    assert schemas["JsonSector"]["properties"]["fields"] == fields
    assert "equal the path's stream_id" in schemas["WireSector"]["properties"]["stream_id"]["description"]
    assert "[-180, -90)" in schemas["JsonSector"]["properties"]["sector_index"]["description"]
