"""Logging on stderr: readable lines on a terminal, one JSON object per line otherwise.

``REGTREE_LOG_FORMAT`` (setting ``log_format``) chooses: ``text``, ``json``, or ``auto`` (the
default): text when stderr is a terminal, JSON when it is not (a file, a pipe, a container's
log collector). ``extra={...}`` fields become keys of the JSON object, ``key=value`` pairs
after a text line's message.
"""

from __future__ import annotations

import json
import logging
import sys
from datetime import UTC, datetime
from typing import Any, Literal, TextIO

LogFormat = Literal["auto", "json", "text"]

_RESERVED = set(logging.LogRecord("", 0, "", 0, "", (), None).__dict__) | {"message", "asctime"}


def _extras(record: logging.LogRecord) -> dict[str, Any]:
    return {
        key: value
        for key, value in record.__dict__.items()
        if key not in _RESERVED and not key.startswith("_")
    }


class JsonFormatter(logging.Formatter):
    """Format a record as a JSON line; ``extra={...}`` fields become top-level keys."""

    def format(self, record: logging.LogRecord) -> str:
        doc: dict[str, Any] = {
            "ts": datetime.fromtimestamp(record.created, UTC).isoformat(timespec="milliseconds"),
            "level": record.levelname.lower(),
            "logger": record.name,
            "msg": record.getMessage(),
            "pid": record.process,
        }
        doc.update(_extras(record))
        if record.exc_info:
            doc["exc"] = self.formatException(record.exc_info)
        return json.dumps(doc, default=str)


class TextFormatter(logging.Formatter):
    """``12:03:04 WARNING regtree.worker: lease lost job_id=7``: local time, level, logger,
    message, then the ``extra={...}`` fields as ``key=value``."""

    def format(self, record: logging.LogRecord) -> str:
        when = datetime.fromtimestamp(record.created).strftime("%H:%M:%S")
        line = f"{when} {record.levelname:<7} {record.name}: {record.getMessage()}"
        pairs = [f"{key}={_value(value)}" for key, value in _extras(record).items()]
        if pairs:
            line += "  " + " ".join(pairs)
        if record.exc_info:
            line += "\n" + self.formatException(record.exc_info)
        return line


def _value(value: Any) -> str:
    text = value if isinstance(value, str) else json.dumps(value, default=str)
    return json.dumps(text) if not text or any(c in text for c in ' ="') else text


def resolve_format(fmt: str, stream: TextIO) -> Literal["json", "text"]:
    """``json`` or ``text`` for a configured ``fmt`` (``auto``: text on a terminal)."""
    if fmt in ("json", "text"):
        return fmt  # type: ignore[return-value]
    if fmt != "auto":
        raise ValueError(f"log format must be auto, json or text; got {fmt!r}")
    try:
        return "text" if stream.isatty() else "json"
    except (AttributeError, ValueError):  # closed or not a real stream
        return "json"


def configure_logging(level: str = "INFO", fmt: str = "auto", *, stream: TextIO | None = None
                      ) -> None:  # fmt: skip
    """Send the root, uvicorn and regtree loggers to ``stream`` (stderr), as text or JSON
    lines (see the module's doc)."""
    stream = stream if stream is not None else sys.stderr
    handler = logging.StreamHandler(stream)
    chosen = resolve_format(fmt, stream)
    handler.setFormatter(JsonFormatter() if chosen == "json" else TextFormatter())
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level.upper())
    for name in ("uvicorn", "uvicorn.error", "uvicorn.access"):
        logger = logging.getLogger(name)
        logger.handlers[:] = []
        logger.propagate = True
    # Alembic announces every plugin it loads at INFO.
    logging.getLogger("alembic.runtime.plugins").setLevel(logging.WARNING)
    # Request lines are logged by our own middleware, with timings and request ids.
    logging.getLogger("uvicorn.access").disabled = True
