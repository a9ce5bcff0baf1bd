"""The `phim` command itself: lazy imports, generated help with environment variables, --version, --json on
stdout, exit codes (0 success, 1 the run failed, 2 usage)."""

from __future__ import annotations

import json
import subprocess
import sys

import click
import pytest
from click.testing import CliRunner
from conftest import REPO
from server_helpers import free_port

from phim.cli import COMMANDS, Entry, Group, load
from phim.cli import main as app
from server.cli import serve, setting_group
from server.settings import SettingGroup, Settings

HEAVY = ("torch", "zenoh", "fastapi", "uvicorn", "httpx", "matplotlib")


def imported_after(args: list[str]) -> set[str]:
    """The heavy packages a fresh interpreter has imported after running `phim ARGS` (which must exit 0)."""
    code = "\n".join(
        [
            "import sys",
            "from phim.cli import main",
            f"try: main({args!r}, prog_name='phim')",
            "except SystemExit as e: assert e.code == 0, e.code",
            f"print('loaded:' + ','.join(m for m in {HEAVY!r} if m in sys.modules), file=sys.stderr)",
        ]
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, check=True)
    (line,) = [x for x in out.stderr.splitlines() if x.startswith("loaded:")]
    return set(filter(None, line.removeprefix("loaded:").split(",")))


def test_help_and_version_import_nothing_heavy() -> None:
    assert imported_after(["--help"]) == set()
    assert imported_after(["--version"]) == set()
    assert imported_after(["loadtest", "--help"]) == set()  # a clients-only install has no torch
    assert imported_after(["replay", "--help"]) == set()
    assert imported_after(["serve", "--help"]) == set()  # settings only: no torch, no FastAPI


def entries() -> list[tuple[str, Entry]]:
    out = []
    for name, e in COMMANDS.items():
        out += (
            [(f"{name} {n}", sub) for n, sub in e.commands.items()] if isinstance(e, Group) else [(name, e)]
        )
    return out


@pytest.mark.parametrize(("name", "entry"), entries(), ids=[n for n, _ in entries()])
def test_every_command_loads_and_shows_generated_help(name: str, entry: Entry) -> None:
    command = load(entry)
    assert isinstance(command, click.Command) and entry.help
    result = CliRunner().invoke(app, [*name.split(), "--help"], terminal_width=200)
    assert result.exit_code == 0, result.output
    assert f"Usage: phim {name} [OPTIONS]" in result.output
    assert "[PHIM_" not in result.output  # no hand-written "[PHIM_X; default]" strings: click makes them


def test_root_help_lists_every_command_and_version_answers() -> None:
    result = CliRunner().invoke(app, ["--help"])
    assert result.exit_code == 0
    for name in COMMANDS:
        assert f"  {name} " in result.output
    version = CliRunner().invoke(app, ["--version"])
    assert version.exit_code == 0 and version.output.startswith("phim, version ")


def test_shared_options_name_their_environment_variables() -> None:
    out = CliRunner().invoke(app, ["loadtest", "--help"], terminal_width=200).output
    for var in ("PHIM_URL", "PHIM_TRANSPORT", "PHIM_ZENOH_CONNECT", "PHIM_TIMEOUT_S"):
        assert var in out
    out = CliRunner().invoke(app, ["bench", "model", "--help"], terminal_width=200).output
    for var in ("PHIM_CONFIG", "PHIM_DEVICE", "PHIM_CHECKPOINT", "PHIM_THREADS"):
        assert var in out


def test_serve_has_a_flag_for_every_setting_with_its_variable() -> None:
    flags = {p.name: p for p in serve.params}
    assert set(flags) == set(Settings.model_fields)
    out = CliRunner().invoke(app, ["serve", "--help"], terminal_width=200).output
    for name in Settings.model_fields:
        assert f"PHIM_{name.upper()}" in out
    assert "--zenoh / --no-zenoh" in out and "--max-batch INTEGER" in out


SERVE_HELP_LINES = 160  # at 80 columns (`phim serve --help | wc -l`); as one flat list it took 222


def test_serve_help_lists_every_option_once_in_its_group_and_is_short() -> None:
    out = CliRunner().invoke(app, ["serve", "--help"], terminal_width=80).output
    sections: dict[str, list[str]] = {}
    for line in out.splitlines():
        if line.endswith(":") and not line.startswith(" "):
            sections[line.removesuffix(":")] = []
        elif line.startswith("  -") and sections:
            sections[list(sections)[-1]].append(line.split()[0].rstrip(","))
    assert list(sections) == [g.value for g in SettingGroup] + ["Other"]
    assert sections["Other"] == ["-h"]
    listed = [flag for flags in sections.values() for flag in flags]
    assert len(listed) == len(set(listed)) == len(Settings.model_fields) + 1  # each once, and --help
    for name, field in Settings.model_fields.items():
        flag = "--" + name.removesuffix("_enabled").replace("_", "-")
        assert flag in sections[setting_group(field).value], (name, sections)
    assert "[default:" not in out  # a default the description names joins its variable's bracket
    assert "PHIM_TENANT_QUEUE_SIZE; default: queue_size/2]" in " ".join(out.split())
    assert len(out.splitlines()) <= SERVE_HELP_LINES, out


@pytest.mark.parametrize(
    ("args", "what"),
    [
        (["serve", "--max-batch", "0"], "max_batch"),
        (["serve", "--zenoh-mode", "bogus"], "bogus"),
        (["loadtest", "--vehicles", "0"], "--vehicles"),
        (["loadtest", "--sweep", "1,x"], "--sweep"),
        (["eval", "--data", "waymo:/x", "--scans", "1"], "waymo"),
        (["no-such-command"], "no-such-command"),
    ],
)
def test_usage_errors_exit_2_naming_what_is_wrong(args: list[str], what: str) -> None:
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 2, result.output
    assert what in result.output


def test_client_options_come_from_the_environment_and_json_goes_to_stdout(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    url = f"http://127.0.0.1:{free_port()}"  # nobody listens: every sector is lost to the transport
    monkeypatch.setenv("PHIM_URL", url)
    args = [
        "loadtest",
        "--synthetic",
        "--duration",
        "0.3",
        "--sectors-per-turn",
        "4",
        "--no-progress",
        "--json",
    ]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 1, result.output  # lost to the transport: a failed run
    doc = json.loads(result.stdout)  # stdout holds the JSON and nothing else
    assert doc["config"]["connect"]["url"] == url and doc["sent"] == doc["lost"] > 0
