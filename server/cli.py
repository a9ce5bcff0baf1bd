"""`phim serve`: its flags are generated from `server.settings.Settings`, the one place every server setting,
its environment variable (PHIM_<NAME>), default and help live. A flag given wins over the environment."""

from __future__ import annotations

import enum
import faulthandler
import logging
import re
import signal
import sys
import types
import typing
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click
from pydantic import ValidationError
from pydantic.fields import FieldInfo

from server.settings import SettingGroup, Settings

if TYPE_CHECKING:
    import uvicorn

ENV_PREFIX = "PHIM_"
HELP_COLUMN = 28  # option names up to this wide keep their help on their line


def _click_type(annotation: Any) -> click.ParamType | type:
    """The click type of a settings field: Literal -> a choice, X | None -> X, endpoint tuples -> a string."""
    origin = typing.get_origin(annotation)
    if origin is typing.Literal:
        return click.Choice([str(a) for a in typing.get_args(annotation)])
    if origin in (types.UnionType, typing.Union):
        (inner,) = [a for a in typing.get_args(annotation) if a is not type(None)]
        return _click_type(inner)
    if origin is tuple:
        return str  # comma-separated, split by Settings
    if annotation is Path:
        return click.Path(path_type=Path)
    return annotation


DESCRIBED_DEFAULT = re.compile(r"(?P<text>.*?) ?\[default: (?P<default>[^\]]*)\](?P<end>\.?)")


def _default_text(name: str, field: FieldInfo) -> str:
    if field.default_factory is not None or field.default is None:
        return ""  # the description says what an unset value means
    value = field.default
    if isinstance(value, tuple):
        value = ",".join(value) or "none"
    elif isinstance(value, bool):
        value = "on" if value else "off"
    elif isinstance(value, enum.Enum):
        value = value.value
    return f"; default: {value}"


def setting_group(field: FieldInfo) -> SettingGroup:
    """The help section a setting's annotation names (`Annotated[int, SettingGroup.LIMITS]`)."""
    (group,) = [m for m in field.metadata if isinstance(m, SettingGroup)]
    return group


def settings_option(name: str, field: FieldInfo) -> click.Option:
    """One flag per setting: --<name> (a bool `x_enabled` or `x` is --x/--no-x), never read from the
    environment by click (pydantic-settings does that), None when not given."""
    flag = name.removesuffix("_enabled").replace("_", "-")
    text, default = str(field.description), _default_text(name, field)
    described = DESCRIBED_DEFAULT.fullmatch(text)  # "... [default: half of queue_size]." for an unset value
    if described and not default:
        text, default = described["text"] + described["end"], f"; default: {described['default']}"
    help_text = f"{text} [env var: {ENV_PREFIX}{name.upper()}{default}]"
    if field.annotation is bool:
        return click.Option([f"--{flag}/--no-{flag}", name], default=None, help=help_text)
    return click.Option([f"--{flag}", name], type=_click_type(field.annotation), default=None, help=help_text)


class GroupedCommand(click.Command):
    """A command whose help lists its options by setting group, one section each (--help last)."""

    def __init__(self, *args: Any, groups: dict[str, SettingGroup], **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.groups = groups  # parameter name -> its section

    def format_options(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        sections: dict[str, list[tuple[str, str]]] = {g.value: [] for g in SettingGroup}
        sections["Other"] = []
        for param in self.get_params(ctx):
            row = param.get_help_record(ctx)
            if row is not None:  # the names padded: one column for every section
                group = self.groups.get(param.name or "")
                sections[group.value if group else "Other"].append((row[0].ljust(HELP_COLUMN), row[1]))
        for title, rows in sections.items():
            if rows:
                with formatter.section(title):
                    formatter.write_dl(rows, col_max=HELP_COLUMN)


def _serve(**flags: Any) -> None:
    try:
        settings = Settings(**{k: v for k, v in flags.items() if v is not None})
    except ValidationError as e:
        raise click.UsageError(str(e)) from None
    run_server(settings)


serve = GroupedCommand(
    "serve",
    callback=_serve,
    params=[settings_option(name, field) for name, field in Settings.model_fields.items()],
    groups={name: setting_group(field) for name, field in Settings.model_fields.items()},
    help="Serve the detector over HTTP and zenoh until SIGTERM/SIGINT (then drain and exit).",
    context_settings={"max_content_width": 110},
)


def run_server(settings: Settings) -> None:
    """Serve until a signal; exit code 1 when the server could not start (the log says why)."""
    import torch
    import uvicorn

    from server.app import create_app
    from server.logs import configure_logging

    configure_logging(settings.log_level, settings.log_format)
    # a native crash (a kernel's segfault) prints every thread's Python stack to stderr (the process's own,
    # not a caller's replacement of sys.stderr) before the process dies: the log says where
    faulthandler.enable(sys.__stderr__)
    if settings.threads:
        torch.set_num_threads(settings.threads)
    logging.getLogger("phim.serve").info(
        "phim serve: %s://%s:%d worker=%s zenoh=%s torch_threads=%d",
        "https" if settings.tls_cert else "http",
        settings.host,
        settings.port,
        settings.worker_id,
        settings.zenoh_enabled,
        torch.get_num_threads(),
    )
    server = uvicorn.Server(uvicorn_config(create_app(settings), settings))
    for sig in (signal.SIGINT, signal.SIGTERM):  # uvicorn re-raises the signal after its graceful shutdown:
        signal.signal(sig, _after_shutdown)  # end with exit code 0 instead of dying by it again
    try:
        server.run()
    except SystemExit:  # uvicorn exits with 3 when the app's start-up (zenoh, the live view, ...) fails
        if server.started:
            raise
    if not server.started:
        raise SystemExit(1)  # startup failed (the log says why)


def uvicorn_config(app: Any, settings: Settings, log_level: str | None = None) -> uvicorn.Config:
    """The uvicorn config `phim serve` runs `app` with (the tests' servers too): its address, TLS, read
    deadlines (`server.http_protocol`) and graceful shutdown."""
    import uvicorn

    from server.http_protocol import with_deadlines

    return uvicorn.Config(
        app,
        host=settings.host,
        port=settings.port,
        log_config=None,
        log_level=log_level or settings.log_level,
        access_log=settings.access_log,
        ws="none",
        http=with_deadlines(
            settings.http_header_timeout_s,
            settings.http_body_timeout_s,
            settings.http_max_header_bytes,
            settings.http_max_headers,
        ),
        ssl_certfile=settings.tls_cert,
        ssl_keyfile=settings.tls_key,
        lifespan="on",
        timeout_graceful_shutdown=max(1, round(settings.drain_timeout_s)),
    )


def _after_shutdown(sig: int, frame: object) -> None:
    logging.getLogger("phim.serve").info("stopped by signal %d after a graceful shutdown", sig)
