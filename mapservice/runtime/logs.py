"""Structured logs (structlog): key=value on a console, one JSON object per line in production.

The service's own loggers are structlog's; the libraries it runs (faust, aiokafka,
uvicorn with its access log, confluent-kafka's Python side) log through the standard
library, whose records go through the same processors and renderer, so in JSON mode every
line on stderr is one JSON object carrying `component`, `level`, `logger` and `timestamp`.

No line carries a secret sent in a URL: whatever a line holds (a uvicorn access record's
path, an HTTP client's request line, an exception's text), a query parameter whose name
says it is a secret (password, token, key, ...) has its value replaced by `[redacted]`.
Clients put credentials there (ClickHouse's `?password=`), so every logger is covered,
not a list of the ones known to print URLs.
"""

from __future__ import annotations

import logging
import re
import sys
from typing import TextIO, cast
from urllib.parse import unquote_plus

import structlog

# uvicorn's access log record: args are (client address, method, path, HTTP version, status).
_ACCESS_FIELDS = ("client", "method", "path", "http_version", "status")


# name=value in a query string (after ? or &), the name and value as they were sent.
_QUERY_PAIR = re.compile(r"([?&])([^=&#?\s\"']+)=([^&#\s\"']*)")
# A parameter whose name (decoded, any case) holds one of these carries a secret.
_SECRET_NAME_PARTS = ("pass", "pwd", "secret", "token", "key", "auth", "credential", "sig")
REDACTED = "[redacted]"


def redact_query_secrets(text: str) -> str:
    """`text` with the value of every secret-named query parameter replaced by REDACTED."""
    if "=" not in text:
        return text

    def redact(pair: re.Match[str]) -> str:
        name = unquote_plus(pair[2]).lower()
        if any(part in name for part in _SECRET_NAME_PARTS):
            return f"{pair[1]}{pair[2]}={REDACTED}"
        return pair[0]

    return _QUERY_PAIR.sub(redact, text)


def _redacted(value):
    if isinstance(value, str):
        return redact_query_secrets(value)
    if isinstance(value, tuple | list):
        return type(value)(_redacted(item) for item in value)
    if isinstance(value, dict):
        return {key: _redacted(item) for key, item in value.items()}
    return value


def _redact_secrets(_logger, _name: str, event_dict: dict) -> dict:
    """Every value of the line (its message, fields and formatted exception) redacted."""
    for key, value in event_dict.items():
        if key != "_record":
            event_dict[key] = _redacted(value)
    return event_dict


def _access_fields(_logger, _name: str, event_dict: dict) -> dict:
    """Turns a uvicorn access record's arguments into fields of their own (other records'
    arguments are already in their message)."""
    args = event_dict.pop("positional_args", None)
    record = event_dict.get("_record")
    if (
        record is not None
        and record.name == "uvicorn.access"
        and isinstance(args, tuple)
        and len(args) == len(_ACCESS_FIELDS)
    ):
        event_dict.update(zip(_ACCESS_FIELDS, args))
        event_dict["event"] = "request"
    return event_dict


class _CurrentStderr:
    """sys.stderr as it is at each write: loggers are cached on first use, and one cached
    while stderr was redirected (a test's capture, a CLI's progress display) must not keep
    writing to a stream that has since been closed."""

    def write(self, text: str) -> int:
        return sys.stderr.write(text)

    def flush(self) -> None:
        sys.stderr.flush()


def configure(level: str = "INFO", fmt: str = "console", component: str = "mapservice") -> None:
    renderer = (
        structlog.processors.JSONRenderer()
        if fmt == "json"
        else structlog.dev.ConsoleRenderer(colors=sys.stderr.isatty())
    )

    def add_component(_logger, _name: str, event_dict: dict) -> dict:
        # A processor, not only a context variable: threads (paho's, executors, uvicorn
        # in a thread) start with an empty context.
        event_dict.setdefault("component", component)
        return event_dict

    shared = [
        structlog.contextvars.merge_contextvars,
        add_component,
        structlog.processors.add_log_level,
        structlog.processors.TimeStamper(fmt="iso", utc=True),
    ]
    structlog.configure(
        processors=[*shared, structlog.processors.format_exc_info, _redact_secrets, renderer],
        wrapper_class=structlog.make_filtering_bound_logger(logging.getLevelName(level.upper())),
        logger_factory=structlog.PrintLoggerFactory(file=cast(TextIO, _CurrentStderr())),
        cache_logger_on_first_use=True,
    )
    structlog.contextvars.bind_contextvars(component=component)
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(
        structlog.stdlib.ProcessorFormatter(
            foreign_pre_chain=[
                *shared,
                structlog.stdlib.add_logger_name,
                _access_fields,
                structlog.processors.format_exc_info,
                _redact_secrets,
            ],
            processors=[structlog.stdlib.ProcessorFormatter.remove_processors_meta, renderer],
            pass_foreign_args=True,
        )
    )
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level.upper())
    # Libraries that install handlers of their own (uvicorn does) log through the root's.
    for name in ("uvicorn", "uvicorn.error", "uvicorn.access", "faust", "aiokafka", "mode"):
        lib = logging.getLogger(name)
        lib.handlers.clear()
        lib.propagate = True
