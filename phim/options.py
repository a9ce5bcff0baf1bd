"""What every command family shares: the --json option and a choice of enum values. Each option is defined
once, here or in its family's module (clients/options.py, model/tools/options.py; the server's flags come
from its Settings); click generates the help, defaults and environment variables from these definitions."""

from __future__ import annotations

import enum
from typing import Any

import click

json_option = click.option(
    "--json", "as_json", is_flag=True, help="Print the result as JSON on stdout (nothing else goes there)."
)


class EnumValue(click.Choice):
    """A choice among an enum's values (click's own enum choice matches member names) -> the member."""

    def __init__(self, enum_type: type[enum.Enum]) -> None:
        super().__init__([str(m.value) for m in enum_type])
        self.enum_type = enum_type

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> enum.Enum:
        raw = value.value if isinstance(value, enum.Enum) else value
        return self.enum_type(super().convert(raw, param, ctx))
