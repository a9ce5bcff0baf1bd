"""The house rules (docs/architecture.md, "The house"), read from every module's import statements, including
those inside functions: imports run one way, clients -> contract <- server -> model, with the data layer
(lidar) beneath clients, server and model, and no cycles."""

from __future__ import annotations

import ast
import sys
from collections.abc import Callable

import pytest
from conftest import REPO

PACKAGES = ("contract", "lidar", "phim", "model", "server", "clients")
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


@pytest.mark.parametrize(
    ("package", "forbidden"),
    [
        ("server", ("clients",)),
        ("clients", ("server", "torch", "model")),
        ("model", ("server", "clients")),
        ("model.eval", ("model.train",)),
        ("lidar", ("torch", "model", "server", "clients")),
        ("phim", ("model", "server", "clients", "contract", "torch")),
    ],
)
def test_imports_run_one_way(package: str, forbidden: tuple[str, ...]) -> None:
    def allowed(dep: str) -> bool:
        return not any(dep == f or dep.startswith(f + ".") for f in forbidden)

    assert imports_of(package), package
    assert offenders(package, allowed) == []


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
