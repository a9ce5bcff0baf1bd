"""The server's logs on stderr: text lines, or a JSON object per line for log collectors (--log-format json).

uvicorn runs with log_config=None, so its loggers propagate to the root logger: one handler formats the
server's records and uvicorn's alike.
"""

from __future__ import annotations

import json
import logging
import sys
from datetime import UTC, datetime
from typing import Literal

TEXT_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


class JsonFormatter(logging.Formatter):
    """A record -> {"time", "level", "logger", "message"[, "exception"][, "stack"]} on one line.

    The standard library's Formatter rather than python-json-logger: four fields and the exception text need
    no dependency, and json.dumps escapes newlines and non-ASCII text (a traceback stays on its line)."""

    def format(self, record: logging.LogRecord) -> str:
        entry = {
            "time": datetime.fromtimestamp(record.created, UTC).isoformat(timespec="milliseconds"),
            "level": record.levelname,
            "logger": record.name,
            "message": record.getMessage(),
        }
        if record.exc_info:
            entry["exception"] = self.formatException(record.exc_info)
        if record.stack_info:
            entry["stack"] = self.formatStack(record.stack_info)
        return json.dumps(entry)


def configure_logging(level: str, log_format: Literal["text", "json"]) -> None:
    """Every logger (uvicorn's too) to stderr at `level`, in text or JSON lines; warnings.warn as well."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(JsonFormatter() if log_format == "json" else logging.Formatter(TEXT_FORMAT))
    logging.basicConfig(level=level.upper(), handlers=[handler], force=True)
    logging.captureWarnings(True)
