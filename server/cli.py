"""The `phim` command. Subcommands grow with each part of the project."""

from __future__ import annotations

import typer

from model.cli import bench_app, model_app

app = typer.Typer(help="PHiM streaming LiDAR detector.", no_args_is_help=True, add_completion=False)
app.add_typer(model_app, name="model")
app.add_typer(bench_app, name="bench")


if __name__ == "__main__":
    app()
