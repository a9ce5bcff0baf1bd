"""Rendezvous hashing (contract.placement): stable, balanced, and minimal when workers leave or join."""

from __future__ import annotations

from collections import Counter

from contract import KeySpace, stream_owner
from contract.placement import weight

STREAMS = [f"car-{i}" for i in range(3000)]


def owners(workers: list[str]) -> dict[str, str | None]:
    return {s: stream_owner(s, workers) for s in STREAMS}


def test_the_weight_is_a_fixed_function_every_process_agrees_on() -> None:
    # a fixed hash, not Python's (salted per process): a change here moves every fleet's streams
    assert weight("worker-0", "car-1") == 0xEC37DBA867AF25AD
    assert stream_owner("car-1", ["worker-0", "worker-1", "worker-2"]) == "worker-0"


def test_owners_are_balanced_and_do_not_depend_on_the_order_given() -> None:
    workers = ["gpu-a", "gpu-b", "gpu-c"]
    placed = owners(workers)
    assert placed == owners(workers[::-1])
    shares = Counter(placed.values())
    assert set(shares) == set(workers)
    assert all(abs(n / len(STREAMS) - 1 / 3) < 0.04 for n in shares.values()), shares
    assert stream_owner("car-1", []) is None


def test_a_worker_leaving_moves_only_its_own_streams() -> None:
    before = owners(["gpu-a", "gpu-b", "gpu-c"])
    after = owners(["gpu-a", "gpu-c"])
    moved = {s for s in STREAMS if before[s] != after[s]}
    assert moved == {s for s in STREAMS if before[s] == "gpu-b"}
    assert Counter(after[s] for s in moved).keys() == {"gpu-a", "gpu-c"}  # spread over both, not piled


def test_a_worker_joining_takes_about_a_quarter_and_nothing_else_moves() -> None:
    before = owners(["gpu-a", "gpu-b", "gpu-c"])
    after = owners(["gpu-a", "gpu-b", "gpu-c", "gpu-d"])
    moved = {s for s in STREAMS if before[s] != after[s]}
    assert all(after[s] == "gpu-d" for s in moved)
    assert abs(len(moved) / len(STREAMS) - 1 / 4) < 0.04, len(moved)


def test_a_workers_own_keys_are_under_the_stream_so_a_vehicles_acl_covers_them() -> None:
    keys = KeySpace()
    assert keys.sector("car-1") == "phim/v1/streams/car-1/sector"
    assert keys.sector("car-1", "gpu-a") == "phim/v1/streams/car-1/workers/gpu-a/sector"
    assert keys.worker_sector_queryable("gpu-a") == "phim/v1/streams/*/workers/gpu-a/sector"
    assert keys.worker_sector_subscriber("gpu-a") == "phim/v1/streams/*/workers/gpu-a/sectors"
    assert keys.stream_id_of(keys.sector("car-1", "gpu-a")) == "car-1"
