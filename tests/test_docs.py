"""The design docs are in the present tense: they say how things are and why, with no dates and no timings.
Measurements live in docs/benchmarks.md (today's figures, each with its machine, date and command) and the
past in docs/history/. docs/model-card.md is exempt too: a model card reports the shipped model's figures
and when they were measured, by design (its earlier versions: docs/history/model-card.md).

A timing is a number with a unit of time ("12 ms", "3.4 s", "15–60 s", "5.7 us", "20 minutes"); a flag such
as `--max-minutes` or `--warmup S` is not one. Where a number with a unit of time is a setting (a default
timeout, a period the code is written to), ALLOWED names it, line fragment by line fragment, with why."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from conftest import REPO

DOCS = REPO / "docs"
FIGURES = ("benchmarks.md", "model-card.md")  # report measurements by design (docs/history/ too)
DATE = re.compile(r"\b20\d\d-\d\d-\d\d\b")
TIMING = re.compile(
    r"(?<![\w.-])\d+(?:[.,]\d+)?(?:\s?[–-]\s?\d+(?:[.,]\d+)?)?\s?"
    r"(?:ns|µs|us|ms|s|sec|secs|seconds?|min|minutes?|h|hours?)(?![\w/])"
)

# (doc, the line's fragment holding the setting): a default or a fixed period, not something measured
ALLOWED: tuple[tuple[str, str], ...] = (
    ("architecture.md", "`min(1 s, idle_timeout / 4)`"),  # the device loop's eviction period (code)
    ("deployment.md", "(up to 10 minutes of warm-up)"),  # the manifest's startup probe
    ("deployment.md", "keeps serving 10 s (preStop)"),  # the manifest's preStop hook
    ("deployment.md", "10 s by default"),  # zenoh's link lease, its default
    ("deployment.md", "every 2.5 ms from 5 to 40 ms (a sensor sends a sector every 25 ms)"),  # histogram
    ("deployment.md", "up to 10 s."),  # the latency histogram's last bucket
    ("operations.md", "the sensor period (25 ms)"),  # 10 Hz, 4 sectors a turn
    ("protocol.md", "p99 <= 25 ms (one"),  # the load test's default threshold: one sensor period
    ("protocol.md", "(50 ms, doubling to 1 s;"),  # the load tester's back-off
    ("ros2.md", "every 5 s)"),  # the bridge's warning rate limit
    ("security.md", "(at most every 5 s)"),  # the client's claim-table log rate limit
)


EXTERNAL = {"docs/design.md"}  # rmw_zenoh's design notes (docs/ros2.md), not ours


def design_docs() -> list[Path]:
    return sorted(p for p in DOCS.glob("*.md") if p.name not in FIGURES)


def findings(name: str, text: str) -> list[str]:
    """'doc:line: match' for every date or timing of `text`, the fragments ALLOWED for `name` taken out."""
    allowed = [fragment for doc, fragment in ALLOWED if doc == name]
    out = []
    for number, line in enumerate(text.splitlines(), 1):
        for fragment in allowed:
            line = line.replace(fragment, "")
        out += [f"{name}:{number}: {m.group(0)!r}" for m in [*DATE.finditer(line), *TIMING.finditer(line)]]
    return out


def test_the_design_docs_hold_no_dates_and_no_timings() -> None:
    docs = design_docs()
    names = {p.name for p in docs}
    assert {"architecture.md", "model.md", "protocol.md", "deployment.md", "ros2.md", "simulator.md"} <= names
    found = [f for p in docs for f in findings(p.name, p.read_text())]
    assert not found, "move these to docs/benchmarks.md or docs/history/:\n" + "\n".join(found)


def test_every_allowed_fragment_is_still_there() -> None:
    """The allowlist shrinks with the docs: a fragment no longer in its doc is a stale entry."""
    stale = [(doc, f) for doc, f in ALLOWED if f not in (DOCS / doc).read_text()]
    assert not stale


@pytest.mark.parametrize(
    ("text", "found"),
    [
        ("took 12 ms a step", ["'12 ms'"]),
        ("3.4 s on the CPU", ["'3.4 s'"]),
        ("compiled for 15–60 s while", ["'15–60 s'"]),
        ("0.31-0.39 ms per step", ["'0.31-0.39 ms'"]),
        ("decodes in 5.7 us, 320us from JSON", ["'5.7 us'", "'320us'"]),
        ("take 6 to 12 minutes", ["'12 minutes'"]),
        ("measured on 2026-12-01", ["'2026-12-01'"]),
        ("`--max-minutes`, `--warmup S` seconds, 4 sectors, 10 m/s, 40 sectors/s, 2 × 32, v1.5", []),
    ],
)
def test_the_patterns_catch_dates_and_timings_only(text: str, found: list[str]) -> None:
    assert [f.split(": ", 1)[1] for f in findings("x.md", text)] == found


def test_relative_links_between_docs_resolve() -> None:
    """A measurement moved to docs/benchmarks.md or docs/history/ is still found from where it was."""
    broken = []
    for page in [REPO / "README.md", *DOCS.glob("*.md"), *DOCS.glob("history/*.md")]:
        for target in re.findall(r"\]\(([^)#:\s]+\.md)(?:#[^)]*)?\)", page.read_text()):
            if not (page.parent / target).exists():
                broken.append(f"{page.relative_to(REPO)} -> {target}")
        for target in re.findall(r"\bdocs/[\w/.-]+\.md\b", page.read_text()):
            if not (REPO / target).exists() and target not in EXTERNAL:
                broken.append(f"{page.relative_to(REPO)} -> {target}")
    assert not broken


def test_the_repository_paths_the_docs_name_exist() -> None:
    """A file the docs name by its path in this repository (`model/ops/scan.py`, `tests/test_docs.py`) is
    there: docs change with the code they describe."""
    roots = ("contract", "lidar", "model", "server", "clients", "phim", "ros", "tests", "scripts", "deploy")
    files = r"[\w/.-]*\.(?:py|sh|md|toml|ya?ml|json5?|conf|txt|csv|png)\b"  # a file, not a topic or key
    pattern = re.compile(rf"(?<![\w/.-])(?:{'|'.join(roots)})/{files}")
    missing = [
        f"{page.relative_to(REPO)}: {path}"
        for page in [REPO / "README.md", *DOCS.glob("*.md")]
        for path in sorted(set(pattern.findall(page.read_text())))
        if not (REPO / path).exists()
    ]
    assert not missing
