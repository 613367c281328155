"""Structured logs (structlog): key=value on a console, one JSON object per line in production.

The service's own loggers are structlog's; the libraries it runs (faust, aiokafka,
uvicorn with its access log, confluent-kafka's Python side) log through the standard
library, whose records go through the same processors and renderer, so in JSON mode every
line on stderr is one JSON object carrying `component`, `level`, `logger` and `timestamp`.
"""

from __future__ import annotations

import logging
import sys

import structlog

# uvicorn's access log record: args are (client address, method, path, HTTP version, status).
_ACCESS_FIELDS = ("client", "method", "path", "http_version", "status")


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
        processors=[*shared, structlog.processors.format_exc_info, renderer],
        wrapper_class=structlog.make_filtering_bound_logger(logging.getLevelName(level.upper())),
        logger_factory=structlog.PrintLoggerFactory(file=sys.stderr),
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
