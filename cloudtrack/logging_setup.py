"""One logging set-up for every process: readable lines by default, JSON lines with --log-json; either
way the secrets of any URL in a line are hidden (`cloudtrack.config_files.hide_url_secrets`)."""

from __future__ import annotations

import json
import logging
import sys
import time
from typing import Any

from cloudtrack.config_files import hide_url_secrets

_STANDARD_ATTRS = set(vars(logging.LogRecord("", 0, "", 0, "", (), None))) | {"message", "asctime"}


class JsonLinesFormatter(logging.Formatter):
    """One JSON object per line with time, level, logger, message and any `extra=` fields."""

    def format(self, record: logging.LogRecord) -> str:
        entry: dict[str, Any] = {
            "time": round(record.created, 3),
            "level": record.levelname.lower(),
            "logger": record.name,
            "message": record.getMessage(),
        }
        for key, value in vars(record).items():
            if key not in _STANDARD_ATTRS and not key.startswith("_"):
                entry[key] = value
        if record.exc_info:
            entry["exception"] = self.formatException(record.exc_info)
        return hide_url_secrets(json.dumps(entry, default=str))


class ReadableFormatter(logging.Formatter):
    def __init__(self) -> None:
        super().__init__("%(asctime)s.%(msecs)03d %(levelname)-7s %(name)s: %(message)s", "%H:%M:%S")
        self.converter = time.gmtime

    def format(self, record: logging.LogRecord) -> str:
        return hide_url_secrets(super().format(record))  # a password in a URL never reaches a log


class CurrentStderrHandler(logging.StreamHandler):  # type: ignore[type-arg]
    """Writes to whatever `sys.stderr` is at the time of the record, not the stream it was when set up: a
    process that swaps stderr (a test's capture, a daemon's redirect) and closes the old one would otherwise
    turn every later log line into a slow "Logging error" traceback on the thread that logged."""

    def __init__(self) -> None:
        logging.Handler.__init__(self)

    @property
    def stream(self) -> Any:
        return sys.stderr

    @stream.setter
    def stream(self, _value: Any) -> None:
        pass  # always the current stderr


def setup_logging(level: str = "INFO", json_lines: bool = False) -> None:
    """Configure the root logger once; later calls replace the handler (tests, subcommands)."""
    root = logging.getLogger()
    for handler in list(root.handlers):
        root.removeHandler(handler)
    handler = CurrentStderrHandler()
    handler.setFormatter(JsonLinesFormatter() if json_lines else ReadableFormatter())
    root.addHandler(handler)
    root.setLevel(level.upper())


def add_logging_flags(parser: Any) -> None:
    parser.add_argument("--log-level", default="INFO", help="DEBUG, INFO, WARNING or ERROR (default INFO)")
    parser.add_argument("--log-json", action="store_true", help="log JSON lines instead of readable text")
