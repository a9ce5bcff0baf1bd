"""The `phim` command: a table of subcommands, each imported only when it runs or shows its own help.

`phim --help` and `phim --version` import nothing of the project and no third-party package but click, so
they answer at once; `phim loadtest --help` imports the load tester's options (no torch, no zenoh, no
FastAPI). Each entry names where its command lives as "module:function" (click's documented lazy-loading
pattern): a click command whose options come from one place (`phim.options` and the families' option
modules; `phim serve`'s from the server's Settings).
Exit codes: 0 success, 1 the run failed or broke a threshold, 2 usage.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass

import click

from phim.process import tune_malloc


@dataclass(frozen=True)
class Entry:
    target: str  # "module:function"
    help: str  # the one line `phim --help` shows


@dataclass(frozen=True)
class Group:
    help: str
    commands: dict[str, Entry]


COMMANDS: dict[str, Entry | Group] = {
    "serve": Entry("server.cli:serve", "Serve the detector over HTTP and zenoh until SIGTERM/SIGINT."),
    "loadtest": Entry(
        "clients.cli:loadtest", "Simulated vehicles streaming to a server: throughput, latency."
    ),
    "router": Entry("server.router_cli:router_cmd", "A zenoh router where workers and vehicles meet."),
    "replay": Entry("clients.cli:replay", "Stream a recorded drive to a server and write its detections."),
    "sim": Entry("lidar.sim.cli:sim_cmd", "Simulate one LiDAR turn through a random street scene."),
    "train": Entry("model.train.cli:train_cmd", "Train a model (streaming, as the paper trains)."),
    "train-refiner": Entry(
        "model.train.refine_cli:train_refiner_cmd", "Train the box refiner on a trained, frozen detector."
    ),
    "eval": Entry("model.eval.cli:eval_cmd", "Waymo-style AP/APH per class and level, per buffer fill."),
    "diagnose": Entry("model.eval.cli:diagnose_cmd", "Each part of the predicted boxes against the truth."),
    "auth": Group(
        "Access tokens of `phim serve --auth-tokens` (docs/security.md).",
        {"add-token": Entry("server.auth_cli:add_token_cmd", "Make a token for a stream-ID prefix.")},
    ),
    "model": Group(
        "Inspect model configs.",
        {"info": Entry("model.tools.cli:info", "Parameter count and measured GFLOPs of a config.")},
    ),
    "bench": Group(
        "Benchmarks (a table, or JSON with --json, at the end).",
        {
            "model": Entry("model.tools.cli:bench_model_cmd", "Per-sector latency, sector buffer loaded."),
            "engines": Entry(
                "model.tools.cli:bench_engines_cmd", "Engines against each other in one process: ratios."
            ),
            "refiner": Entry("model.tools.cli:bench_refiner_cmd", "The box refiner's share of a step."),
            "ops": Entry("model.tools.cli:bench_ops_cmd", "Torch ops and host syncs of one streaming step."),
            "sim": Entry("lidar.sim.cli:bench_sim_cmd", "Simulator throughput, single-threaded."),
            "server": Entry("clients.bench.server:bench_server_cmd", "The server's own overhead per sector."),
            "fleet": Entry(
                "clients.bench.fleet:bench_fleet_cmd", "Throughput of 1..N workers behind a router."
            ),
        },
    ),
}


def load(entry: Entry) -> click.Command:
    """Import the command's module and return its click command."""
    module, name = entry.target.split(":")
    command = getattr(importlib.import_module(module), name)
    if not isinstance(command, click.Command):
        raise TypeError(f"{entry.target} is not a click command")
    return command


class LazyGroup(click.Group):
    """A group whose commands are imported when resolved; its help lists them from the table."""

    def __init__(self, table: dict[str, Entry | Group], **kwargs: object) -> None:
        super().__init__(**kwargs)  # type: ignore[arg-type]
        self.table = table

    def list_commands(self, ctx: click.Context) -> list[str]:
        return list(self.table)

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        entry = self.table.get(cmd_name)
        if isinstance(entry, Group):
            return LazyGroup(entry.commands, name=cmd_name, help=entry.help, no_args_is_help=True)
        return None if entry is None else load(entry)

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        rows = [(name, e.help) for name, e in self.table.items()]
        with formatter.section("Commands"):
            formatter.write_dl(rows)


@click.group(
    "phim",
    cls=LazyGroup,
    table=COMMANDS,
    no_args_is_help=True,
    context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 110},
)
@click.version_option(package_name="phim", prog_name="phim")
def main() -> None:
    """PHiM streaming LiDAR detector: serve it, load-test it, train and evaluate it."""
    tune_malloc()  # sector-sized buffers stay on the heap (see phim.process)
