"""What a long command is doing, on stderr (stdout stays the command's result, e.g. its --json): a line when
each stage starts, with the seconds since the command began, so that nothing runs silently for long; and
the notes that say when a command falls back to other input than the user may expect."""

from __future__ import annotations

import time

import click


class Progress:
    """`progress("loading the model")` -> stderr: `[bench model   2.1 s] loading the model`."""

    def __init__(self, command: str) -> None:
        self.command = command
        self.started = time.monotonic()
        self.said = self.started  # when the last line went out

    def __call__(self, what: str) -> None:
        click.echo(f"[{self.command} {time.monotonic() - self.started:5.1f} s] {what}", err=True)
        self.said = time.monotonic()

    def count(self, what: str, done: int, total: int, every_s: float = 5.0) -> None:
        """`done` of `total` `what` so far: a line every `every_s` seconds at most, and at the end."""
        if done == total or time.monotonic() - self.said >= every_s:
            self(f"{done} of {total} {what}")


def note(command: str, message: str) -> None:
    """A fallback or a substitution the user should know of (stderr): `phim bench refiner: note: ...`."""
    click.echo(f"phim {command}: note: {message}", err=True)
