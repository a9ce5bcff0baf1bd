"""The Envoy example (deploy/envoy/envoy.yaml): no Envoy runs here, so its essentials are checked by reading
it: ring hash over the same workers as the nginx config, a hash key that is the stream ID of every stream
route (the path regex applied as Envoy would, RE2 and Python agreeing on this pattern), and no retries."""

from __future__ import annotations

import re
from pathlib import Path

import yaml

ENVOY = Path(__file__).resolve().parents[1] / "deploy" / "envoy" / "envoy.yaml"
NGINX = ENVOY.parents[1] / "nginx" / "phim.conf"


def config() -> dict:
    return yaml.safe_load(ENVOY.read_text())["static_resources"]


def route() -> dict:
    (listener,) = config()["listeners"]
    (chain,) = listener["filter_chains"]
    (manager,) = chain["filters"]
    (host,) = manager["typed_config"]["route_config"]["virtual_hosts"]
    (only,) = host["routes"]
    return only["route"]


def test_envoy_hashes_every_route_of_a_stream_to_its_stream_id() -> None:
    (policy,) = route()["hash_policy"]
    header = policy["header"]
    assert header["header_name"] == ":path"
    pattern = re.compile(header["regex_rewrite"]["pattern"]["regex"])
    substitution = header["regex_rewrite"]["substitution"].replace("\\1", r"\g<1>")
    for path in ("/v1/streams/car-7/sectors", "/v1/streams/car-7", "/v1/streams/car-7/sectors?x=1"):
        assert pattern.sub(substitution, path) == "car-7", path
    assert pattern.sub(substitution, "/health/ready") == "/health/ready"  # others: the whole path
    assert "retry_policy" not in route()  # a sector is never resent to another worker's state


def test_envoy_rings_over_the_same_workers_as_nginx() -> None:
    (cluster,) = config()["clusters"]
    assert cluster["lb_policy"] == "RING_HASH" and route()["cluster"] == cluster["name"]
    (group,) = cluster["load_assignment"]["endpoints"]
    envoy = sorted(
        f"{e['endpoint']['address']['socket_address']['address']}:"
        f"{e['endpoint']['address']['socket_address']['port_value']}"
        for e in group["lb_endpoints"]
    )
    nginx = sorted(re.findall(r"^\s*server\s+(\S+?);", NGINX.read_text(), re.M))
    assert envoy == nginx
