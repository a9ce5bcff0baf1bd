"""The house rules (docs/architecture.md, "The house"), read from every module's import statements, including
those inside functions: imports run one way, clients -> contract <- server -> model, with the data layer
(lidar) beneath clients, server and model, ROS 2 and Foxglove (ros) on it beneath clients and server, and no
cycles."""

from __future__ import annotations

import ast
import sys
from collections.abc import Callable

import pytest
from conftest import REPO

PACKAGES = ("contract", "lidar", "ros", "phim", "model", "server", "clients")
STDLIB = sys.stdlib_module_names


def modules() -> dict[str, set[str]]:
    """'package.module' -> the full names it imports (absolute imports only: the project uses no others;
    `from package import submodule` counts as importing the submodule)."""
    paths = {
        ".".join(path.relative_to(REPO).with_suffix("").parts).removesuffix(".__init__"): path
        for package in PACKAGES
        for path in (REPO / package).rglob("*.py")
    }
    out: dict[str, set[str]] = {}
    for name, path in paths.items():
        out[name] = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                out[name] |= {a.name for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                subs = {f"{node.module}.{a.name}" for a in node.names} & paths.keys()
                out[name] |= subs or {node.module}
    return out


MODULES = modules()


def imports_of(prefix: str) -> dict[str, set[str]]:
    return {m: deps for m, deps in MODULES.items() if m == prefix or m.startswith(prefix + ".")}


def offenders(prefix: str, allowed: Callable[[str], bool]) -> list[str]:
    found = ((m, d) for m, deps in imports_of(prefix).items() for d in deps)
    return sorted(f"{m} imports {d}" for m, d in found if not allowed(d))


def top(name: str) -> str:
    return name.split(".")[0]


def test_the_contract_imports_only_numpy_msgpack_and_the_standard_library() -> None:
    assert MODULES["contract"]  # read
    allowed = {"contract", "numpy", "msgpack", "msgspec"} | STDLIB  # its own modules, numpy, the codec
    assert offenders("contract", lambda d: top(d) in allowed) == []


def test_ros_imports_the_contract_the_data_layer_and_its_codecs_only() -> None:
    # ROS 2 messages, PointCloud2, recordings and Foxglove scenes: torch-free, zenoh-free (the bridge's
    # transport is server/ros2_bridge.py), beneath clients and server
    allowed = {"ros", "contract", "lidar", "numpy", "msgspec", "rosbags", "mcap", "foxglove"} | STDLIB
    assert imports_of("ros"), "ros"
    assert offenders("ros", lambda d: top(d) in allowed) == []


@pytest.mark.parametrize(
    ("package", "forbidden"),
    [
        ("server", ("clients",)),
        ("clients", ("server", "torch", "model")),
        ("model", ("server", "clients")),
        ("model.eval", ("model.train",)),
        ("lidar", ("torch", "model", "server", "clients", "ros")),
        ("phim", ("model", "server", "clients", "contract", "torch")),
    ],
)
def test_imports_run_one_way(package: str, forbidden: tuple[str, ...]) -> None:
    def allowed(dep: str) -> bool:
        return not any(dep == f or dep.startswith(f + ".") for f in forbidden)

    assert imports_of(package), package
    assert offenders(package, allowed) == []


# the server reaches the model through the engine interface (model.engine: the engines' types, settings and
# builder) and the configs; model.checkpoint names the shipped default (`python -m server.default_model`)
SERVER_MODEL_IMPORTS = {"model.engine", "model.config", "model.checkpoint"}


def test_the_server_reaches_the_model_through_the_engine_interface_only() -> None:
    used = {d for deps in imports_of("server").values() for d in deps if top(d) == "model"}
    assert "model.engine" in used and len(SERVER_MODEL_IMPORTS) <= 4
    assert used <= SERVER_MODEL_IMPORTS, sorted(used - SERVER_MODEL_IMPORTS)
    inside = ("model.graph", "model.ops", "model.geometry", "model.layers")  # how an engine runs
    assert [d for d in used if d.startswith(tuple(p + "." for p in inside)) or d in inside] == []


def test_no_import_cycles_between_modules() -> None:
    graph = {m: {d for d in deps if d in MODULES and d != m} for m, deps in MODULES.items()}
    seen: dict[str, int] = {}  # 1: on the current path, 2: done

    def visit(m: str, path: list[str]) -> None:
        seen[m] = 1
        for d in sorted(graph[m]):
            assert seen.get(d) != 1, " -> ".join([*path, m, d])
            if d not in seen:
                visit(d, [*path, m])
        seen[m] = 2

    for m in sorted(graph):
        if m not in seen:
            visit(m, [])
